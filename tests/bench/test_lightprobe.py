"""bench/lightprobe.py: the fitted room's light against Mitsuba's irradiance meters. Its two measures, checked
where the answer is known in closed form: Mitsuba's meter under a rectangular lamp (Howell's configuration
factor), and the gather in a closed box of one radiance."""

from __future__ import annotations

import numpy as np
import pytest

from bench.lightprobe import OFFSET_M, emitter_irradiance, gather, meters, unseen_ceiling
from pipeline.trace.lightfit import RoomLights, closing_box
from tests.pipeline.shapes import parallel_rectangle_factor

UP = np.array([0.0, 0.0, 1.0])


def test_meter_under_a_lamp_reads_its_irradiance_and_nothing_with_the_lamp_hidden():
    """A 1 x 1 m lamp 1 m over the meter, facing it, radiance (1, 2, 3): pi L F (F: four corner factors of
    0.5 x 0.5 m at 1 m less the meter's offset) to 3 % (Monte Carlo); with the emitters hidden (the indirect
    light) the empty scene sends nothing."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is a test-only dependency (pip install mitsuba)")
    from bench.lightsuite import _mi

    mi = _mi()
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = [0.5, 0, 0], [0, -0.5, 0], [0, 0, -1], [0, 0, 1.0]   # faces down
    L = np.array([1.0, 2.0, 3.0])
    scene = mi.load_dict({"type": "scene", "lamp": {
        "type": "rectangle", "to_world": mi.ScalarTransform4f(M.tolist()),
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": L.tolist()}}}})
    p, n = np.zeros((1, 3)), np.tile(UP, (1, 1))
    want = np.pi * L * 4 * parallel_rectangle_factor(0.5, 0.5, 1.0 - OFFSET_M)
    got = meters(scene, p, n, spp=65536, indirect=False)[0]
    assert np.all(np.abs(got / want - 1) < 0.03), (got, want)
    assert np.all(meters(scene, p, n, spp=1024, indirect=True) == 0)


def _room_lights(box_radiance: float, floor_radiance: float) -> RoomLights:
    """A 4 x 4 x 2.5 m closing box of one radiance around a floor quad (the scan's mesh: one face up, wound
    counter-clockwise seen from above) of another."""
    V, F, _, _ = closing_box(np.array([[-2, -2, 0], [2, 2, 2.5]], float), UP, 0.5, margin=0.0)
    floor = np.array([[-1.9, -1.9, 0.5], [1.9, -1.9, 0.5], [1.9, 1.9, 0.5], [-1.9, 1.9, 0.5]])
    verts = np.concatenate([floor, V]).astype(np.float32)
    faces = np.concatenate([[[0, 1, 2], [0, 2, 3]], F + 4]).astype(np.int32)
    rad = np.concatenate([np.full((4, 3), floor_radiance), np.full((len(V), 3), box_radiance)]).astype(np.float32)
    return RoomLights(vertices=verts, faces=faces, radiance=rad, light_tri=np.zeros(len(faces), bool),
                      num_mesh_vertices=4, num_mesh_tris=2, summary={"box_cells": len(V) // 4})


def test_gather_sorts_the_light_by_what_sends_it():
    """Above the floor quad facing up: the box's radiance x pi, all of it from the box. Facing down: the floor's
    seen side x pi. Under it facing up: its unseen side only (the fit replaces that light)."""
    rl = _room_lights(0.3, 0.1)
    P = np.array([[0.0, 0.0, 1.5], [0.0, 0.0, 0.6], [0.0, 0.0, 0.3]])
    N = np.array([UP, -UP, UP])
    g = gather(rl, P, N, rays=256, rng=np.random.default_rng(0))
    np.testing.assert_allclose(g["box"][0], np.pi * 0.3, rtol=1e-5)
    assert g["box_share"][0] == 1 and np.all(g["mesh"][0] == 0)
    np.testing.assert_allclose(g["mesh"][1], np.pi * 0.1, rtol=0.02)     # the quad does not quite reach the walls
    assert g["box_share"][1] < 0.05 and np.all(g["unseen_side"][1] == 0)
    np.testing.assert_allclose(g["unseen_side"][2], np.pi * 0.1, rtol=0.02)
    assert np.all(g["mesh"][2] == 0)


def test_unseen_ceiling_is_the_box_top():
    rl = _room_lights(0.3, 0.1)
    cen, rad = unseen_ceiling(rl, UP, floor=0.0)
    assert len(cen) == 64 and np.allclose(cen[:, 2], 2.5) and np.allclose(rad, 0.3)


def test_emitter_irradiance_under_a_lamp_is_howells_factor_and_a_shade_stops_it():
    """A 1 x 1 m lamp of radiance (1, 2, 3) 1 m over a point, facing it (wound to face down), and a second,
    dimmer one off to the side: pi L F from the first plus the second's share (F: Howell's four corner factors;
    the second's by the same formula, as the difference of two rectangles), to 3 % (Monte Carlo). Both sides
    emit, as the tracer samples them: the lamp wound facing up lights the point the same. A shade between
    the point and the lamps leaves nothing."""
    h = 1.0                                   # the lamps' height over the point

    def room(up_wound: bool, shade: bool) -> RoomLights:
        quad = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
        lamp = np.c_[quad, np.full(4, h)]
        lamp2 = np.c_[quad * [0.5, 0.5] + [1.25, 0.0], np.full(4, h)]       # 0.5 x 0.5 m at x 1.0-1.5
        sh = np.c_[quad * 4, np.full(4, 0.5)]
        V = np.concatenate([lamp, lamp2] + ([sh] if shade else [])).astype(np.float32)
        down, up = [[0, 2, 1], [0, 3, 2]], [[0, 1, 2], [0, 2, 3]]
        w = up if up_wound else down
        F = np.array(w + [[a + 4 for a in t] for t in w] + ([[a + 8 for a in t] for t in down] if shade else []))
        R = np.concatenate([np.tile([1.0, 2.0, 3.0], (4, 1)), np.tile([0.5, 0.5, 0.5], (4, 1))]
                           + ([np.zeros((4, 3))] if shade else [])).astype(np.float32)
        lt = np.array([True] * 4 + [False] * (2 if shade else 0))
        return RoomLights(vertices=V, faces=F.astype(np.int32), radiance=R, light_tri=lt, num_mesh_vertices=0,
                          num_mesh_tris=0, summary={})

    f = parallel_rectangle_factor
    second = 2 * (f(1.5, 0.25, h) - f(1.0, 0.25, h))     # x 1.0-1.5, y -0.25-0.25: two strips from the axis
    want = np.pi * (np.array([1.0, 2.0, 3.0]) * 4 * f(0.5, 0.5, h) + 0.5 * second)
    p, n = np.zeros((1, 3)), UP[None]
    for up_wound in (False, True):
        got = emitter_irradiance(room(up_wound, False), p, n, 65536, np.random.default_rng(1))[0]
        assert np.all(np.abs(got / want - 1) < 0.03), (up_wound, got, want)
    assert np.all(emitter_irradiance(room(False, True), p, n, 4096, np.random.default_rng(1)) == 0)


def test_a_tuning_room_without_out_is_refused(tmp_path, capsys):
    """bench.lightprobe on the tuning-only room without --out would overwrite the results the README links (the
    six rooms'): refused with the fix before anything runs."""
    from bench.lightprobe import main

    with pytest.raises(SystemExit) as e:
        main(["--suite", str(tmp_path / "s"), "--work", str(tmp_path / "w"), "--rooms", "spot, coloured_dev"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "coloured_dev is for tuning only" in err and "give --out" in err
