"""The fitted room lights against an independent renderer: a tiny version of the Mitsuba 3 light suite
(bench/lightsuite.py) run through the real CLI (bench/lighting.py's runner: ingest to composite, the
objects at their true poses).

The suite's rooms are rendered here by Mitsuba (a test-only dependency) at 160x120, a few samples per
pixel; what is checked is what the tiny version can tell apart from noise: where the main light is and
how bright the objects come out, not the PSNR targets of the full benchmark.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.bench.suite import need_suite_renderer

pytestmark = pytest.mark.slow

ROOMS = ("ceiling", "window")


@pytest.fixture(scope="module")
def suite(tmp_path_factory):
    need_suite_renderer()
    from bench.lightsuite import TINY, build_suite
    out = tmp_path_factory.mktemp("lightsuite")
    build_suite(out, ROOMS, **{**TINY, "frames": 4})
    return out


def test_tiny_suite_is_complete_and_ingests(suite, tmp_path):
    import cv2

    from bench.lightsuite import TINY, build_suite
    from pipeline.config import build_config
    from pipeline.ingest import ingest_scan

    for r in ROOMS:
        root = suite / r
        assert (root / "done.json").is_file()
        m = cv2.imread(str(root / "truth" / "frame-000001.mask.png"), cv2.IMREAD_UNCHANGED)
        assert m.shape == (120, 160) and set(np.unique(m)) == {0, 1, 2, 3}
        d = cv2.imread(str(root / "scan" / "frames" / "frame-000000.depth.png"), cv2.IMREAD_UNCHANGED)
        assert d.dtype == np.uint16 and d.min() > 0
        assert [o["obj_id"] for o in json.loads((root / "truth" / "objects.json").read_text())] == [1, 5, 9]
    again = build_suite(suite, ROOMS[:1], **{**TINY, "frames": 4})     # cached: read back, not rendered
    assert again[ROOMS[0]]["exposure"] == json.loads((suite / ROOMS[0] / "truth" / "room.json").read_text())["exposure"]
    cfg = build_config({"scan": {"paths": [str(suite / ROOMS[0] / "scan")], "format": "7scenes"}})
    sc = ingest_scan(suite / ROOMS[0] / "scan", "room", tmp_path / "run" / "ingest" / "room", cfg)
    assert sc.num_frames == 4 and np.allclose(sc.up_w, [0, 0, 1])


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("lighting")


@pytest.fixture(scope="module")
def results(suite, work):
    from bench.lighting import run_room

    return {r: run_room(suite / r, work / r, ("scan", "fit")) for r in ROOMS}


@pytest.mark.parametrize("room", ROOMS)
def test_fit_finds_the_main_light(results, room):
    lights = results[room]["variants"]["fit"]["lights"]
    assert lights, "the suite's room has no main emitter"
    best = max(lights, key=lambda e: e["power_ratio"])
    # some of the recovered power sits within LIGHT_RADIUS of a true emitter, centred near it
    assert best["power_ratio"] > 0.25, lights
    assert best["position_error_m"] is not None and best["position_error_m"] < 0.8, lights


@pytest.mark.parametrize("room", ROOMS)
def test_fit_lights_the_objects_within_a_factor_of_the_truth(results, room):
    """A coarse check at this size (160x120, noisy photos, objects of ~150 px): brightness within a factor
    of 2 of the truth per channel, which a wrong light scale or a lost light fails (the published lights
    come out 1.4-2.9x too bright on the full suite). Accuracy is bench/lighting.py's to measure."""
    v = results[room]["variants"]
    fit = np.asarray(v["fit"]["brightness"])
    assert v["fit"]["frames_scored"] == 4
    assert np.all(np.isfinite(fit))
    assert np.all(np.abs(np.log(fit)) < np.log(2.0)), fit.tolist()


def test_fit_summary_is_recorded(results, suite):
    v = results["ceiling"]["variants"]["fit"]["fit"]
    assert v["fitted"] and v["note"] == ""
    json.dumps(results)   # JSON-able


def test_results_name_the_render_they_were_measured_on(results, suite, tmp_path):
    """Each room's results carry a fingerprint of its rendered images: the same bytes give the same
    fingerprint, one changed byte in one photo another (a regenerated suite is another render)."""
    import shutil

    from bench.lighting import render_fingerprint

    got = {r: results[r]["render"] for r in ROOMS}
    assert len(set(got.values())) == len(ROOMS)
    copy = tmp_path / "room"
    shutil.copytree(suite / ROOMS[0], copy)
    assert render_fingerprint(copy) == got[ROOMS[0]]
    photo = copy / "scan" / "frames" / "frame-000002.color.png"
    raw = bytearray(photo.read_bytes())
    raw[-20] ^= 1
    photo.write_bytes(bytes(raw))
    assert render_fingerprint(copy) != got[ROOMS[0]]


def test_a_variant_at_another_seed_runs_on_its_own(results, suite, work):
    """bench.lighting --seeds: the fit variant again at run seed 1, on the same base (ingest to raster at seed 0),
    in its own folder, with the seed in its config; the seed draws the fit's points and samples, so its figures
    are another draw, and seed 0's folder and figures stay as they were."""
    from bench.lighting import run_room, seeds_summary
    from pipeline.cli import CONFIG_NAME
    from pipeline.config import load_config

    room = ROOMS[0]
    marker = work / room / "fit" / "bench_variant.json"
    before = marker.read_bytes()
    got = run_room(suite / room, work / room, ("fit",), seed=1)
    assert got["seed"] == 1 and results[room]["seed"] == 0
    assert load_config(work / room / "fit-s1" / CONFIG_NAME).run.seed == 1
    assert load_config(work / room / "fit" / CONFIG_NAME).run.seed == 0
    assert marker.read_bytes() == before
    b0, b1 = results[room]["variants"]["fit"]["brightness"], got["variants"]["fit"]["brightness"]
    assert b0 != b1, "the same figures at seed 1: the seed did not reach the fit"
    summary = seeds_summary({0: {room: results[room]}, 1: {room: got}})
    assert summary["rooms"][room]["brightness"] == [[round(x, 3) for x in b0], [round(x, 3) for x in b1]]
