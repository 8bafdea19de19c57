"""Microsoft 7-Scenes layout.

Files (in the scan folder, or in its single sub-folder of frames such as ``seq-01/`` or ``frames/``)::

    frame-XXXXXX.color.png|jpg   colour, 640x480
    frame-XXXXXX.depth.png       uint16 millimetres, 0 and 65535 = invalid
    frame-XXXXXX.pose.txt        4x4 camera-to-world, metres, OpenCV camera axes
    camera-intrinsics.txt        3x3 K (the same K for colour and depth)
    gravity-direction.txt        optional: unit gravity vector (pointing down) in the world frame

No mesh is shipped: ingest reconstructs one. The one K and the poses are the depth camera's; the
Kinect v1's colour camera (shorter focal length, a few centimetres away) is not calibrated in this
dataset. This reader gives the depth camera's K to both; ingest then estimates the colour camera from
the frames (:func:`pipeline.registration.register_scan`) and records the result in ``scan.json``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.errors import InputError
from pipeline.scanformats.common import (check_image_sizes, check_intrinsics, index_files, match_frames,
                                         read_frame_poses, read_matrix, read_numbers)
from pipeline.types import Scan

FORMAT = "7scenes"
COLOR_RX = r"frame-(\d+)\.color\.(?:png|jpg|jpeg)"
DEPTH_RX = r"frame-(\d+)\.depth\.png"
POSE_RX = r"frame-(\d+)\.pose\.txt"


def frames_dir(root: Path) -> Path | None:
    """The folder holding the ``frame-*`` files: ``root`` itself or its one sub-folder that has them."""
    if index_files(root, COLOR_RX) or index_files(root, POSE_RX):
        return root
    subs = sorted(p for p in root.iterdir() if p.is_dir() and (index_files(p, COLOR_RX) or index_files(p, POSE_RX)))
    if len(subs) > 1:
        raise InputError(f"{root}: holds {len(subs)} sequences of frames ({', '.join(p.name for p in subs[:4])}); "
                         f"name one sequence folder per entry of scan.paths")
    return subs[0] if subs else None


def looks_like(root: Path) -> bool:
    try:
        return frames_dir(root) is not None
    except InputError:
        return True


def _find(root: Path, fdir: Path, name: str) -> Path | None:
    for d in (fdir, root):
        if (d / name).is_file():
            return d / name
    return None


def read(root: Path) -> Scan:
    """Read a 7-Scenes scan folder; see the module docstring for the layout."""
    root = Path(root)
    fdir = frames_dir(root)
    if fdir is None:
        raise InputError(f"{root}: no frame-XXXXXX.color.png|jpg / .pose.txt files found (7-Scenes layout)")
    colors = index_files(fdir, COLOR_RX)
    depths = index_files(fdir, DEPTH_RX)
    pose_files = index_files(fdir, POSE_RX)
    kpath = _find(root, fdir, "camera-intrinsics.txt")
    if kpath is None:
        raise InputError(f"{root}: camera-intrinsics.txt is missing; write the 3x3 colour intrinsics there "
                         f"(7-Scenes Kinect: '585 0 320 / 0 585 240 / 0 0 1')")
    K = read_matrix(kpath, 3, 3, "intrinsics")
    poses = read_frame_poses(pose_files)
    kept, skipped = match_frames(root, colors, depths, poses, pose_files)
    cpaths = [str(colors[i].resolve()) for i in kept]
    dpaths = [str(depths[i].resolve()) for i in kept]
    w, h = check_image_sizes(cpaths, None, "colour")
    check_intrinsics(K, w, h, kpath)
    check_image_sizes(dpaths, (w, h), "depth", depth=True)
    up = np.zeros(3)
    # Relative to the scan root: scan.json must not depend on where the scan (or the run) lives.
    meta: dict = {"skipped": skipped, "intrinsics_file": Path(os.path.relpath(kpath, root)).as_posix(),
                  "registration": "7-Scenes ships the depth camera's K only: used for colour too"}
    gpath = _find(root, fdir, "gravity-direction.txt")
    if gpath is not None:
        g = read_numbers(gpath, "gravity direction")
        if g.size != 3 or not np.all(np.isfinite(g)) or np.linalg.norm(g) < 1e-6:
            raise InputError(f"{gpath}: gravity direction must be 3 finite numbers of a non-zero vector, "
                             f"found {g.tolist()}; fix or delete the file (up is then found from the floor)")
        # The file holds the direction gravity pulls (down), checked on redkitchen against the floor.
        up = -g / np.linalg.norm(g)
        meta["up_source"] = f"metadata: {gpath.name} (negated: the file points down)"
    F = len(kept)
    T = np.stack([poses[i] for i in kept])
    Ks = np.repeat(K[None], F, axis=0)
    return Scan(name=root.name, root=str(root.resolve()), format=FORMAT,
                frame_ids=np.asarray(kept, dtype=np.int64), color_paths=tuple(cpaths), depth_paths=tuple(dpaths),
                width=w, height=h, K=Ks, T_c2w=T, depth_width=w, depth_height=h, depth_K=Ks.copy(),
                depth_scale=0.001, depth_registered=False, up_w=up, mesh_path="", meta=meta)
