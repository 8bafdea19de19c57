"""3RScan layout.

Files::

    mesh.refined.v2.obj (+ .mtl + texture)   the scan's textured mesh, metres, world frame
    sequence/_info.txt                        sizes, intrinsics, extrinsics, depth shift (see below)
    sequence/frame-XXXXXX.color.jpg           colour (e.g. 960x540)
    sequence/frame-XXXXXX.depth.pgm           uint16 depth, ``value / m_depthShift`` metres
    sequence/frame-XXXXXX.pose.txt            4x4 camera-to-world, metres

``_info.txt`` lines are ``key = values``: ``m_colorWidth``, ``m_colorHeight``, ``m_depthWidth``,
``m_depthHeight``, ``m_depthShift``, ``m_calibrationColorIntrinsic`` and
``m_calibrationDepthIntrinsic`` (4x4 row-major), optionally ``m_calibrationColorExtrinsic`` and
``m_calibrationDepthExtrinsic`` (4x4, camera to the sensor rig; identity in the public release).
Colour and depth have different resolutions and intrinsics; depth is registered to colour with both
intrinsics and ``T_d2c = inv(E_color) @ E_depth``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pipeline.errors import InputError
from pipeline.scanformats.common import (check_extrinsic, check_image_sizes, check_intrinsics, index_files,
                                         match_frames, read_frame_poses, read_matrix)
from pipeline.types import Scan

FORMAT = "3rscan"
COLOR_RX = r"frame-(\d+)\.color\.(?:jpg|jpeg|png)"
DEPTH_RX = r"frame-(\d+)\.depth\.pgm"
POSE_RX = r"frame-(\d+)\.pose\.txt"
MESH_NAMES = ("mesh.refined.v2.obj", "mesh.refined.obj")
REQUIRED = ("m_colorWidth", "m_colorHeight", "m_depthWidth", "m_depthHeight", "m_depthShift",
            "m_calibrationColorIntrinsic", "m_calibrationDepthIntrinsic")


def _seq_dir(root: Path) -> Path:
    return root / "sequence" if (root / "sequence").is_dir() else root


def looks_like(root: Path) -> bool:
    seq = _seq_dir(root)
    return (seq / "_info.txt").is_file() or bool(index_files(seq, DEPTH_RX))


def parse_info(path: Path) -> dict[str, list[float]]:
    """``key = numbers`` lines of a 3RScan ``_info.txt`` (non-numeric values are kept as text)."""
    if not path.is_file():
        raise InputError(f"{path}: _info.txt is missing; it holds the 3RScan intrinsics and image sizes: "
                         f"restore it from the scan's sequence.zip")
    out: dict = {}
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        if "=" not in line:
            continue
        k, v = (s.strip() for s in line.split("=", 1))
        try:
            out[k] = [float(t) for t in v.split()]
        except ValueError:
            out[k] = v
    missing = [k for k in REQUIRED if k not in out or isinstance(out[k], str)]
    if missing:
        raise InputError(f"{path}: missing or non-numeric {', '.join(missing)}; restore _info.txt from the "
                         f"scan's sequence.zip")
    return out


def _mat4(info: dict, key: str, path: Path) -> np.ndarray:
    v = info.get(key)
    if v is None:
        return np.eye(4)
    if isinstance(v, str) or len(v) != 16:
        raise InputError(f"{path}: {key} must hold 16 numbers (4x4 row-major), found {v!r}")
    return np.asarray(v, dtype=np.float64).reshape(4, 4)


def read(root: Path) -> Scan:
    """Read a 3RScan scan folder; see the module docstring for the layout."""
    root = Path(root)
    seq = _seq_dir(root)
    ipath = seq / "_info.txt"
    info = parse_info(ipath)
    w, h = int(info["m_colorWidth"][0]), int(info["m_colorHeight"][0])
    wd, hd = int(info["m_depthWidth"][0]), int(info["m_depthHeight"][0])
    shift = float(info["m_depthShift"][0])
    if shift <= 0:
        raise InputError(f"{ipath}: m_depthShift = {shift} must be > 0 (depth units per metre, usually 1000)")
    Kc = check_intrinsics(_mat4(info, "m_calibrationColorIntrinsic", ipath)[:3, :3], w, h, ipath)
    Kd = check_intrinsics(_mat4(info, "m_calibrationDepthIntrinsic", ipath)[:3, :3], wd, hd, ipath)
    Ec = check_extrinsic(_mat4(info, "m_calibrationColorExtrinsic", ipath), ipath, "m_calibrationColorExtrinsic")
    Ed = check_extrinsic(_mat4(info, "m_calibrationDepthExtrinsic", ipath), ipath, "m_calibrationDepthExtrinsic")
    T_d2c = np.linalg.inv(Ec) @ Ed
    colors = index_files(seq, COLOR_RX)
    depths = index_files(seq, DEPTH_RX)
    pose_files = index_files(seq, POSE_RX)
    poses = read_frame_poses(pose_files)
    kept, skipped = match_frames(root, colors, depths, poses, pose_files)
    cpaths = [str(colors[i].resolve()) for i in kept]
    dpaths = [str(depths[i].resolve()) for i in kept]
    check_image_sizes(cpaths, (w, h), "colour")
    check_image_sizes(dpaths, (wd, hd), "depth", depth=True)
    mesh = next((root / n for n in MESH_NAMES if (root / n).is_file()), None)
    F = len(kept)
    registered = (w, h) == (wd, hd) and np.allclose(Kc, Kd) and np.allclose(T_d2c, np.eye(4))
    meta = {"skipped": skipped, "T_d2c": T_d2c.tolist(), "info_file": Path(os.path.relpath(ipath, root)).as_posix(),
            "registration": "depth resampled into the colour camera with both intrinsics from _info.txt"}
    return Scan(name=root.name, root=str(root.resolve()), format=FORMAT,
                frame_ids=np.asarray(kept, dtype=np.int64), color_paths=tuple(cpaths), depth_paths=tuple(dpaths),
                width=w, height=h, K=np.repeat(Kc[None], F, axis=0), T_c2w=np.stack([poses[i] for i in kept]),
                depth_width=wd, depth_height=hd, depth_K=np.repeat(Kd[None], F, axis=0),
                depth_scale=1.0 / shift, depth_registered=bool(registered), up_w=np.zeros(3),
                mesh_path=str(mesh.resolve()) if mesh else "", meta=meta)
