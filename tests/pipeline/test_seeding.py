"""Generators depend on names, not on call order."""

from __future__ import annotations

import pytest

from pipeline.seeding import item_rng


def test_same_name_same_stream_any_order():
    a = [item_rng(5, "simulate", k).random() for k in ("x", "y", "z")]
    b = [item_rng(5, "simulate", k).random() for k in ("z", "y", "x")][::-1]
    assert a == b


def test_different_names_seeds_and_stages_differ():
    base = item_rng(5, "simulate", "x").random()
    assert item_rng(5, "simulate", "y").random() != base
    assert item_rng(6, "simulate", "x").random() != base
    assert item_rng(5, "raster", "x").random() != base
    assert item_rng(0, "simulate", "x").random() == item_rng(0, "simulate", "x").random()


def test_negative_seed_is_refused():
    with pytest.raises(ValueError):
        item_rng(-1, "a")
