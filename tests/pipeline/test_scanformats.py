"""Scan layout readers: round trips on scans written here in each layout, and every bad-input case.

The test scans show an analytic room (an axis-aligned box, z up) seen by cameras inside it; depth is
exact (ray/box intersection), so registration and reconstruction can be checked against the truth.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.scanformats import common
from pipeline.scanformats.common import IngestWarning, read_color, read_depth, register_depth
from pipeline.scanformats.detect import detect_format, read_scan

ROOM_LO = np.array([-2.0, -1.5, 0.0])
ROOM_HI = np.array([2.0, 1.5, 2.5])
UP = np.array([0.0, 0.0, 1.0])


# ---------------------------------------------------------------------------------------------------
# An analytic room and writers for each layout (shared with test_ingest.py)
# ---------------------------------------------------------------------------------------------------

def look_pose(pos: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at ``pos`` looking at ``target`` with z up."""
    z = target - pos
    z = z / np.linalg.norm(z)
    x = np.cross(z, UP)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = pos
    return T


def trajectory(n: int) -> np.ndarray:
    """``n`` poses on a small circle at 1.4 m height, looking outwards and slightly down."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        pos = np.array([0.3 * np.cos(a), 0.3 * np.sin(a), 1.4])
        out.append(look_pose(pos, pos + np.array([np.cos(a + 0.3), np.sin(a + 0.3), -0.35])))
    return np.stack(out)


def intrinsics(w: int, h: int, f_scale: float = 0.9) -> np.ndarray:
    return np.array([[f_scale * w, 0, w / 2 - 0.3], [0, f_scale * w, h / 2 + 0.2], [0, 0, 1]])


def render_room(T: np.ndarray, K: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact depth (metres along z) and a colour image (checker on walls, by world position)."""
    u, v = np.meshgrid(np.arange(w) + 0.0, np.arange(h) + 0.0)
    d_c = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    d_w = T[:3, :3] @ d_c
    o = T[:3, 3:4]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d_w > 0, (ROOM_HI[:, None] - o) / d_w, (ROOM_LO[:, None] - o) / d_w)
    t[~np.isfinite(t)] = np.inf
    z = t.min(axis=0)
    p = o + d_w * z
    chk = (np.floor(p[0] / 0.5) + np.floor(p[1] / 0.5) + np.floor(p[2] / 0.5)) % 2
    axis = np.argmin(t, axis=0)
    base = np.array([[180, 60, 60], [60, 160, 60], [70, 70, 190]], dtype=np.float64)[axis]
    col = base * (0.6 + 0.4 * chk[:, None])
    return z.reshape(h, w).astype(np.float32), col.reshape(h, w, 3).astype(np.uint8)


def room_mesh(step: float = 0.25) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The room box as a triangle mesh (faces facing inwards), with vertex colours."""
    import trimesh

    m = trimesh.creation.box(extents=ROOM_HI - ROOM_LO)
    m.apply_translation((ROOM_HI + ROOM_LO) / 2)
    m = m.subdivide().subdivide()
    V = np.asarray(m.vertices)
    F = np.asarray(m.faces)[:, ::-1]
    C = np.full((len(V), 3), 150, np.uint8)
    return V, F, C


def write_mat(path: Path, M: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(" ".join(f"{x:.17g}" for x in row) for row in np.atleast_2d(M)) + "\n")


def write_png16(path: Path, depth_m: np.ndarray, scale: float = 1000.0) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.round(depth_m * scale).astype(np.uint16))


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), rgb[..., ::-1])


def write_7scenes(root: Path, n: int = 6, w: int = 64, h: int = 48, gravity: bool = False) -> dict:
    """A 7-Scenes folder; returns the truth (K, poses, ids)."""
    root.mkdir(parents=True, exist_ok=True)
    K = intrinsics(w, h)
    Ts = trajectory(n)
    write_mat(root / "camera-intrinsics.txt", K)
    if gravity:
        write_mat(root / "gravity-direction.txt", -UP[None])
    for k, T in enumerate(Ts):
        z, col = render_room(T, K, w, h)
        write_rgb(root / f"frame-{k:06d}.color.png", col)
        write_png16(root / f"frame-{k:06d}.depth.png", z)
        write_mat(root / f"frame-{k:06d}.pose.txt", T)
    return {"K": K, "T": Ts, "ids": np.arange(n)}


def write_3rscan(root: Path, n: int = 5, w: int = 96, h: int = 54, wd: int = 48, hd: int = 36) -> dict:
    seq = root / "sequence"
    seq.mkdir(parents=True, exist_ok=True)
    Kc, Kd = intrinsics(w, h, 0.8), intrinsics(wd, hd, 0.7)
    Ts = trajectory(n)
    flat = lambda K: " ".join(f"{x:.17g}" for x in (np.pad(K, ((0, 1), (0, 1))) + np.diag([0, 0, 0, 1.0])).ravel())  # noqa: E731
    (seq / "_info.txt").write_text(
        f"m_versionNumber = 4\nm_sensorName = StructureSensor\nm_colorWidth = {w}\nm_colorHeight = {h}\n"
        f"m_depthWidth = {wd}\nm_depthHeight = {hd}\nm_depthShift = 1000\n"
        f"m_calibrationColorIntrinsic = {flat(Kc)}\nm_calibrationColorExtrinsic = {flat(np.eye(3))}\n"
        f"m_calibrationDepthIntrinsic = {flat(Kd)}\nm_calibrationDepthExtrinsic = {flat(np.eye(3))}\n"
        f"m_frames.size = {n}\n")
    for k, T in enumerate(Ts):
        _, col = render_room(T, Kc, w, h)
        z, _ = render_room(T, Kd, wd, hd)
        write_rgb(seq / f"frame-{k:06d}.color.jpg", col)
        seq.joinpath(f"frame-{k:06d}.depth.pgm").parent.mkdir(exist_ok=True)
        cv2.imwrite(str(seq / f"frame-{k:06d}.depth.pgm"), np.round(z * 1000).astype(np.uint16))
        write_mat(seq / f"frame-{k:06d}.pose.txt", T)
    # textured OBJ mesh of the room
    V, F, _ = room_mesh()
    uv = (V[:, :2] - ROOM_LO[:2]) / (ROOM_HI - ROOM_LO)[:2]
    lines = ["mtllib mesh.refined.mtl", "usemtl mat0"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in V]
    lines += [f"vt {a:.6f} {b:.6f}" for a, b in uv]
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in F]
    (root / "mesh.refined.v2.obj").write_text("\n".join(lines) + "\n")
    (root / "mesh.refined.mtl").write_text("newmtl mat0\nKd 1 1 1\nmap_Kd mesh.refined_0.png\n")
    tex = np.zeros((16, 16, 3), np.uint8)
    tex[..., 1] = 200
    write_rgb(root / "mesh.refined_0.png", tex)
    return {"K": Kc, "Kd": Kd, "T": Ts, "ids": np.arange(n)}


def write_scannet(root: Path, n: int = 5, w: int = 96, h: int = 72, wd: int = 64, hd: int = 48,
                  invalid: tuple[int, ...] = (), mesh: bool = True) -> dict:
    Kc, Kd = intrinsics(w, h, 0.9), intrinsics(wd, hd, 0.9)
    Kd[0, 2] += 1.5  # different principal points: registration must use both
    Ts = trajectory(n)
    write_mat(root / "intrinsic" / "intrinsic_color.txt", np.pad(Kc, ((0, 1), (0, 1))) + np.diag([0, 0, 0, 1]))
    write_mat(root / "intrinsic" / "intrinsic_depth.txt", np.pad(Kd, ((0, 1), (0, 1))) + np.diag([0, 0, 0, 1]))
    write_mat(root / "intrinsic" / "extrinsic_color.txt", np.eye(4))
    write_mat(root / "intrinsic" / "extrinsic_depth.txt", np.eye(4))
    for k, T in enumerate(Ts):
        _, col = render_room(T, Kc, w, h)
        z, _ = render_room(T, Kd, wd, hd)
        write_rgb(root / "color" / f"{k}.jpg", col)
        write_png16(root / "depth" / f"{k}.png", z)
        write_mat(root / "pose" / f"{k}.txt", np.full((4, 4), -np.inf) if k in invalid else T)
    if mesh:
        import trimesh

        V, F, C = room_mesh()
        trimesh.Trimesh(V, F, vertex_colors=C, process=False).export(root / "scene0000_00_vh_clean_2.ply")
    keep = [k for k in range(n) if k not in invalid]
    return {"K": Kc, "Kd": Kd, "T": Ts[keep], "ids": np.array(keep)}


def write_transforms(root: Path, n: int = 5, w: int = 64, h: int = 48, depth: bool = True) -> dict:
    K = intrinsics(w, h)
    Ts = trajectory(n)
    frames = []
    for k, T in enumerate(Ts):
        z, col = render_room(T, K, w, h)
        write_rgb(root / "images" / f"frame_{k:05d}.png", col)
        fr = {"file_path": f"images/frame_{k:05d}.png",
              "transform_matrix": (T @ np.diag([1.0, -1.0, -1.0, 1.0])).tolist()}  # OpenCV -> OpenGL
        if depth:
            write_png16(root / "depths" / f"frame_{k:05d}.png", z)
            fr["depth_file_path"] = f"depths/frame_{k:05d}.png"
        frames.append(fr)
    # nerfstudio's pixel centres are at i + 0.5: its cx, cy are OpenCV's + 0.5
    doc = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + 0.5, "cy": K[1, 2] + 0.5, "w": w, "h": h,
           "camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(doc))
    return {"K": K, "T": Ts, "ids": np.arange(n)}


WRITERS = {"7scenes": write_7scenes, "3rscan": write_3rscan, "scannet": write_scannet,
           "transforms": write_transforms}


# ---------------------------------------------------------------------------------------------------
# Round trips
# ---------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("fmt", sorted(WRITERS))
def test_round_trip_every_layout(tmp_path, fmt):
    truth = WRITERS[fmt](tmp_path / "scan")
    assert detect_format(tmp_path / "scan") == fmt
    s = read_scan(tmp_path / "scan")
    assert s.format == fmt and s.num_frames == len(truth["ids"])
    np.testing.assert_array_equal(s.frame_ids, truth["ids"])
    np.testing.assert_allclose(s.K, np.broadcast_to(truth["K"], s.K.shape), atol=1e-6)
    np.testing.assert_allclose(s.T_c2w, truth["T"], atol=1e-6)
    c = read_color(s, 0)
    assert c.dtype == np.uint8 and c.shape == (s.height, s.width, 3)
    d = read_depth(s, 0)
    assert d.dtype == np.float32 and d.shape == (s.height, s.width)
    z, _ = render_room(truth["T"][0], truth["K"], s.width, s.height)
    err = np.abs(d - z)[d > 0]
    # registered depth of another resolution: nearest depth pixel, so errors only where depth changes fast
    assert np.median(err) < 0.01 and (d > 0).mean() > 0.95


def test_transforms_converts_opengl_axes(tmp_path):
    write_transforms(tmp_path, n=2, depth=False)
    doc = json.loads((tmp_path / "transforms.json").read_text())
    s = read_scan(tmp_path)
    T_gl = np.asarray(doc["frames"][0]["transform_matrix"])
    # OpenGL looks down -z with y up; OpenCV looks down +z with y down: same centre, flipped axes
    np.testing.assert_allclose(s.T_c2w[0][:3, 2], -T_gl[:3, 2], atol=1e-12)
    np.testing.assert_allclose(s.T_c2w[0][:3, 1], -T_gl[:3, 1], atol=1e-12)
    np.testing.assert_allclose(s.T_c2w[0][:3, 3], T_gl[:3, 3], atol=1e-12)
    assert s.depth_paths == ("", "")


def test_scannet_registration_uses_both_intrinsics(tmp_path):
    truth = write_scannet(tmp_path, n=1)
    s = read_scan(tmp_path)
    assert not s.depth_registered and (s.depth_width, s.depth_height) == (64, 48)
    z, _ = render_room(truth["T"][0], truth["K"], s.width, s.height)
    d = read_depth(s, 0)
    # wrong approach for comparison: resizing the depth image ignores the different principal points
    naive = cv2.resize(common.read_depth_raw(s, 0), (s.width, s.height), interpolation=cv2.INTER_NEAREST)
    assert np.median(np.abs(d - z)) <= np.median(np.abs(naive - z))
    assert np.median(np.abs(d - z)) < 0.005


def test_register_depth_identity_and_extrinsic():
    K = intrinsics(40, 30)
    d = np.full((30, 40), 2.0, np.float32)
    np.testing.assert_array_equal(register_depth(d, K, K, np.eye(4), 40, 30), d)
    # a depth camera 0.1 m to the left of the colour camera sees a fronto-parallel plane at the same depth
    T = np.eye(4)
    T[0, 3] = -0.1
    out = register_depth(d, K, K, T, 40, 30)
    assert np.allclose(out[out > 0], 2.0) and (out > 0).mean() > 0.8


def test_sevenscenes_gravity_file_points_down(tmp_path):
    write_7scenes(tmp_path, n=3, gravity=True)
    s = read_scan(tmp_path)
    np.testing.assert_allclose(s.up_w, UP, atol=1e-12)


def test_sevenscenes_frames_in_subfolder_and_65535_invalid(tmp_path):
    write_7scenes(tmp_path / "seq-01", n=3)
    (tmp_path / "seq-01" / "camera-intrinsics.txt").rename(tmp_path / "camera-intrinsics.txt")
    d = cv2.imread(str(tmp_path / "seq-01" / "frame-000000.depth.png"), cv2.IMREAD_UNCHANGED)
    d[0, 0] = 65535
    cv2.imwrite(str(tmp_path / "seq-01" / "frame-000000.depth.png"), d)
    s = read_scan(tmp_path)
    assert s.num_frames == 3 and read_depth(s, 0)[0, 0] == 0.0


def test_real_sevenscenes_sample_reads(shared_data):
    s = read_scan(shared_data / "scans" / "7scenes-redkitchen")
    assert s.format == "7scenes" and s.num_frames == 100 and (s.width, s.height) == (640, 480)
    np.testing.assert_allclose(s.K[0], [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    d = read_depth(s, 0)
    assert d.dtype == np.float32 and 0.3 < np.median(d[d > 0]) < 4.0
    assert abs(np.linalg.norm(s.up_w) - 1) < 1e-9


# ---------------------------------------------------------------------------------------------------
# Bad input: one test per case, each a clear InputError (or a counted warning where decided)
# ---------------------------------------------------------------------------------------------------

def test_unknown_format(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(InputError, match="unknown scan format.*scan.format"):
        detect_format(tmp_path)


def test_missing_folder(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        read_scan(tmp_path / "nope")


def test_missing_image_named_in_transforms(tmp_path):
    write_transforms(tmp_path, n=3)
    (tmp_path / "images" / "frame_00001.png").unlink()
    with pytest.raises(InputError, match=r"frame_00001\.png: colour image .* is missing"):
        read_scan(tmp_path)


def test_frame_without_colour_is_skipped_with_warning(tmp_path):
    write_7scenes(tmp_path, n=4)
    (tmp_path / "frame-000002.color.png").unlink()
    with pytest.warns(IngestWarning, match="skipped 1 of 4 frame.*no colour image"):
        s = read_scan(tmp_path)
    assert list(s.frame_ids) == [0, 1, 3] and s.meta["skipped"]["no_color"] == 1


# A bad image fails its own frame, not the scan: the reader names it in a warning and keeps it listed;
# decoding it raises (ingest leaves such frames out and reports them: tests/pipeline/test_e2e.py).

def test_unreadable_image(tmp_path):
    write_7scenes(tmp_path, n=3)
    (tmp_path / "frame-000001.color.png").write_bytes(b"not an image at all")
    with pytest.warns(IngestWarning, match=r"frame-000001\.color\.png: colour image cannot be read.*left out"):
        s = read_scan(tmp_path)
    assert (s.width, s.height) == (64, 48)
    with pytest.raises(InputError, match=r"frame-000001\.color\.png: colour image cannot be read"):
        read_color(s, 1)
    read_color(s, 0)


def test_scan_whose_every_image_is_unreadable_fails(tmp_path):
    write_7scenes(tmp_path, n=2)
    for k in range(2):
        (tmp_path / f"frame-00000{k}.color.png").write_bytes(b"junk")
    with pytest.warns(IngestWarning), pytest.raises(InputError, match=r"none of the scan's 2 colour images"):
        read_scan(tmp_path)


def test_truncated_image_fails_when_read(tmp_path):
    write_7scenes(tmp_path, n=2)
    p = tmp_path / "frame-000001.color.png"
    p.write_bytes(p.read_bytes()[:60])  # header intact, pixels gone
    try:
        s = read_scan(tmp_path)
    except InputError as e:  # caught up front is fine too
        assert "frame-000001.color.png" in str(e)
        return
    with pytest.raises(InputError, match=r"frame-000001\.color\.png: colour image cannot be read"):
        read_color(s, 1)


def test_depth_wrong_size(tmp_path):
    write_7scenes(tmp_path, n=3)
    write_png16(tmp_path / "frame-000001.depth.png", np.ones((10, 12)))
    with pytest.warns(IngestWarning, match=r"frame-000001\.depth\.png: depth image is 12x10, expected 64x48"):
        s = read_scan(tmp_path)
    with pytest.raises(InputError, match=r"frame-000001\.depth\.png: depth map is 12x10, expected 64x48"):
        read_depth(s, 1)


def test_depth_wrong_dtype(tmp_path):
    write_7scenes(tmp_path, n=3)
    cv2.imwrite(str(tmp_path / "frame-000002.depth.png"), np.full((48, 64), 7, np.uint8))
    with pytest.warns(IngestWarning, match=r"frame-000002\.depth\.png: depth image has pixel type 'L'.*16-bit"):
        s = read_scan(tmp_path)
    with pytest.raises(InputError, match=r"frame-000002\.depth\.png: depth image is uint8.*16-bit"):
        read_depth(s, 2)


def test_pose_with_nan_is_skipped_with_warning(tmp_path):
    write_7scenes(tmp_path, n=4)
    write_mat(tmp_path / "frame-000001.pose.txt", np.full((4, 4), np.nan))
    with pytest.warns(IngestWarning, match="skipped 1 of 4 frame.*non-finite"):
        s = read_scan(tmp_path)
    assert list(s.frame_ids) == [0, 2, 3] and s.meta["skipped"]["invalid_pose"] == 1


def test_scannet_inf_poses_are_skipped_and_counted(tmp_path):
    write_scannet(tmp_path, n=6, invalid=(1, 4))
    with pytest.warns(IngestWarning, match="skipped 2 of 6"):
        s = read_scan(tmp_path)
    assert list(s.frame_ids) == [0, 2, 3, 5] and s.meta["skipped"]["invalid_pose"] == 2


def test_all_poses_invalid(tmp_path):
    write_scannet(tmp_path, n=2, invalid=(0, 1))
    with pytest.warns(IngestWarning), pytest.raises(
            InputError, match=r"no usable frame: 0 of 2 frame number\(s\) seen .*\(2 have a non-finite"):
        read_scan(tmp_path)


def test_pose_not_rigid_costs_only_its_frame(tmp_path):
    """A scaled rotation (det 1.33) is one bad frame: skipped and named, the others are kept."""
    truth = write_7scenes(tmp_path, n=3)
    T = trajectory(3)[1]
    T[:3, :3] *= 1.1
    write_mat(tmp_path / "frame-000001.pose.txt", T)
    with pytest.warns(IngestWarning, match=r"skipped 1 of 3 frame\(s\) that have a malformed pose or one that "
                                           r"is not a rigid transform \(first: frame 1: .*frame-000001\.pose\.txt: "
                                           r"pose is not a rigid transform \(det R = 1\.33"):
        s = read_scan(tmp_path)
    assert list(s.frame_ids) == [0, 2] and s.meta["skipped"]["bad_pose"] == 1
    np.testing.assert_allclose(s.T_c2w, truth["T"][[0, 2]], atol=1e-9)


def test_pose_not_orthonormal_costs_only_its_frame(tmp_path):
    write_7scenes(tmp_path, n=3)
    T = trajectory(3)[2]
    T[0, 1] += 0.2  # shear
    write_mat(tmp_path / "frame-000002.pose.txt", T)
    with pytest.warns(IngestWarning, match=r"frame 2: .*not a rigid transform \(det R = .*\|R\^T R - I\| = 1\.95e-01"):
        s = read_scan(tmp_path)
    assert list(s.frame_ids) == [0, 1]


def test_pose_malformed_costs_only_its_frame(tmp_path):
    write_7scenes(tmp_path, n=3)
    (tmp_path / "frame-000000.pose.txt").write_text("1 0 0\n0 1 0\n")
    with pytest.warns(IngestWarning, match=r"frame-000000\.pose\.txt: pose must hold 4x4 = 16 numbers, found 6"):
        s = read_scan(tmp_path)
    assert list(s.frame_ids) == [1, 2]


def test_scan_with_every_pose_broken_says_how_much_was_usable(tmp_path):
    write_7scenes(tmp_path, n=3)
    for k in range(3):
        T = trajectory(3)[k]
        T[:3, :3] *= 2.0
        write_mat(tmp_path / f"frame-{k:06d}.pose.txt", T)
    with pytest.warns(IngestWarning), pytest.raises(
            InputError, match=r"no usable frame: 0 of 3 frame number\(s\) seen .*\(3 have a malformed pose"):
        read_scan(tmp_path)


def test_transforms_json_non_rigid_pose_costs_only_its_frame(tmp_path):
    write_transforms(tmp_path, n=4)
    doc = json.loads((tmp_path / "transforms.json").read_text())
    M = np.asarray(doc["frames"][2]["transform_matrix"])
    M[:3, :3] *= 0.5
    doc["frames"][2]["transform_matrix"] = M.tolist()
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    with pytest.warns(IngestWarning, match=r"skipped 1 of 4 frame\(s\) that have a pose that is not a rigid "
                                           r"transform \(first: .*frame 2"):
        s = read_scan(tmp_path)
    assert list(s.frame_ids) == [0, 1, 3] and s.meta["skipped"]["bad_pose"] == 1


def test_frame_numbering_gaps_are_kept_with_warning(tmp_path):
    write_7scenes(tmp_path, n=6)
    for k in (3, 4):
        for kind in ("color.png", "depth.png", "pose.txt"):
            (tmp_path / f"frame-{k:06d}.{kind}").unlink()
    with pytest.warns(IngestWarning, match="frame numbering is irregular.*after frame 2"):
        s = read_scan(tmp_path)
    assert list(s.frame_ids) == [0, 1, 2, 5]


def test_regular_subsampled_numbering_is_silent(tmp_path):
    truth = write_7scenes(tmp_path, n=3)
    for k in (2, 1):  # renumber 0, 1, 2 -> 0, 10, 20 (like the real sample: every 10th frame)
        for kind in ("color.png", "depth.png", "pose.txt"):
            (tmp_path / f"frame-{k:06d}.{kind}").rename(tmp_path / f"frame-{10 * k:06d}.{kind}")
    s = read_scan(tmp_path)  # filterwarnings=error: any warning fails
    assert list(s.frame_ids) == [0, 10, 20]
    np.testing.assert_allclose(s.T_c2w, truth["T"], atol=1e-9)


def test_count_mismatch_missing_pose_and_depth(tmp_path):
    write_7scenes(tmp_path, n=5)
    (tmp_path / "frame-000001.pose.txt").unlink()
    (tmp_path / "frame-000003.depth.png").unlink()
    with pytest.warns(IngestWarning) as rec:
        s = read_scan(tmp_path)
    msgs = " | ".join(str(w.message) for w in rec)
    assert "no pose file" in msgs and "no depth map" in msgs
    assert list(s.frame_ids) == [0, 2, 4]
    assert s.meta["skipped"] == {"no_color": 0, "no_depth": 1, "no_pose": 1, "invalid_pose": 0, "bad_pose": 0}


def test_intrinsics_missing(tmp_path):
    write_7scenes(tmp_path, n=2)
    (tmp_path / "camera-intrinsics.txt").unlink()
    with pytest.raises(InputError, match="camera-intrinsics.txt is missing; write the 3x3"):
        read_scan(tmp_path)


def test_intrinsics_zero_focal(tmp_path):
    write_7scenes(tmp_path, n=2)
    write_mat(tmp_path / "camera-intrinsics.txt", np.array([[0, 0, 32], [0, 0, 24], [0, 0, 1.0]]))
    with pytest.raises(InputError, match=r"camera-intrinsics\.txt: intrinsics have a zero.*focal length"):
        read_scan(tmp_path)


def test_scannet_intrinsics_missing(tmp_path):
    write_scannet(tmp_path, n=2)
    (tmp_path / "intrinsic" / "intrinsic_depth.txt").unlink()
    with pytest.raises(InputError, match=r"intrinsic_depth\.txt: depth intrinsics file is missing"):
        read_scan(tmp_path)


def test_transforms_intrinsics_missing(tmp_path):
    write_transforms(tmp_path, n=2)
    doc = json.loads((tmp_path / "transforms.json").read_text())
    for k in ("fl_x", "fl_y"):
        doc.pop(k)
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="intrinsics missing: add 'fl_x'"):
        read_scan(tmp_path)


def test_3rscan_info_incomplete(tmp_path):
    write_3rscan(tmp_path, n=2)
    info = tmp_path / "sequence" / "_info.txt"
    info.write_text("\n".join(li for li in info.read_text().splitlines() if "DepthIntrinsic" not in li))
    with pytest.raises(InputError, match=r"_info\.txt: missing or non-numeric m_calibrationDepthIntrinsic"):
        read_scan(tmp_path)


def test_multiple_sequences_need_one_folder_each(tmp_path):
    write_7scenes(tmp_path / "seq-01", n=2)
    write_7scenes(tmp_path / "seq-02", n=2)
    with pytest.raises(InputError, match="holds 2 sequences.*one sequence folder"):
        read_scan(tmp_path, "7scenes")


# ---------------------------------------------------------------------------------------------------
# Scans written by the project's synthetic scan generator (issue 4)
# ---------------------------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("layout", sorted(WRITERS))
def test_round_trip_synthscan_layouts(tmp_path, layout):
    """Each layout written by pipeline.synthscan gives back its true intrinsics, poses and frame count."""
    synth = pytest.importorskip("pipeline.synthscan")
    import warnings

    from pipeline.io import load_npz, read_json

    out = Path(synth.make_scan(tmp_path / layout, layout=layout, seed=2, width=96, height=72, frames=6))
    truth = load_npz(out / "ground_truth" / "cameras.npz")
    doc = read_json(out / "ground_truth" / "scan.json")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IngestWarning)  # a generated lost-tracking frame is skipped
        s = read_scan(out)
    valid = truth["pose_valid"].astype(bool)
    assert s.num_frames == int(valid.sum())
    np.testing.assert_array_equal(s.frame_ids, truth["frame_ids"][valid])
    np.testing.assert_allclose(s.K, np.broadcast_to(truth["K"], s.K.shape), atol=1e-6)
    np.testing.assert_allclose(s.T_c2w, truth["T_c2w"][valid], atol=1e-6)
    assert (s.width, s.height) == (doc["width"], doc["height"])
    d = read_depth(s, 0)
    assert d.shape == (s.height, s.width) and np.median(d[d > 0]) > 0.3
    # the up direction: 7-Scenes from gravity-direction.txt, the others from their mesh's floor
    up_true = np.asarray(doc["up_w"], dtype=np.float64)
    if s.mesh_path:
        from pipeline.reconstruct import floor_up
        from pipeline.scanformats.mesh import load_mesh_file

        V, F, _ = load_mesh_file(s.mesh_path)
        up, _ = floor_up(V, F, s.T_c2w)
    else:
        up = s.up_w
    assert np.degrees(np.arccos(np.clip(up @ up_true, -1, 1))) < 1.0


def test_transforms_malformed_matrix(tmp_path):
    write_transforms(tmp_path, n=2, depth=False)
    doc = json.loads((tmp_path / "transforms.json").read_text())
    doc["frames"][1]["transform_matrix"] = [[1, 0, 0], ["a", 1, 0]]
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="frame 1 transform_matrix is not a 4x4 list of numbers"):
        read_scan(tmp_path)
