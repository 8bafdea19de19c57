"""Tests of the synthetic scan generator (pipeline/synthscan).

The layouts are read back with small independent readers written from the formats' specifications
(not with the generator's own code), and compared with the ground truth to 1e-6.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline import runfolder
from pipeline.errors import UserError
from pipeline.scanformats.common import read_depth
from pipeline.synthscan import builtin_scan, make_scan
from pipeline.synthscan.generate import GT_DIR, _motion_extent
from pipeline.synthscan.writers import LAYOUTS

TINY = {"width": 160, "height": 120, "frames": 8}
POSE_TOL = 1e-6


# ---------------------------------------------------------------------------------------------------
# Fixtures: one tiny scan per layout, made once per module
# ---------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def scans(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("synthscan")
    return {layout: make_scan(root / layout, layout=layout, seed=3, **TINY) for layout in LAYOUTS}


def truth(scan: Path) -> tuple[dict, dict]:
    doc = json.loads((scan / GT_DIR / "scan.json").read_text())
    with np.load(scan / GT_DIR / "cameras.npz") as z:
        cams = {k: z[k] for k in z.files}
    return doc, cams


# ---------------------------------------------------------------------------------------------------
# Independent readers of the five layouts
# ---------------------------------------------------------------------------------------------------

def read_7scenes(scan: Path) -> dict:
    K = np.loadtxt(scan / "camera-intrinsics.txt")
    frames = sorted((scan / "frames").glob("frame-*.pose.txt"))
    poses = np.stack([np.loadtxt(p) for p in frames])
    color = cv2.imread(str(frames[0]).replace(".pose.txt", ".color.png"), cv2.IMREAD_UNCHANGED)
    depth = cv2.imread(str(frames[0]).replace(".pose.txt", ".depth.png"), cv2.IMREAD_UNCHANGED)
    gravity = np.loadtxt(scan / "gravity-direction.txt")
    return {"K": K, "depth_K": K, "T_c2w": poses, "color": color, "depth": depth, "gravity": gravity,
            "n_color": len(list((scan / "frames").glob("frame-*.color.png")))}


def read_3rscan(scan: Path) -> dict:
    info = {}
    for line in (scan / "sequence" / "_info.txt").read_text().splitlines():
        k, v = line.split(" = ", 1)
        info[k] = v
    K = np.array(info["m_calibrationColorIntrinsic"].split(), float).reshape(4, 4)[:3, :3]
    dK = np.array(info["m_calibrationDepthIntrinsic"].split(), float).reshape(4, 4)[:3, :3]
    frames = sorted((scan / "sequence").glob("frame-*.pose.txt"))
    poses = np.stack([np.loadtxt(p) for p in frames])
    depth = cv2.imread(str(frames[0]).replace(".pose.txt", ".depth.pgm"), cv2.IMREAD_UNCHANGED)
    color = cv2.imread(str(frames[0]).replace(".pose.txt", ".color.jpg"), cv2.IMREAD_UNCHANGED)
    return {"K": K, "depth_K": dK, "T_c2w": poses, "color": color, "depth": depth, "info": info,
            "n_color": len(list((scan / "sequence").glob("frame-*.color.jpg")))}


def read_scannet(scan: Path) -> dict:
    K = np.loadtxt(scan / "intrinsic" / "intrinsic_color.txt")[:3, :3]
    dK = np.loadtxt(scan / "intrinsic" / "intrinsic_depth.txt")[:3, :3]
    n = len(list((scan / "pose").glob("*.txt")))
    poses = np.stack([np.loadtxt(scan / "pose" / f"{i}.txt") for i in range(n)])
    color = cv2.imread(str(scan / "color" / "0.jpg"), cv2.IMREAD_UNCHANGED)
    depth = cv2.imread(str(scan / "depth" / "0.png"), cv2.IMREAD_UNCHANGED)
    return {"K": K, "depth_K": dK, "T_c2w": poses, "color": color, "depth": depth,
            "n_color": len(list((scan / "color").glob("*.jpg")))}


def read_transforms(scan: Path) -> dict:
    doc = json.loads((scan / "transforms.json").read_text())
    # nerfstudio: pixel i is centred at i + 0.5; OpenCV at i.
    K = np.array([[doc["fl_x"], 0, doc["cx"] - 0.5], [0, doc["fl_y"], doc["cy"] - 0.5], [0, 0, 1]])
    gl_to_cv = np.diag([1.0, -1.0, -1.0, 1.0])
    poses = np.stack([np.array(f["transform_matrix"]) @ gl_to_cv for f in doc["frames"]])
    color = cv2.imread(str(scan / doc["frames"][0]["file_path"]), cv2.IMREAD_UNCHANGED)
    depth = cv2.imread(str(scan / doc["frames"][0]["depth_file_path"]), cv2.IMREAD_UNCHANGED)
    return {"K": K, "depth_K": K, "T_c2w": poses, "color": color, "depth": depth, "doc": doc,
            "n_color": len(doc["frames"])}


def read_bop(scan: Path) -> dict:
    cams = json.loads((scan / "scene_camera.json").read_text())
    ids = sorted(cams, key=int)
    K = np.array(cams[ids[0]]["cam_K"], float).reshape(3, 3)
    poses = []
    for i in ids:
        T = np.eye(4)      # BOP: x_cam = R_w2c x_world + t_w2c (mm)
        T[:3, :3], T[:3, 3] = np.reshape(cams[i]["cam_R_w2c"], (3, 3)), np.array(cams[i]["cam_t_w2c"]) / 1000
        poses.append(np.linalg.inv(T))
    color = cv2.imread(str(scan / "rgb" / f"{int(ids[0]):06d}.png"), cv2.IMREAD_UNCHANGED)
    depth = cv2.imread(str(scan / "depth" / f"{int(ids[0]):06d}.png"), cv2.IMREAD_UNCHANGED)
    return {"K": K, "depth_K": K, "T_c2w": np.stack(poses), "color": color, "depth": depth, "cams": cams,
            "n_color": len(list((scan / "rgb").glob("*.png")))}


READERS = {"7scenes": read_7scenes, "3rscan": read_3rscan, "scannet": read_scannet, "transforms": read_transforms,
           "bop": read_bop}


def read_ply(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Header lines, vertex records and faces of a binary little-endian PLY as the writers make them."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().splitlines()
    assert header[0] == "ply" and header[1] == "format binary_little_endian 1.0"
    types = {"float": "<f4", "uchar": "u1", "int": "<i4"}
    fields, nv, nf = [], 0, 0
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            nv = int(parts[2])
        elif parts[:2] == ["element", "face"]:
            nf = int(parts[2])
        elif parts[0] == "property" and parts[1] != "list":
            fields.append((parts[2], types[parts[1]]))
    v = np.frombuffer(data, dtype=fields, count=nv, offset=end)
    f = np.frombuffer(data, dtype=[("n", "u1"), ("i", "<i4", (3,))], count=nf, offset=end + v.nbytes)
    assert (f["n"] == 3).all()
    return header, v, f["i"]


# ---------------------------------------------------------------------------------------------------
# Layouts: files, intrinsics and poses read back equal the truth
# ---------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("layout", LAYOUTS)
def test_layout_reads_back_true_intrinsics_and_poses(scans, layout):
    scan = scans[layout]
    doc, cams = truth(scan)
    got = READERS[layout](scan)
    valid = cams["pose_valid"]
    np.testing.assert_allclose(got["K"], cams["K"], atol=POSE_TOL, rtol=0)
    np.testing.assert_allclose(got["depth_K"], cams["depth_K"], atol=POSE_TOL, rtol=0)
    poses = got["T_c2w"]
    if layout == "scannet":
        assert np.isneginf(poses[~valid]).all()
        poses = poses[valid]
    assert len(poses) == int(valid.sum()) == doc["num_valid_poses"]
    np.testing.assert_allclose(poses, cams["T_c2w"][valid], atol=POSE_TOL, rtol=0)
    assert got["n_color"] == (int(valid.sum()) if layout == "transforms" else TINY["frames"])
    assert got["color"].shape == (doc["height"], doc["width"], 3) and got["color"].dtype == np.uint8
    assert got["depth"].shape == (doc["depth_height"], doc["depth_width"])
    assert got["depth"].dtype == np.uint16


def test_scannet_has_lost_tracking_frames_and_smaller_depth(scans):
    doc, cams = truth(scans["scannet"])
    assert (~cams["pose_valid"]).sum() >= 1
    assert doc["depth_width"] < doc["width"] and doc["depth_height"] < doc["height"]
    header, v, f = read_ply(scans["scannet"] / f"{doc['scene']}_vh_clean_2.ply")
    assert [n for n in v.dtype.names] == ["x", "y", "z", "red", "green", "blue", "alpha"]
    assert len(f) > 1000
    for name in ("extrinsic_color.txt", "extrinsic_depth.txt"):
        np.testing.assert_array_equal(np.loadtxt(scans["scannet"] / "intrinsic" / name), np.eye(4))


def test_3rscan_info_mesh_and_pgm(scans):
    scan = scans["3rscan"]
    doc, _ = truth(scan)
    info = read_3rscan(scan)["info"]
    assert int(info["m_colorWidth"]) == doc["width"] and int(info["m_depthHeight"]) == doc["depth_height"]
    assert float(info["m_depthShift"]) == 1000.0
    assert int(info["m_frames.size"]) == TINY["frames"]
    head = (scan / "sequence" / "frame-000000.depth.pgm").read_bytes()[:20]
    assert head.startswith(b"P5\n") and b"65535" in head
    obj = (scan / "mesh.refined.v2.obj").read_text()
    assert obj.startswith("mtllib mesh.refined.mtl\n")
    assert "map_Kd mesh.refined_0.png" in (scan / "mesh.refined.mtl").read_text()
    tex = cv2.imread(str(scan / "mesh.refined_0.png"))
    assert tex is not None and tex.shape[0] == tex.shape[1]
    nv = sum(1 for line in obj.splitlines() if line.startswith("v "))
    faces = [line for line in obj.splitlines() if line.startswith("f ")]
    idx = np.array([[int(t.split("/")[0]) for t in line.split()[1:]] for line in faces])
    assert idx.min() >= 1 and idx.max() <= nv


def test_7scenes_world_is_first_camera_and_gravity_points_down(scans):
    doc, cams = truth(scans["7scenes"])
    np.testing.assert_array_equal(cams["T_c2w"][0], np.eye(4))
    g = read_7scenes(scans["7scenes"])["gravity"]
    np.testing.assert_allclose(g, -np.array(doc["up_w"]), atol=1e-12)
    # A camera held upright: its "down" axis (+y) points roughly along gravity.
    assert float(cams["T_c2w"][0][:3, 1] @ g) > 0.7


def test_transforms_json_fields(scans):
    doc = read_transforms(scans["transforms"])["doc"]
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h", "frames", "ply_file_path"):
        assert key in doc
    assert (scans["transforms"] / doc["ply_file_path"]).is_file()
    f0 = doc["frames"][0]
    assert set(f0) == {"file_path", "depth_file_path", "transform_matrix"}


# ---------------------------------------------------------------------------------------------------
# Round trip through ingest (pipeline/ingest.py, issue 3)
# ---------------------------------------------------------------------------------------------------

def ingest_back(scan: Path, run_dir: Path):
    from pipeline import ingest
    from pipeline.config import build_config

    cfg = build_config({"ingest": {"tsdf_voxel": 0.08, "tsdf_trunc": 0.3, "depth_max": 5.0}})
    ingest.ingest_scan(scan, "s", run_dir / "ingest" / "s", cfg)
    return runfolder.load_scan(run_dir, "s")


@pytest.mark.parametrize("layout", [pytest.param("7scenes", marks=pytest.mark.slow), "3rscan", "scannet",
                                    "transforms", "bop"])
def test_round_trip_through_ingest(scans, tmp_path, layout, recwarn):
    from pipeline import ingest

    doc, cams = truth(scans[layout])
    s = ingest_back(scans[layout], tmp_path)
    valid = cams["pose_valid"]
    assert s.num_frames == int(valid.sum()) == doc["num_valid_poses"]
    np.testing.assert_array_equal(s.frame_ids, cams["frame_ids"][valid])
    np.testing.assert_allclose(s.T_c2w, cams["T_c2w"][valid], atol=POSE_TOL, rtol=0)
    assert (s.width, s.height) == (doc["width"], doc["height"])
    # transforms.json stores cx, cy + 0.5 (nerfstudio pixel centres); ingest converts back to OpenCV.
    np.testing.assert_allclose(s.K, np.broadcast_to(cams["K"], s.K.shape), atol=POSE_TOL, rtol=0)
    if layout in ("3rscan", "scannet"):
        assert (s.depth_width, s.depth_height) == (doc["depth_width"], doc["depth_height"])
        np.testing.assert_allclose(s.depth_K, np.broadcast_to(cams["depth_K"], s.depth_K.shape), atol=POSE_TOL,
                                   rtol=0)
    assert s.depth_scale == pytest.approx(0.001)
    assert float(s.up_w @ np.array(doc["up_w"])) > 0.99
    V, F, _ = runfolder.load_room_mesh(s)
    assert len(F) > 0
    d = read_depth(s, 0)
    gt = cv2.imread(str(scans[layout] / doc["frames_info"][int(np.flatnonzero(valid)[0])]["gt_depth"]),
                    cv2.IMREAD_UNCHANGED)
    assert d.shape == (doc["height"], doc["width"]) and gt is not None


# ---------------------------------------------------------------------------------------------------
# Ground truth content
# ---------------------------------------------------------------------------------------------------

def test_ground_truth_files(scans):
    scan = scans["7scenes"]
    g = scan / GT_DIR
    doc, cams = truth(scan)
    header, v, f = read_ply(g / "mesh.ply")
    assert {"material_id", "part_id", "red"} <= set(v.dtype.names)
    mats = json.loads((g / "materials.json").read_text())["materials"]
    assert v["material_id"].max() < len(mats)
    lights = json.loads((g / "lights.json").read_text())
    kinds = sorted(L["kind"] for L in lights["lights"])
    assert kinds.count("area") >= 1 and "window" in kinds
    for L in lights["lights"]:
        assert np.allclose(L["power"], np.pi * np.array(L["radiance"]) * L["area_m2"])
    thin = json.loads((g / "thin_parts.json").read_text())["thin_parts"]
    names = {t["name"] for t in thin}
    assert {"table_leg_0", "chair_leg_0"} <= names and any(n.startswith("shelf_board") for n in names)
    assert all(t["thickness_m"] < 0.04 for t in thin)
    assert sum(t["scan_mesh_missing_fraction"] > 0.2 for t in thin) >= len(thin) // 2
    kinds = cams["blur_kind"]
    assert (kinds == 1).sum() >= 1 and (kinds == 2).sum() >= 1
    assert (cams["blur_strength_px"][kinds > 0] > 0).all() and (cams["blur_strength_px"][kinds == 0] == 0).all()
    for fr in doc["frames_info"]:
        assert (scan / fr["color"]).is_file() and (scan / fr["gt_depth"]).is_file()
    # All files listed exist, and every file under the folder is listed.
    listed = set(doc["files"])
    on_disk = {str(p.relative_to(scan)) for p in scan.rglob("*") if p.is_file()}
    assert listed == on_disk


def test_true_depth_lies_on_true_mesh(scans):
    """Back-projected ground-truth depth of a frame lands on the true mesh's triangles (within 2 mm)."""
    scan = scans["scannet"]
    doc, cams = truth(scan)
    _, v, faces = read_ply(scan / GT_DIR / "mesh.ply")
    verts = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    i = int(np.flatnonzero(cams["pose_valid"])[1])
    d = cv2.imread(str(scan / doc["frames_info"][i]["gt_depth"]), cv2.IMREAD_UNCHANGED) * doc["gt_depth_scale"]
    K, T = cams["depth_K"], cams["T_c2w"][i]
    vv, uu = np.nonzero(d > 0)
    z = d[vv, uu]
    P = np.stack([(uu - K[0, 2]) / K[0, 0] * z, (vv - K[1, 2]) / K[1, 1] * z, z], 1) @ T[:3, :3].T + T[:3, 3]
    # Distance to the nearest triangle plane among faces whose vertices are near the point.
    tri = verts[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = tri.mean(1)
    from scipy.spatial import cKDTree

    tree = cKDTree(c)
    _, nn = tree.query(P, k=8)
    dist = np.abs(np.einsum("pkd,pkd->pk", P[:, None, :] - tri[nn, 0], n[nn])).min(axis=1)
    assert np.median(dist) < 5e-4
    assert np.quantile(dist, 0.95) < 2e-3


def test_sensor_depth_is_degraded_but_close(scans):
    scan = scans["7scenes"]
    doc, _ = truth(scan)
    fr = doc["frames_info"][0]
    gt = cv2.imread(str(scan / fr["gt_depth"]), cv2.IMREAD_UNCHANGED) * doc["gt_depth_scale"]
    sensor = cv2.imread(str(scan / fr["depth"]), cv2.IMREAD_UNCHANGED) * 0.001
    both = (gt > 0) & (sensor > 0)
    assert both.mean() > 0.5
    assert ((gt > 0) & (sensor == 0)).sum() > 0          # some pixels dropped out
    err = np.abs(sensor[both] - gt[both])
    assert np.median(err) < 0.01 and err.max() < 0.1
    assert np.any(err > 0)


def test_scan_mesh_is_scanner_like(scans):
    g = scans["7scenes"] / GT_DIR
    _, tv, tf = read_ply(g / "mesh.ply")
    _, sv, sf = read_ply(g / "scan_mesh.ply")
    assert len(sf) > len(tf)                               # over-tessellated
    cols = np.stack([sv["red"], sv["green"], sv["blue"]], 1)
    assert cols.std(axis=0).min() > 5                      # baked shading and texture, not flat


# ---------------------------------------------------------------------------------------------------
# Determinism and folder handling
# ---------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("layout", ["7scenes", "3rscan"])
def test_same_seed_same_bytes(scans, tmp_path, layout):
    again = make_scan(tmp_path / "again", layout=layout, seed=3, **TINY)
    a = {str(p.relative_to(scans[layout])): p.read_bytes() for p in scans[layout].rglob("*") if p.is_file()}
    b = {str(p.relative_to(again)): p.read_bytes() for p in again.rglob("*") if p.is_file()}
    assert a.keys() == b.keys()
    differing = [k for k in a if a[k] != b[k]]
    assert differing == []


def test_different_seed_different_room(tmp_path, scans):
    other = make_scan(tmp_path / "s4", layout="7scenes", seed=4, **TINY)
    assert (other / GT_DIR / "mesh.ply").read_bytes() != (scans["7scenes"] / GT_DIR / "mesh.ply").read_bytes()


@pytest.mark.slow
def test_regenerating_removes_stale_frames(tmp_path):
    out = make_scan(tmp_path / "s", layout="scannet", seed=0, width=64, height=48, frames=6)
    assert (out / "color" / "5.jpg").is_file()
    make_scan(out, layout="scannet", seed=0, width=64, height=48, frames=3)
    assert not (out / "color" / "5.jpg").exists()
    assert sorted(p.name for p in (out / "color").iterdir()) == ["0.jpg", "1.jpg", "2.jpg"]


def test_refuses_foreign_non_empty_folder(tmp_path):
    (tmp_path / "mine.txt").write_text("keep me")
    with pytest.raises(UserError, match="not empty"):
        make_scan(tmp_path, layout="7scenes", seed=0, width=64, height=48, frames=2)
    assert (tmp_path / "mine.txt").read_text() == "keep me"


def test_output_path_that_is_a_file_or_a_broken_manifest(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(UserError, match="is a file"):
        make_scan(f, layout="7scenes", seed=0, width=64, height=48, frames=2)
    broken = tmp_path / "broken"
    (broken / GT_DIR).mkdir(parents=True)
    (broken / GT_DIR / "scan.json").write_text("{not json")
    with pytest.raises(UserError, match="unreadable"):
        make_scan(broken, layout="7scenes", seed=0, width=64, height=48, frames=2)


@pytest.mark.parametrize("kwargs, match", [
    ({"layout": "kinect"}, "layout"),
    ({"seed": -1}, "seed"),
    ({"width": 0}, "size"),
    ({"frames": 0}, "frames"),
])
def test_bad_arguments_are_user_errors(tmp_path, kwargs, match):
    args = {"layout": "7scenes", "seed": 0, "width": 64, "height": 48, "frames": 2} | kwargs
    with pytest.raises(UserError, match=match):
        make_scan(tmp_path / "x", **args)


def test_unknown_photo_mode_is_a_user_error(tmp_path):
    # the traced mode itself is tested in test_synthscan_traced.py
    with pytest.raises(UserError, match="photo mode"):
        make_scan(tmp_path / "x", layout="7scenes", seed=0, width=64, height=48, frames=2, photo_mode="mitsuba")


def test_builtin_tiny_is_reused_and_unknown_name_fails(tmp_path):
    out = builtin_scan("tiny", tmp_path / "tiny")
    doc, cams = truth(out)
    assert (doc["width"], doc["height"], doc["frames"], doc["layout"]) == (160, 120, 8, "7scenes")
    stamp = (out / GT_DIR / "scan.json").stat().st_mtime_ns
    assert builtin_scan("tiny", out) == out
    assert (out / GT_DIR / "scan.json").stat().st_mtime_ns == stamp
    with pytest.raises(UserError, match="builtin:demo"):
        builtin_scan("huge", tmp_path / "h")


def test_cli_make_scan_and_contact_sheet(tmp_path, capsys):
    from pipeline.cli import main

    sheet = tmp_path / "sheet.png"
    rc = main(["make-scan", str(tmp_path / "s"), "--layout", "transforms", "--seed", "2", "--size", "64x48",
               "--frames", "4", "--contact-sheet", str(sheet), "-q"])
    assert rc == 0
    img = cv2.imread(str(sheet))
    assert img is not None and img.shape[0] > 48
    assert (tmp_path / "s" / "transforms.json").is_file()
    rc = main(["make-scan", str(tmp_path / "t"), "--layout", "7scenes", "--seed", "0", "--frames", "0"])
    assert rc == 2
    assert "--frames 0" in capsys.readouterr().err
    rc = main(["make-scan", str(tmp_path / "u"), "--layout", "7scenes", "--seed", "0", "--frames", "2",
               "--contact-sheet", str(tmp_path / "sheet.jpg")])
    assert rc == 2
    assert "contact sheet is a PNG" in capsys.readouterr().err
    assert not (tmp_path / "u").exists()


# ---------------------------------------------------------------------------------------------------
# Pieces, against analytic answers
# ---------------------------------------------------------------------------------------------------

def test_depth_render_matches_analytic_plane():
    """A tilted view of the floor: rendered depth equals the ray-plane intersection at pixel centres."""
    from pipeline.seeding import item_rng
    from pipeline.camera import Camera
    from pipeline.synthscan.render import RasterPhotoRenderer
    from pipeline.synthscan.room import make_room, tessellate
    from pipeline.synthscan.trajectory import look_at

    room = make_room(item_rng(0, "t"))
    floor = [room.parts[0].quad_start]
    mesh = tessellate(room, 0.5, floor)
    r = RasterPhotoRenderer(room, mesh, np.ones((len(mesh.vertices), 3), np.float32))
    try:
        eye = np.array([1.5, 1.2, 1.4])
        T = look_at(eye, np.array([2.5, 2.0, 0.0]), roll=0.2)
        K = np.array([[100.0, 0, 40.3], [0, 110.0, 29.7], [0, 0, 1]])
        d = r.render_depth(Camera(K, T, 80, 60)).astype(np.float64)
    finally:
        r.close()
    v, u = np.mgrid[0:60, 0:80]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    dw = rays @ T[:3, :3].T
    z = -eye[2] / dw[..., 2]                   # z-depth: the camera ray has unit z
    inside = (d > 0)
    inside[1:-1, 1:-1] &= (d[:-2, 1:-1] > 0) & (d[2:, 1:-1] > 0) & (d[1:-1, :-2] > 0) & (d[1:-1, 2:] > 0)
    assert inside.sum() > 1000
    np.testing.assert_allclose(d[inside], z[inside], atol=2e-4)


def _corner_irradiance(a: float, b: float, h: float) -> float:
    """Irradiance (for L = 1) under the corner of an a x b rectangle at height h (tabulated form factor)."""
    X, Y = a / h, b / h
    F = (X / math.sqrt(1 + X * X) * math.atan(Y / math.sqrt(1 + X * X))
         + Y / math.sqrt(1 + Y * Y) * math.atan(X / math.sqrt(1 + Y * Y))) / (2 * math.pi)
    return math.pi * F


def test_polygon_irradiance_matches_form_factor():
    from pipeline.synthscan.lighting import direct_irradiance
    from pipeline.synthscan.room import Light

    a, h = 0.3, 1.7
    corners = np.array([[-a, -a, h], [-a, a, h], [a, a, h], [a, -a, h]])
    L = Light("l", "area", corners, np.array([0, 0, -1.0]), np.array([2.0, 2.0, 2.0]))
    E = direct_irradiance(np.zeros((1, 3)), np.array([[0, 0, 1.0]]), (L,))
    assert E[0, 0] == pytest.approx(2.0 * 4 * _corner_irradiance(a, a, h), rel=1e-9)
    # Facing away, or behind the emitter: nothing.
    assert direct_irradiance(np.zeros((1, 3)), np.array([[0, 0, -1.0]]), (L,))[0, 0] == 0.0
    assert direct_irradiance(np.array([[0, 0, 2.0]]), np.array([[0, 0, -1.0]]), (L,))[0, 0] == 0.0
    # A huge emitter approaches pi * L.
    big = Light("b", "area", corners * [1e4, 1e4, 1], np.array([0, 0, -1.0]), np.ones(3))
    assert direct_irradiance(np.zeros((1, 3)), np.array([[0, 0, 1.0]]), (big,))[0, 0] == pytest.approx(math.pi, rel=1e-3)


def test_shadows_block_light():
    from pipeline.synthscan.lighting import EmbreeShadows
    from pipeline.synthscan.room import Light

    corners = np.array([[-0.3, -0.3, 2.0], [-0.3, 0.3, 2.0], [0.3, 0.3, 2.0], [0.3, -0.3, 2.0]])
    L = Light("l", "area", corners, np.array([0, 0, -1.0]), np.ones(3))
    blocker = np.array([[-1, -1, 1.0], [1, -1, 1.0], [1, 1, 1.0], [-1, 1, 1.0]])
    vis = EmbreeShadows(blocker, np.array([[0, 1, 2], [0, 2, 3]]))(
        np.array([[0, 0, 0.0], [5, 0, 0.0]]), np.array([[0, 0, 1.0], [0, 0, 1.0]]), L)
    np.testing.assert_allclose(vis, [0.0, 1.0])


def test_ambient_occlusion_open_plane_and_closed_box():
    from pipeline.seeding import item_rng
    from pipeline.synthscan.lighting import EmbreeShadows
    from pipeline.synthscan.room import _Builder, make_room, tessellate

    plane = np.array([[-5, -5, 0.0], [5, -5, 0.0], [5, 5, 0.0], [-5, 5, 0.0]])
    ao = EmbreeShadows(plane, np.array([[0, 1, 2], [0, 2, 3]])).ambient_occlusion(
        np.zeros((1, 3)), np.array([[0, 0, 1.0]]))
    assert ao[0] == 1.0
    b = _Builder()
    b.box("b", 0, (0, 0, 0), (0.4, 0.4, 0.4))
    room = make_room(item_rng(0, "t"))
    box = dataclasses.replace(room, quad_origin=np.array(b.o), quad_a=np.array(b.a), quad_b=np.array(b.b),
                              quad_material=np.zeros(6, np.int32), quad_part=np.zeros(6, np.int32))
    mesh = tessellate(box, 0.1)
    inside = EmbreeShadows(mesh.vertices, mesh.faces).ambient_occlusion(
        np.zeros((1, 3)), np.array([[0, 0, 1.0]]), max_distance=1.0)
    assert inside[0] == 0.0


def test_motion_extent_of_a_pure_rotation():
    from pipeline.synthscan.trajectory import exposure_path

    K = np.array([[200.0, 0, 79.5], [0, 200.0, 59.5], [0, 0, 1]])
    depth = np.full((120, 160), 2.0, np.float32)
    ang = 0.02
    subs = exposure_path(np.eye(4), np.array([0.0, ang, 0.0]), np.zeros(3), 5)
    np.testing.assert_allclose(subs[2], np.eye(4), atol=1e-15)
    ext = _motion_extent(depth, K, np.eye(4), subs[0], subs[-1])
    assert ext == pytest.approx(200.0 * ang, rel=0.05)     # f * angle near the image centre


def test_depth_degradation_model():
    from pipeline.synthscan import degrade

    K = np.array([[300.0, 0, 99.5], [0, 300.0, 99.5], [0, 0, 1]])
    rng = np.random.default_rng(0)
    near = degrade.degrade_depth(np.full((200, 200), 1.0, np.float32), K, rng)
    far = degrade.degrade_depth(np.full((200, 200), 3.0, np.float32), K, rng)
    assert near.dtype == np.uint16
    sd_near = near[near > 0].astype(float).std() / 1000
    sd_far = far[far > 0].astype(float).std() / 1000
    assert sd_near == pytest.approx(degrade.DEPTH_NOISE_A + degrade.DEPTH_NOISE_B * 0.36, rel=0.3)
    assert sd_far == pytest.approx(degrade.DEPTH_NOISE_A + degrade.DEPTH_NOISE_B * 6.76, rel=0.1)
    assert (degrade.degrade_depth(np.full((50, 50), 6.0, np.float32), K, rng) == 0).all()   # beyond range
    assert (degrade.degrade_depth(np.zeros((50, 50), np.float32), K, rng) == 0).all()       # no surface
    # A plane seen at grazing incidence drops out; seen more frontally it stays.
    a = math.radians(80.0)
    n = np.array([0.0, -math.sin(a), math.cos(a)])
    c = n @ np.array([0.0, 0.0, 2.0])
    v, u = np.mgrid[0:200, 0:200]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((200, 200))], -1)
    nr = rays @ n
    z = np.where(nr > 1e-3, c / np.maximum(nr, 1e-3), 0.0).astype(np.float32)
    z[z > 4.0] = 0.0
    inc = np.degrees(np.arccos(np.clip(nr / np.linalg.norm(rays, axis=-1), -1, 1)))
    est = np.degrees(np.arccos(degrade.depth_normals_cos(z, K)))
    ok = (z > 0) & (np.abs(v - 100) < 96) & (np.abs(u - 100) < 96)
    ok[1:-1, 1:-1] &= (z[:-2, 1:-1] > 0) & (z[2:, 1:-1] > 0)
    assert np.abs(est[ok] - inc[ok]).max() < 1.0
    out = degrade.degrade_depth(z, K, rng)
    assert (out[ok & (inc > 83)] > 0).mean() < 0.01
    assert (out[ok & (inc < 68)] > 0).mean() > 0.9


def test_defocus_and_photo_encoding():
    from pipeline.synthscan import degrade

    k = degrade.disk_kernel(3.0)
    assert k.sum() == pytest.approx(1.0, abs=1e-6)
    rng = np.random.default_rng(1)
    img = rng.random((64, 64, 3)).astype(np.float32)
    blurred = degrade.defocus(img, 3.0)
    lap = lambda x: cv2.Laplacian(x[..., 0], cv2.CV_32F).var()   # noqa: E731
    assert lap(blurred) < 0.1 * lap(img)
    a = degrade.encode_photo(img * 2.0, np.random.default_rng(5))
    b = degrade.encode_photo(img * 2.0, np.random.default_rng(5))
    assert a.dtype == np.uint8 and np.array_equal(a, b)
    assert (a == 255).mean() > 0.3                                  # over-exposed values clip to white


def test_textures_tile_seamlessly():
    from pipeline.synthscan.textures import KINDS, make_texture

    for kind in KINDS:
        t = make_texture(kind, np.random.default_rng(0), (0.5, 0.4, 0.3), 64).astype(float)
        # The jump across the wrap edge is no larger than typical jumps inside the texture.
        inner = np.abs(np.diff(t, axis=1)).mean()
        wrap = np.abs(t[:, 0] - t[:, -1]).mean()
        if kind == "tiles":      # the wrap is a tile boundary: compare with the boundary in the middle
            inner = np.abs(t[:, 31] - t[:, 32]).mean()
        assert wrap <= 3 * inner + 1.0, kind
