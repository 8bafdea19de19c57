"""Ingest stage: outputs and loading API, room meshes (converted or reconstructed), up direction,
determinism, and the mesh-related bad inputs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline import ingest, runfolder
from pipeline.config import build_config
from pipeline.errors import InputError, UserError
from tests.support.reference import raycast
from pipeline.reconstruct import drop_small_components, floor_up, fuse_tsdf
from pipeline.stages import StageContext
from pipeline.scanformats.common import read_color, read_depth
from pipeline.scanformats.detect import read_scan
from pipeline.scanformats.mesh import canonical_order, ply_bytes, read_room_ply
from tests.pipeline.test_scanformats import (ROOM_HI, ROOM_LO, UP, room_mesh, trajectory, write_3rscan,
                                             write_7scenes, write_scannet, write_transforms)


def box_distance(P: np.ndarray) -> np.ndarray:
    """Distance of points near the room's walls to the nearest wall plane."""
    return np.minimum(np.abs(P - ROOM_LO), np.abs(P - ROOM_HI)).min(axis=1)


def run_stage(run_dir: Path, raw_cfg: dict) -> dict:
    """Plan and run every ingest item directly, after generating the built-in scans as creating the run
    folder does."""
    from pipeline.cli import generate_builtin_scan

    cfg = build_config(raw_cfg)
    for p in cfg.scan.paths:
        if p.startswith("builtin:"):
            generate_builtin_scan(run_dir, p[len("builtin:"):])
    ctx = StageContext(run_dir=run_dir, cfg=cfg, stage="ingest")
    return {it.key: ingest.run_item(ctx, it) for it in ingest.plan(ctx)}


TSDF = {"tsdf_voxel": 0.08, "tsdf_trunc": 0.3, "depth_max": 5.0}


# ---------------------------------------------------------------------------------------------------
# Names and stage plan
# ---------------------------------------------------------------------------------------------------

def test_scene_names_unique_and_folder_safe():
    names = ingest.scene_names(["/a/kitchen", "/b/kitchen/", "/c/my scan!", "builtin:demo", "/d/objects",
                                "/e/kitchen"])
    assert names == ["kitchen", "kitchen-2", "my_scan_", "demo", "objects-scan", "kitchen-3"]


def test_plan_has_one_item_per_scan_and_objects(tmp_path):
    write_7scenes(tmp_path / "x" / "room", n=2)
    write_7scenes(tmp_path / "y" / "room", n=2)
    cfg = build_config({"scan": {"paths": [str(tmp_path / "x" / "room"), str(tmp_path / "y" / "room")]}})
    items = ingest.plan(StageContext(run_dir=tmp_path, cfg=cfg, stage="ingest"))
    assert [it.key for it in items] == ["room", "room-2", "objects"]


# ---------------------------------------------------------------------------------------------------
# Whole stage on scans written in every layout
# ---------------------------------------------------------------------------------------------------

def test_stage_ingests_every_layout_and_loads_back(tmp_path):
    t7 = write_7scenes(tmp_path / "s7", n=10, w=80, h=60, gravity=True)
    t3 = write_3rscan(tmp_path / "s3", n=4)
    tn = write_scannet(tmp_path / "sn", n=4)
    tt = write_transforms(tmp_path / "st", n=4)
    mesh = tmp_path / "room.ply"
    V, F, C = room_mesh()
    mesh.write_bytes(ply_bytes(V, F, C))
    paths = [str(tmp_path / n) for n in ("s7", "s3", "sn", "st")]
    run = tmp_path / "run"
    res = run_stage(run, {"scan": {"paths": paths[:3]}, "ingest": TSDF, "objects": {"paths": ["builtin:shapes"]}})
    res.update(run_stage(run, {"scan": {"paths": [paths[3]], "mesh": str(mesh)}}))
    assert runfolder.list_scenes(run) == ["s3", "s7", "sn", "st"]
    assert res["s7"]["mesh"].startswith("TSDF") and res["s3"]["mesh"].startswith("converted")
    for name, truth in (("s7", t7), ("s3", t3), ("sn", tn), ("st", tt)):
        s = runfolder.load_scan(run, name)
        np.testing.assert_allclose(s.T_c2w, truth["T"], atol=1e-6)
        np.testing.assert_allclose(s.K[0], truth["K"], atol=1e-6)
        Vr, Fr, Cr = runfolder.load_room_mesh(s)
        assert Vr.dtype == np.float64 and Fr.dtype == np.int32 and Cr.dtype == np.uint8
        assert len(Fr) > 0 and np.median(box_distance(Vr)) < 0.03
        np.testing.assert_allclose(s.up_w, UP, atol=0.02)
        d = read_depth(s, 0)
        assert d.shape == (s.height, s.width) and read_color(s, 0).shape == (s.height, s.width, 3)
    s7 = runfolder.load_scan(run, "s7")
    assert s7.meta["up_source"].startswith("metadata") and s7.meta["up"]["metadata_vs_floor_deg"] < 2
    assert runfolder.load_scan(run, "sn").meta["up_source"].startswith("mesh")
    # the 3RScan texture (green) became vertex colours
    _, _, C3 = runfolder.load_room_mesh(runfolder.load_scan(run, "s3"))
    assert np.all(C3[:, 1] > 150) and np.all(C3[:, 0] < 50)
    objs = runfolder.load_objects(run)
    assert [m.obj_id for m in objs] == [1, 2, 3, 4, 5]


def test_ingest_is_deterministic(tmp_path):
    write_7scenes(tmp_path / "scan", n=8, w=64, h=48)
    raw = {"scan": {"paths": [str(tmp_path / "scan")]}, "ingest": TSDF}
    run_stage(tmp_path / "a", raw)
    run_stage(tmp_path / "b", raw)
    for rel in ("scan/scan.json", "scan/frames.npz", "scan/room.ply", "objects/library.json",
                "objects/obj_000001.npz"):
        assert (tmp_path / "a" / "ingest" / rel).read_bytes() == (tmp_path / "b" / "ingest" / rel).read_bytes(), rel


def test_max_frames_keeps_evenly_spaced_frames(tmp_path):
    write_7scenes(tmp_path / "scan", n=9)
    run_stage(tmp_path / "run", {"scan": {"paths": [str(tmp_path / "scan")], "max_frames": 3}, "ingest": TSDF})
    s = runfolder.load_scan(tmp_path / "run", "scan")
    assert list(s.frame_ids) == [0, 4, 8] and s.meta["frames_read"] == 9


def test_load_scan_of_unknown_scene(tmp_path):
    with pytest.raises(UserError, match="was not ingested"):
        runfolder.load_scan(tmp_path, "nope")


def test_unknown_builtin_scan(tmp_path):
    with pytest.raises(UserError, match="unknown built-in scan 'builtin:huge'"):
        run_stage(tmp_path, {"scan": {"paths": ["builtin:huge"]}})


def test_builtin_tiny_scan(tmp_path):
    res = run_stage(tmp_path, {"scan": {"paths": ["builtin:tiny"]}})
    s = runfolder.load_scan(tmp_path, "tiny")
    assert res["tiny"]["frames"] == s.num_frames > 0
    assert np.all(np.isfinite(s.up_w)) and abs(np.linalg.norm(s.up_w) - 1) < 1e-9
    assert len(runfolder.load_room_mesh(s)[1]) > 0


# ---------------------------------------------------------------------------------------------------
# Reconstruction and up direction
# ---------------------------------------------------------------------------------------------------

def test_tsdf_reconstructs_the_room_walls(tmp_path):
    write_7scenes(tmp_path, n=12, w=80, h=60)
    s = read_scan(tmp_path)
    V, F, C = fuse_tsdf(s, voxel=0.05, trunc=0.2, depth_max=5.0)
    dist = box_distance(V)
    assert np.median(dist) < 0.01 and np.percentile(dist, 90) < 0.03
    assert C.dtype == np.uint8 and C.shape == V.shape
    # rendered depth of the reconstruction matches the exact depth
    d_true = read_depth(s, 3)
    d = raycast([(V, F)], s.K[3], s.T_c2w[3], s.width, s.height)[0]
    ok = (d > 0) & (d_true > 0)
    assert ok.mean() > 0.9 and np.median(np.abs(d - d_true)[ok]) < 0.01


def test_tsdf_with_no_depth_in_range_is_an_error(tmp_path):
    write_7scenes(tmp_path, n=2)
    s = read_scan(tmp_path)
    with pytest.raises(InputError, match="empty mesh.*depth_max"):
        fuse_tsdf(s, voxel=0.05, trunc=0.2, depth_max=0.1)


def test_floor_up_finds_the_floor_for_any_world_rotation():
    V, F, _ = room_mesh()
    Ts = trajectory(8)
    rng = np.random.default_rng(0)
    for _ in range(3):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        T = np.eye(4)
        T[:3, :3] = R
        up, info = floor_up(V @ R.T, F, T @ Ts)
        assert np.degrees(np.arccos(np.clip(up @ (R @ UP), -1, 1))) < 0.5
        assert abs(info["camera_height_above_floor_m"] - 1.4) < 0.05


def test_floor_up_prefers_floor_over_a_large_table():
    import trimesh

    V, F, _ = room_mesh()
    table = trimesh.creation.box(extents=(3.0, 2.0, 0.05))
    table.apply_translation((0, 0, 0.75))
    Vt = np.concatenate([V, table.vertices])
    Ft = np.concatenate([F, table.faces + len(V)])
    up, info = floor_up(Vt, Ft, trajectory(6))
    assert up @ UP > 0.999 and abs(info["floor_height_m"]) < 0.05


def test_canonical_order_is_the_same_mesh():
    V, F, C = room_mesh()
    perm = np.random.default_rng(1).permutation(len(V))
    inv = np.argsort(perm)
    V2, F2, C2 = V[perm], inv[F], C[perm]
    a = canonical_order(V, F, C)
    b = canonical_order(V2, F2[::-1], C2)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_drop_small_components():
    F = np.array([[0, 1, 2], [1, 2, 3], [4, 5, 6]])
    assert drop_small_components(F, 7, 2).tolist() == [[0, 1, 2], [1, 2, 3]]


def test_room_ply_round_trip(tmp_path):
    V, F, C = room_mesh()
    p = tmp_path / "r.ply"
    p.write_bytes(ply_bytes(V, F, C))
    V2, F2, C2 = read_room_ply(p)
    np.testing.assert_allclose(V2, V, atol=1e-6)
    np.testing.assert_array_equal(F2, F)
    np.testing.assert_array_equal(C2, C)
    import trimesh  # other readers agree

    m = trimesh.load(p, process=False)
    assert len(m.faces) == len(F)


# ---------------------------------------------------------------------------------------------------
# Bad meshes
# ---------------------------------------------------------------------------------------------------

def _transforms_with_mesh(tmp_path: Path, mesh_bytes: bytes, name: str = "mesh.ply") -> dict:
    write_transforms(tmp_path / "scan", n=3, depth=False)
    (tmp_path / name).write_bytes(mesh_bytes)
    return {"scan": {"paths": [str(tmp_path / "scan")], "mesh": str(tmp_path / name)}}


def test_empty_mesh_file(tmp_path):
    raw = _transforms_with_mesh(tmp_path, b"")
    with pytest.raises(InputError, match=r"mesh\.ply: mesh (cannot be read|has 0 vertices)"):
        run_stage(tmp_path / "run", raw)


def test_mesh_without_triangles(tmp_path):
    V, _, _ = room_mesh()
    head = f"ply\nformat ascii 1.0\nelement vertex {len(V)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    body = "\n".join(f"{x} {y} {z}" for x, y, z in V) + "\n"
    raw = _transforms_with_mesh(tmp_path, (head + body).encode())
    with pytest.raises(InputError, match=r"mesh\.ply: mesh has \d+ vertices and no triangle faces"):
        run_stage(tmp_path / "run", raw)


def test_mesh_in_wrong_units(tmp_path):
    V, F, C = room_mesh()
    raw = _transforms_with_mesh(tmp_path, ply_bytes(V * 1000.0 + 5000.0, F, C))
    with pytest.raises(InputError, match=r"no camera sees the mesh.*3 cameras.*millimetres\?"):
        run_stage(tmp_path / "run", raw)


def test_transforms_without_mesh_or_depth(tmp_path):
    write_transforms(tmp_path / "scan", n=2, depth=False)
    with pytest.raises(InputError, match="no mesh and no depth maps.*set scan.mesh"):
        run_stage(tmp_path / "run", {"scan": {"paths": [str(tmp_path / "scan")]}})


def test_scannet_without_mesh_is_reconstructed(tmp_path):
    write_scannet(tmp_path / "scan", n=6, mesh=False)
    res = run_stage(tmp_path / "run", {"scan": {"paths": [str(tmp_path / "scan")]}, "ingest": TSDF})
    assert res["scan"]["mesh"].startswith("TSDF")


# ---------------------------------------------------------------------------------------------------
# The real 7-Scenes sample
# ---------------------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.shared_data
def test_real_sevenscenes_ingest_subset(shared_data, tmp_path):
    """25 of the 100 frames at 3 cm voxels: a mesh that re-renders the real depth, up from the floor."""
    root = shared_data / "scans" / "7scenes-redkitchen"
    run_stage(tmp_path, {"scan": {"paths": [str(root)], "max_frames": 25},
                         "ingest": {"tsdf_voxel": 0.03, "tsdf_trunc": 0.12},
                         "objects": {"paths": ["builtin:shapes"]}})
    s = runfolder.load_scan(tmp_path, "7scenes-redkitchen")
    assert s.num_frames == 25 and s.format == "7scenes"
    # gravity-direction.txt points down: the floor found in the mesh agrees with its negation
    assert s.meta["up"]["metadata_vs_floor_deg"] < 3.0
    assert 1.0 < s.meta["up"]["camera_height_above_floor_m"] < 2.0
    V, F, C = runfolder.load_room_mesh(s)
    errs = []
    for i in (0, 12, 24):
        d_real = read_depth(s, i)
        d = raycast([(V, F)], s.K[i], s.T_c2w[i], s.width, s.height)[0]
        ok = (d > 0) & (d_real > 0)
        errs.append(np.abs(d - d_real)[ok])
    assert np.median(np.concatenate(errs)) < 0.03
    doc = json.loads((tmp_path / "ingest" / "7scenes-redkitchen" / "scan.json").read_text())
    # 7-Scenes gives the depth camera's K only: the colour camera is estimated (issue 16)
    rec = doc["meta"]["color_registration"]
    assert doc["meta"]["registration"].startswith("colour camera estimated") and rec["source"] == "estimated"
    assert 510 < rec["fx"] < 540 and rec["median_after_px"] < 1.5 < rec["median_before_px"]


def test_transforms_ply_file_path_mesh_or_point_cloud(tmp_path):
    V, F, C = room_mesh()
    write_transforms(tmp_path / "a", n=4)
    doc = json.loads((tmp_path / "a" / "transforms.json").read_text())
    doc["ply_file_path"] = "mesh.ply"
    (tmp_path / "a" / "transforms.json").write_text(json.dumps(doc))
    (tmp_path / "a" / "mesh.ply").write_bytes(ply_bytes(V, F, C))
    res = run_stage(tmp_path / "run", {"scan": {"paths": [str(tmp_path / "a")]}, "ingest": TSDF})
    assert res["a"]["mesh"].startswith("converted from") and res["a"]["mesh"].endswith("mesh.ply")
    # nerfstudio's usual ply_file_path: a point cloud -> reconstructed from the depth maps instead
    head = f"ply\nformat ascii 1.0\nelement vertex {len(V)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    (tmp_path / "a" / "mesh.ply").write_text(head + "\n".join(f"{x} {y} {z}" for x, y, z in V) + "\n")
    res = run_stage(tmp_path / "run2", {"scan": {"paths": [str(tmp_path / "a")]}, "ingest": TSDF})
    assert res["a"]["mesh"].startswith("TSDF")


@pytest.mark.shared_data
def test_mesh_made_from_one_depth_frame_is_seen_not_enclosing(shared_data, tmp_path):
    """Issue 20: a mesh from one frame's depth (a kitchen seen from 1-3 m) does not enclose its camera, but
    the camera sees it: ingest accepts it. The same mesh in millimetres is still refused."""
    from tests.support.captures import one_view_scan

    scan, mesh, P, F = one_view_scan(shared_data, tmp_path)
    cam = read_scan(scan).camera(0)
    lo, hi = P[np.unique(F)].min(0), P[np.unique(F)].max(0)
    assert not np.all((cam.center >= lo) & (cam.center <= hi))     # the old bounding-box rule refused it
    res = run_stage(tmp_path / "run", {"scan": {"paths": [str(scan)], "mesh": str(tmp_path / "mesh.ply")}})
    assert res["one-view"]["frames"] == 1 and res["one-view"]["mesh"].startswith("converted")
    (tmp_path / "mm.ply").write_bytes(ply_bytes(P * 1000.0, F, None))
    with pytest.raises(InputError, match=r"no camera sees the mesh.*millimetres\?"):
        run_stage(tmp_path / "run2", {"scan": {"paths": [str(scan)], "mesh": str(tmp_path / "mm.ply")}})


@pytest.mark.parametrize("pitch_deg", [20.0, 45.0, 65.0])
def test_floor_up_of_one_photo_looking_down_at_a_table_before_a_wall(pitch_deg):
    """One camera 1 m from a table top, looking down at it by ``pitch_deg``, a larger wall behind the table
    (as a tabletop capture's depth shows them): up is the table's normal, however steep the view. A
    30-degree cone around the image's up keeps the wall (at 90 - pitch from it) and loses the table."""
    import trimesh

    from pipeline.geometry import look_at

    table = trimesh.creation.box(extents=(1.2, 0.8, 0.04))
    table.apply_translation((0, 0, 0.73))
    wall = trimesh.creation.box(extents=(3.0, 0.04, 2.0))
    wall.apply_translation((0, 0.6, 1.0))
    V = np.concatenate([table.vertices, wall.vertices])
    F = np.concatenate([table.faces, wall.faces + len(table.vertices)])
    target = np.array([0.0, 0.0, 0.75])
    p = np.radians(pitch_deg)
    eye = target + 1.0 * np.array([0.0, -np.cos(p), np.sin(p)])
    mesh = trimesh.Trimesh(V, F).subdivide().subdivide().subdivide()
    up, _ = floor_up(np.asarray(mesh.vertices), np.asarray(mesh.faces), look_at(eye, target)[None])
    assert up @ UP > np.cos(np.radians(1.0)), (pitch_deg, up)
