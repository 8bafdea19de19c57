"""bench/cycles.py, the Blender Cycles peer: its conversions (camera, area lights) checked against references
that do not come from it, and the whole benchmark on the tiny Mitsuba suite.

bpy (Blender as a Python module) is a bench-only dependency that ``bin/test`` does not install (about
500 MB): every test that renders is skipped without it (``.venv/bin/pip install --no-deps bpy==4.2.0``).
"""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from tests.bench.suite import need_suite_renderer

needs_bpy = pytest.mark.skipif(importlib.util.find_spec("bpy") is None,
                               reason="bpy is a bench-only dependency: .venv/bin/pip install --no-deps bpy==4.2.0")


def test_blender_camera_puts_the_principal_point_where_opencv_has_it():
    from bench.cycles import blender_camera

    K = np.array([[525.0, 0.0, 319.5], [0.0, 525.0, 239.5], [0.0, 0.0, 1.0]])
    c = blender_camera(K, 640, 480)
    assert c["lens"] == pytest.approx(525.0 * 36.0 / 640)
    assert c["shift_x"] == pytest.approx(0.0) and c["shift_y"] == pytest.approx(0.0)    # centre of a 640 x 480 image
    K2 = K.copy()
    K2[0, 2], K2[1, 2] = 300.0, 250.0          # principal point left of and below the centre
    c2 = blender_camera(K2, 640, 480)
    assert c2["shift_x"] == pytest.approx(19.5 / 640) and c2["shift_y"] == pytest.approx(10.5 / 640)
    with pytest.raises(ValueError, match="square pixels"):
        blender_camera(np.diag([525.0, 500.0, 1.0]), 640, 480)


def test_light_frame_emits_along_the_normal():
    from bench.cycles import light_frame

    corners = np.array([[0.0, 0.0, 2.0], [0.0, 0.5, 2.0], [1.0, 0.5, 2.0], [1.0, 0.0, 2.0]])
    for normal in ([0.0, 0.0, -1.0], [0.0, 0.0, 1.0]):
        T, sx, sy = light_frame(corners, np.array(normal))
        R = T[:3, :3]
        assert np.allclose(R.T @ R, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        assert np.allclose(-R[:, 2], normal)                 # Blender's area lights emit along local -Z
        assert np.allclose(T[:3, 3], [0.5, 0.25, 2.0])
        assert (sx, sy) == pytest.approx((0.5, 1.0))


@pytest.mark.slow
@needs_bpy
def test_area_light_radiance_under_a_wide_light(tmp_path):
    """A white plane (principled, base colour 1: Blender's is energy conserving, its directional albedo ~1)
    0.5 m under a 200 m square light of radiance L sees L over nearly the whole hemisphere, so it reflects ~L:
    the power :func:`bench.cycles._build` gives Cycles (pi A L) is right, not pi times off."""
    from bench.cycles import render_cycles

    L = np.array([0.5, 0.25, 1.0])
    plane_v = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]], np.float32)
    plane_f = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    far_v = np.array([[50.0, 50.0, -5.0], [51.0, 50.0, -5.0], [50.0, 51.0, -5.0]], np.float32)
    arrays = {"room_v": far_v, "room_f": np.array([[0, 1, 2]], np.int32),
              "room_albedo": np.full((3, 3), 0.5, np.float32),
              "obj0_v": plane_v, "obj0_f": plane_f, "obj0_n": np.tile([0.0, 0.0, 1.0], (4, 1)).astype(np.float32),
              "obj0_albedo": np.ones((4, 3), np.float32)}
    T_c2w = np.eye(4)
    T_c2w[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])   # looking down -z
    T_c2w[:3, 3] = [0.0, 0.0, 0.25]
    meta = {"objects": 1,
            "lights": [{"corners": [[-100, -100, 0.5], [-100, 100, 0.5], [100, 100, 0.5], [100, -100, 0.5]],
                        "normal": [0.0, 0.0, -1.0], "radiance": L.tolist()}],
            "frames": [{"frame": 0, "K": [[16.0, 0, 15.5], [0, 16.0, 11.5], [0, 0, 1]], "T_c2w": T_c2w.tolist(),
                        "width": 32, "height": 24, "border": [8, 6, 24, 18], "exposure": 1.0}]}
    got = render_cycles(arrays, meta, tmp_path / "b", 64)[0]
    c = got["combined"]
    assert c.shape == (12, 16, 4) and np.allclose(c[..., 3], 1.0)
    assert np.allclose(c[..., :3].reshape(-1, 3).mean(axis=0), L, rtol=0.05)


@pytest.mark.slow
@needs_bpy
def test_objects_land_where_opencv_projects_them(tmp_path):
    """A small square at a known point, seen by a camera whose principal point is far off the image centre and
    whose pose is turned: the centroid of Cycles' coverage is the OpenCV projection of the square's centre."""
    from bench.cycles import render_cycles

    c, h = np.array([0.3, -0.2, 2.0]), 0.05                 # world centre, half-size (metres), facing -z
    sq = (c + np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]])).astype(np.float32)
    far_v = np.array([[50.0, 50.0, 50.0], [51.0, 50.0, 50.0], [50.0, 51.0, 50.0]], np.float32)
    a = 0.2                                                  # the camera turned about its y axis
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    T_c2w = np.eye(4)
    T_c2w[:3, :3] = R
    K = np.array([[60.0, 0.0, 20.0], [0.0, 60.0, 9.0], [0.0, 0.0, 1.0]])
    arrays = {"room_v": far_v, "room_f": np.array([[0, 1, 2]], np.int32),
              "room_albedo": np.full((3, 3), 0.5, np.float32),
              "obj0_v": sq, "obj0_f": np.array([[0, 1, 2], [0, 2, 3]], np.int32),
              "obj0_n": np.tile([0.0, 0.0, -1.0], (4, 1)).astype(np.float32),
              "obj0_albedo": np.ones((4, 3), np.float32)}
    meta = {"objects": 1, "lights": [],
            "frames": [{"frame": 0, "K": K.tolist(), "T_c2w": T_c2w.tolist(), "width": 48, "height": 32,
                        "border": [0, 0, 48, 32], "exposure": 1.0}]}
    alpha = render_cycles(arrays, meta, tmp_path / "b", 16)[0]["combined"][..., 3]
    ys, xs = np.mgrid[0:32, 0:48]
    got = np.array([(alpha * xs).sum(), (alpha * ys).sum()]) / alpha.sum()
    pc = R.T @ c                                             # camera frame (OpenCV axes), the camera at the origin
    want = (K @ (pc / pc[2]))[:2]
    assert np.allclose(got, want, atol=0.25), (got, want)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    need_suite_renderer()
    from bench.lightsuite import TINY, build_suite
    root = tmp_path_factory.mktemp("cycles")
    build_suite(root / "suite", ("spot",), **TINY)
    from bench.cycles import main

    assert main(["--suite", str(root / "suite"), "--rooms", "spot", "--frames", "2", "--spp", "4,16",
                 "--presets", "default", "--work", str(root / "work"), "--out", str(root / "cycles")]) == 0
    return root


@pytest.mark.slow
@needs_bpy
def test_cycles_on_the_tiny_suite(tiny):
    """Cycles' objects land where our rasterizer put them (the camera conversion), as bright as Mitsuba's truth
    (the lights and materials), and the JSON holds both sides and the ratio."""
    import cv2

    doc = json.loads((tiny / "cycles.json").read_text())
    assert (tiny / "cycles.png").is_file()
    s = doc["summary"]
    assert set(s["cycles"]) == {"4", "16"} and set(s["ours"]) == {"default"}
    assert s["ratio_cpu"]["at_psnr_objects_db"] == pytest.approx(s["ours"]["default"]["psnr_objects"])
    room = doc["rooms"]["spot"]
    for spp in ("4", "16"):
        c = room["cycles"][spp]
        assert c["psnr_objects"] > 18.0 and c["render_cpu_s_per_image"] > 0
        assert np.all(np.abs(np.log(c["brightness"])) < np.log(1.25)), c["brightness"]   # the truth's +-25 %
    run = tiny / "work" / "spot" / "cycles-s16"
    for f in range(2):
        cov = np.load(run / "trace" / "scan" / "drop0000" / f"f{f:06d}.npz")["coverage"]
        mask = cv2.imread(str(tiny / "suite" / "spot" / "truth" / f"frame-{f:06d}.mask.png"),
                          cv2.IMREAD_UNCHANGED) > 0
        iou = ((cov > 0.5) & mask).sum() / ((cov > 0.5) | mask).sum()
        assert iou > 0.85, iou             # 160 x 120: a third of the object pixels are on an edge
