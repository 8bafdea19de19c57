"""Procedural scenes and an independent ray caster shared by the raster and export tests."""

from __future__ import annotations

import numpy as np

from tests.support.reference import iou, raycast  # noqa: F401  (the tests' independent reference renderer)
from pipeline.geometry import look_at
from pipeline.runfolder import RASTER_TPATH, read_raster_frame
from pipeline.types import ObjectModel, Placement


def load_frame(stem) -> tuple[dict, dict | None]:
    """``(JSON document, arrays or None for a rejected frame)`` of a saved raster frame."""
    rf = read_raster_frame(stem)
    return rf.doc, (rf.arrays() if rf.status == "ok" else None)

W_RUN, H_RUN = 160, 120


def intrinsics(width: int, height: int, f: float) -> np.ndarray:
    return np.array([[f, 0.0, (width - 1) / 2 + 0.3], [0.0, f, (height - 1) / 2 - 0.2], [0.0, 0.0, 1.0]])


def box_mesh(size, center=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.box(extents=size)
    return np.asarray(m.vertices) + np.asarray(center), np.asarray(m.faces, dtype=np.int32)


def merge(*meshes) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, off = [], [], 0
    for v, f in meshes:
        vs.append(v)
        fs.append(f + off)
        off += len(v)
    return np.concatenate(vs), np.concatenate(fs).astype(np.int32)


def room_mesh(with_legs: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A 4 x 4 x 2.5 m room (floor, four walls, no ceiling) with a table; legs optional (thin parts)."""
    parts = [box_mesh((4.0, 4.0, 0.02), (0, 0, -0.01)),
             box_mesh((4.0, 0.02, 2.5), (0, 2.0, 1.25)), box_mesh((4.0, 0.02, 2.5), (0, -2.0, 1.25)),
             box_mesh((0.02, 4.0, 2.5), (2.0, 0, 1.25)), box_mesh((0.02, 4.0, 2.5), (-2.0, 0, 1.25)),
             box_mesh((0.8, 0.5, 0.04), (0.4, 0.3, 0.72))]
    if with_legs:
        for sx in (-1, 1):
            for sy in (-1, 1):
                parts.append(box_mesh((0.03, 0.03, 0.70), (0.4 + sx * 0.36, 0.3 + sy * 0.21, 0.35)))
    return merge(*parts)


def make_object(obj_id: int, kind: str) -> ObjectModel:
    import trimesh

    if kind == "sphere":
        m = trimesh.creation.icosphere(subdivisions=3, radius=0.08)
    elif kind == "box":
        m = trimesh.creation.box(extents=(0.16, 0.10, 0.07))
    elif kind == "torus":
        m = trimesh.creation.torus(major_radius=0.07, minor_radius=0.025)
    elif kind == "cylinder":
        m = trimesh.creation.cylinder(radius=0.04, height=0.18, sections=32)
    else:
        raise ValueError(kind)
    v = np.asarray(m.vertices, dtype=np.float64)
    info = {"diameter": float(np.max(np.linalg.norm(v[:, None] - v[None], axis=-1))) if len(v) < 2000 else 0.0}
    return ObjectModel(obj_id=obj_id, name=kind, source_path=f"/procedural/{kind}", vertices=v,
                       faces=np.asarray(m.faces, dtype=np.int32),
                       normals=np.asarray(m.vertex_normals, dtype=np.float32),
                       vertex_colors=None, uv=None, texture=None, info=info)


def rot(axis, angle) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis) * angle).as_matrix()


def library() -> list[ObjectModel]:
    return [make_object(1, "sphere"), make_object(2, "box"), make_object(3, "torus"), make_object(4, "cylinder")]


def placement(scene: str = "room", drop: int = 0) -> Placement:
    """Objects on the floor and on the table: two overlap, one is cut by the image border, one is behind a
    table leg, one is under the table top."""
    ids = [1, 2, 3, 4, 2, 1, 2]
    Rs = [np.eye(3), rot((0, 0, 1), 0.6), rot((1, 0, 0), 1.2), rot((0, 1, 0), 1.5707963), rot((1, 1, 0), 0.4),
          np.eye(3), rot((0, 0, 1), 1.2)]
    ts = [(0.0, 0.0, 0.08), (0.12, 0.05, 0.035), (0.35, 0.25, 0.79), (-0.3, 0.3, 0.04), (0.45, 0.35, 0.05),
          (-0.7, -0.32, 0.08), (0.05, 0.36, 0.035)]
    n = len(ids)
    return Placement(scene=scene, drop=drop, obj_ids=np.asarray(ids, np.int32), R_m2w=np.asarray(Rs),
                     t_m2w=np.asarray(ts, dtype=np.float64), at_rest=np.ones(n, bool), max_penetration=0.0,
                     verdict="accepted")


def camera(width: int = 320, height: int = 240) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics and pose seeing the objects; the last instance is cut by the image's left border."""
    K = intrinsics(width, height, 0.9 * width)
    T = look_at((0.1, -1.3, 1.1), (0.05, 0.2, 0.25))
    return K, T


def posed(obj: ObjectModel, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return obj.vertices @ np.asarray(R).T + np.asarray(t), obj.faces


# ---------------------------------------------------------------------------------------------------
# Independent reference: Open3D ray casting through OpenCV pixel centres
# ---------------------------------------------------------------------------------------------------

# ---------------------------------------------------------------------------------------------------
# A run folder as ingest writes it (scan + library), without running TSDF fusion
# ---------------------------------------------------------------------------------------------------

def make_run(run_dir, rasterizer, *, width: int = W_RUN, height: int = H_RUN, frames: int = 3,
             drops: int = 2) -> dict:
    """Write ``RUN/ingest/room`` (photos, real depth with the table legs, room mesh WITHOUT them),
    ``RUN/ingest/objects`` and a poses file with ``drops`` placements; return paths and the truth."""
    from pathlib import Path

    import cv2

    from pipeline.runfolder import save_scan
    from pipeline.objects import save_library
    from pipeline.raster import save_poses_file
    from pipeline.scanformats.mesh import ply_bytes
    from pipeline.io import atomic_write_bytes
    from pipeline.types import Scan

    run = Path(run_dir)
    scene_dir = run / "ingest" / "room"
    raw = run / "rawscan"
    raw.mkdir(parents=True, exist_ok=True)
    truth = room_mesh(with_legs=True)
    scan_mesh = room_mesh(with_legs=False)
    rasterizer.add_mesh("make-run-truth", *truth)
    K, T0 = camera(width, height)
    Ts, colors, depths = [], [], []
    for i in range(frames):
        T = look_at((0.1 + 0.08 * i, -1.3, 1.1), (0.05, 0.2, 0.25))
        d = rasterizer.render_depth(K, T, width, height, [("make-run-truth", np.eye(4))])
        img = np.zeros((height, width, 3), np.uint8)
        img[..., 0] = np.clip(d * 60, 0, 255).astype(np.uint8)
        img[..., 1] = (np.arange(width)[None] * 255 // width).astype(np.uint8)
        img[..., 2] = 90
        cpath, dpath = raw / f"frame-{i:06d}.color.png", raw / f"frame-{i:06d}.depth.png"
        cv2.imwrite(str(cpath), img[..., ::-1])
        cv2.imwrite(str(dpath), np.round(d * 1000).astype(np.uint16))
        Ts.append(T)
        colors.append(str(cpath))
        depths.append(str(dpath))
    mesh_path = scene_dir / "room.ply"
    atomic_write_bytes(mesh_path, ply_bytes(scan_mesh[0], scan_mesh[1], None))
    scan = Scan(name="room", root=str(raw), format="7scenes", frame_ids=np.arange(frames, dtype=np.int64) * 10,
                color_paths=tuple(colors), depth_paths=tuple(depths), width=width, height=height,
                K=np.repeat(K[None], frames, 0), T_c2w=np.asarray(Ts), depth_width=width, depth_height=height,
                depth_K=np.repeat(K[None], frames, 0), depth_scale=0.001, depth_registered=True,
                up_w=np.array([0.0, 0.0, 1.0]), mesh_path=str(mesh_path), meta={})
    save_scan(scene_dir, scan)
    lib = library()
    save_library(run / "ingest" / "objects", lib)
    pls = [placement(scene="room", drop=d) for d in range(drops)]
    if drops > 1:  # second drop: the objects shifted along x
        for d in range(1, drops):
            pls[d] = Placement(scene="room", drop=d, obj_ids=pls[d].obj_ids, R_m2w=pls[d].R_m2w,
                               t_m2w=pls[d].t_m2w + np.array([0.03 * d, 0.0, 0.0]), at_rest=pls[d].at_rest,
                               max_penetration=0.0, verdict="accepted")
    poses = save_poses_file(run.parent / f"{run.name}-poses.json", pls)
    return {"poses": poses, "scan": scan, "library": lib, "placements": pls, "truth": truth}


def run_stage_direct(stage, run_dir, cfg) -> dict:
    """Run a stage's items in this process (plan, run_item, finish), as the runner does with one worker."""
    from pipeline.stages import StageContext

    ctx = StageContext(run_dir=run_dir, cfg=cfg, stage=stage.name)
    results = {}
    for item in stage.plan(ctx):
        results[item.key] = stage.run_item(ctx, item) or {}
    if stage.finish is not None:
        stage.finish(ctx, results)
    return results


def write_composites(run_dir, skip=()) -> list:
    """Stand-in for the composite stage's colour output (it needs the path tracer): for each raster frame
    with status ok, ``RUN/composite/<scene>/drop<NNNN>/f<frame>.png`` = the photo with the visible object
    pixels painted magenta. Frames ``(scene, drop, frame)`` in ``skip`` get none. Returns the paths."""
    from pathlib import Path

    import cv2

    from pipeline.runfolder import COMPOSITE_TPATH, load_scan, raster_frames
    from pipeline.scanformats.common import read_color

    run_dir = Path(run_dir)
    out = []
    for key in raster_frames(run_dir):
        scene, drop, frame = key
        if (scene, drop, frame) in skip:
            continue
        doc, arr = load_frame(key.path(run_dir, RASTER_TPATH))
        rgb = read_color(load_scan(run_dir, scene), frame)
        rgb = cv2.resize(rgb, (int(doc["width"]), int(doc["height"])), interpolation=cv2.INTER_AREA)
        obj = arr["labels"] > 0
        rgb[obj] = (0.3 * rgb[obj] + 0.7 * np.array([200, 40, 200])).astype(np.uint8)
        p = key.path(run_dir, COMPOSITE_TPATH)
        p.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(p), np.ascontiguousarray(rgb[..., ::-1]))
        out.append(p)
    return out
