"""What the tests that render the light suite need: Mitsuba 3 and the LM-O models, or a skip saying which is missing."""

from __future__ import annotations

import pytest


def need_suite_renderer() -> None:
    """Skip the calling test unless Mitsuba 3 (a test-only dependency) and the LM-O models are there."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is a test-only dependency (pip install mitsuba)")
    from bench.lightsuite import LMO

    if not LMO.is_dir():
        pytest.skip(f"the LM-O models are not at {LMO} (see ../shared/data/README.md)")
