"""Atomic, deterministic outputs."""

from __future__ import annotations

import numpy as np

from pipeline.io import (atomic_save_npz, atomic_write_image, atomic_write_json, load_npz, read_json,
                         remove_stale_temps)


def test_json_is_deterministic_and_round_trips(tmp_path):
    obj = {"b": np.arange(3), "a": np.float32(0.5), "c": {"z": 1, "y": [1, 2]}}
    atomic_write_json(tmp_path / "x.json", obj)
    atomic_write_json(tmp_path / "y.json", dict(reversed(list(obj.items()))))
    assert (tmp_path / "x.json").read_bytes() == (tmp_path / "y.json").read_bytes()
    assert read_json(tmp_path / "x.json") == {"a": 0.5, "b": [0, 1, 2], "c": {"y": [1, 2], "z": 1}}


def test_npz_round_trip_and_same_bytes(tmp_path):
    a = np.random.default_rng(0).random((4, 5)).astype(np.float32)
    atomic_save_npz(tmp_path / "a.npz", x=a, k=np.eye(3))
    atomic_save_npz(tmp_path / "b.npz", k=np.eye(3), x=a)
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    d = load_npz(tmp_path / "a.npz")
    np.testing.assert_array_equal(d["x"], a)


def test_png_round_trip_rgb_and_uint16(tmp_path):
    import cv2

    rgb = np.zeros((4, 6, 3), np.uint8)
    rgb[..., 0] = 255  # red
    atomic_write_image(tmp_path / "c.png", rgb)
    back = cv2.imread(str(tmp_path / "c.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    np.testing.assert_array_equal(back, rgb)
    depth = (np.arange(24, dtype=np.uint16) * 1000).reshape(4, 6)
    atomic_write_image(tmp_path / "d.png", depth)
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED), depth)


def test_stale_temps_are_removed_and_targets_kept(tmp_path):
    atomic_write_json(tmp_path / "keep.json", {"a": 1})
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "x.npz.tmp-123").write_bytes(b"partial")
    assert remove_stale_temps(tmp_path) == 1
    assert (tmp_path / "keep.json").is_file()
    assert not list(tmp_path.rglob("*.tmp-*"))
