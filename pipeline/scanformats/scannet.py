"""ScanNet layout as exported by its SensReader (``reader.py --export_color_images ...``).

Files::

    color/N.jpg                      colour, 1296x968
    depth/N.png                      uint16 millimetres, 640x480
    pose/N.txt                       4x4 camera-to-world, metres; lost tracking = rows of -inf
    intrinsic/intrinsic_color.txt    4x4 (upper-left 3x3 = K of the colour camera)
    intrinsic/intrinsic_depth.txt    4x4 (K of the depth camera)
    intrinsic/extrinsic_color.txt    optional 4x4 (camera to rig; identity in ScanNet)
    intrinsic/extrinsic_depth.txt    optional 4x4
    sceneXXXX_XX_vh_clean_2.ply      optional mesh with vertex colours, metres, world frame

Depth is registered to colour with both intrinsics (``T_d2c = inv(E_color) @ E_depth``). Frames whose
pose holds ``-inf`` are skipped with a counted warning.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import InputError
from pipeline.scanformats.common import (check_extrinsic, check_image_sizes, check_intrinsics, index_files,
                                         match_frames, read_frame_poses, read_matrix)
from pipeline.types import Scan

FORMAT = "scannet"


def looks_like(root: Path) -> bool:
    return (root / "color").is_dir() and (root / "pose").is_dir()


def _mesh(root: Path) -> Path | None:
    for pat in ("*_vh_clean_2.ply", "*_vh_clean.ply"):
        found = sorted(root.glob(pat))
        if found:
            return found[0]
    return None


def read(root: Path) -> Scan:
    """Read an exported ScanNet scan folder; see the module docstring for the layout."""
    root = Path(root)
    colors = index_files(root / "color", r"(\d+)\.(?:jpg|jpeg|png)")
    depths = index_files(root / "depth", r"(\d+)\.png")
    pose_files = index_files(root / "pose", r"(\d+)\.txt")
    intr = root / "intrinsic"
    Kc4 = read_matrix(intr / "intrinsic_color.txt", 4, 4, "colour intrinsics")
    Kd4 = read_matrix(intr / "intrinsic_depth.txt", 4, 4, "depth intrinsics")
    Ec = read_matrix(intr / "extrinsic_color.txt", 4, 4, "colour extrinsics") \
        if (intr / "extrinsic_color.txt").is_file() else np.eye(4)
    Ed = read_matrix(intr / "extrinsic_depth.txt", 4, 4, "depth extrinsics") \
        if (intr / "extrinsic_depth.txt").is_file() else np.eye(4)
    poses = read_frame_poses(pose_files)
    kept, skipped = match_frames(root, colors, depths, poses, pose_files)
    cpaths = [str(colors[i].resolve()) for i in kept]
    dpaths = [str(depths[i].resolve()) for i in kept]
    w, h = check_image_sizes(cpaths, None, "colour")
    wd, hd = check_image_sizes(dpaths, None, "depth", depth=True)
    Kc = check_intrinsics(Kc4[:3, :3], w, h, intr / "intrinsic_color.txt")
    Kd = check_intrinsics(Kd4[:3, :3], wd, hd, intr / "intrinsic_depth.txt")
    Ec = check_extrinsic(Ec, intr / "extrinsic_color.txt", "colour extrinsics")
    Ed = check_extrinsic(Ed, intr / "extrinsic_depth.txt", "depth extrinsics")
    T_d2c = np.linalg.inv(Ec) @ Ed
    mesh = _mesh(root)
    F = len(kept)
    registered = (w, h) == (wd, hd) and np.allclose(Kc, Kd) and np.allclose(T_d2c, np.eye(4))
    meta = {"skipped": skipped, "T_d2c": T_d2c.tolist(),
            "registration": "depth resampled into the colour camera with intrinsic_depth and "
                            "intrinsic_color (same centre and axes)"}
    return Scan(name=root.name, root=str(root.resolve()), format=FORMAT,
                frame_ids=np.asarray(kept, dtype=np.int64), color_paths=tuple(cpaths), depth_paths=tuple(dpaths),
                width=w, height=h, K=np.repeat(Kc[None], F, axis=0), T_c2w=np.stack([poses[i] for i in kept]),
                depth_width=wd, depth_height=hd, depth_K=np.repeat(Kd[None], F, axis=0),
                depth_scale=0.001, depth_registered=bool(registered), up_w=np.zeros(3),
                mesh_path=str(mesh.resolve()) if mesh else "", meta=meta)
