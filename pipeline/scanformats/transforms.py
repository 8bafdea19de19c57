"""Posed images described by a ``transforms.json`` (nerfstudio / instant-ngp convention).

Keys read: ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h`` (top level, or per frame to override; or
``camera_angle_x`` as in instant-ngp), ``frames[*].file_path``, ``frames[*].transform_matrix`` (4x4
camera-to-world with **OpenGL camera axes**: x right, y up, z backwards), optional
``frames[*].depth_file_path`` (uint16 PNG, ``depth_unit_scale_factor`` metres per unit, default 0.001,
or ``.npy`` float metres) and optional distortion ``k1 k2 p1 p2`` (must be zero: images are used as
pinhole). Paths are relative to the JSON file's folder. The room mesh comes from ``scan.mesh`` in the
config, else from ``ply_file_path`` when that file is a triangle mesh (nerfstudio often points it at a
point cloud: then it is ignored), else it is reconstructed from the depth maps.

Pixel convention: nerfstudio (like COLMAP) puts pixel ``i``'s centre at ``i + 0.5``, OpenCV at ``i``;
so ``K[0, 2] = cx - 0.5`` and ``K[1, 2] = cy - 0.5`` (a centred ``cx = w / 2`` becomes ``(w - 1) / 2``).

Poses are converted to OpenCV axes by flipping the camera's y and z axes:
``T_cv = T_gl @ diag(1, -1, -1, 1)``. Depth maps are taken as rendered/registered from the colour
camera (same K, resized with nearest neighbour when their size differs).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from pipeline.camera import CV_TO_GL
from pipeline.errors import InputError
from pipeline.scanformats.common import BadFrameWarning, check_image_sizes, check_intrinsics, check_pose, warn
from pipeline.types import Scan

FORMAT = "transforms"


def looks_like(root: Path) -> bool:
    return (root / "transforms.json").is_file()


def _resolve_image(root: Path, rel: str, what: str, jpath: Path) -> Path:
    p = (root / rel)
    if p.is_file():
        return p.resolve()
    if not p.suffix:
        for ext in (".png", ".jpg", ".jpeg"):
            if p.with_name(p.name + ext).is_file():
                return p.with_name(p.name + ext).resolve()
    raise InputError(f"{p}: {what} image named in {jpath} is missing; restore it or remove its frame "
                     f"from transforms.json")


def _intrinsics(d: dict, base: dict, jpath: Path) -> tuple[np.ndarray, int, int]:
    get = lambda k: d.get(k, base.get(k))  # noqa: E731 - per-frame values override the top level
    w, h = get("w"), get("h")
    if w is None or h is None:
        raise InputError(f"{jpath}: image size 'w' and 'h' missing; add them (pixels) to transforms.json")
    fx, fy = get("fl_x"), get("fl_y")
    if fx is None and get("camera_angle_x") is not None:
        fx = 0.5 * w / math.tan(0.5 * float(get("camera_angle_x")))
    if fy is None and get("camera_angle_y") is not None:
        fy = 0.5 * h / math.tan(0.5 * float(get("camera_angle_y")))
    fy = fx if fy is None else fy
    if fx is None:
        raise InputError(f"{jpath}: intrinsics missing: add 'fl_x', 'fl_y', 'cx', 'cy' (pixels) to "
                         f"transforms.json")
    cx, cy = get("cx"), get("cy")
    cx = (w / 2.0 if cx is None else float(cx)) - 0.5  # pixel centres at i + 0.5 -> OpenCV's i
    cy = (h / 2.0 if cy is None else float(cy)) - 0.5
    for k in ("k1", "k2", "k3", "p1", "p2"):
        if abs(float(get(k) or 0.0)) > 1e-9:
            raise InputError(f"{jpath}: distortion {k} = {get(k)} is not supported; undistort the images "
                             f"first (e.g. nerfstudio's ns-process-data) and set the coefficients to 0")
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=np.float64)
    return check_intrinsics(K, int(w), int(h), jpath), int(w), int(h)


def read(root: Path) -> Scan:
    """Read a folder with a ``transforms.json``; see the module docstring."""
    root = Path(root)
    jpath = root / "transforms.json"
    try:
        doc = json.loads(jpath.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{jpath}: cannot be read as JSON ({e}); fix the file") from None
    frames = doc.get("frames") if isinstance(doc, dict) else None
    if not frames or not isinstance(frames, list):
        raise InputError(f"{jpath}: no 'frames' list; each frame needs 'file_path' and 'transform_matrix'")
    scale = float(doc.get("depth_unit_scale_factor", 0.001))
    Ks, T, cpaths, dpaths, ids = [], [], [], [], []
    n_invalid = 0
    bad: list[str] = []
    size = None
    for i, fr in enumerate(frames):
        if "file_path" not in fr or "transform_matrix" not in fr:
            raise InputError(f"{jpath}: frame {i} lacks 'file_path' or 'transform_matrix'; fix the file")
        try:
            M = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError):
            M = np.zeros(0)
        if M.shape != (4, 4):
            raise InputError(f"{jpath}: frame {i} transform_matrix is not a 4x4 list of numbers; fix the file")
        where = f"{jpath} (frame {i}, {fr['file_path']})"
        try:
            Tgl = check_pose(M, where)
        except InputError as e:  # not a rigid transform: this frame only (common.match_frames' rule)
            bad.append(str(e))
            continue
        if Tgl is None:
            n_invalid += 1
            continue
        K, w, h = _intrinsics(fr, doc, jpath)
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise InputError(f"{jpath}: frame {i} is {w}x{h} while earlier frames are {size[0]}x{size[1]}; "
                             f"one resolution per scan is supported: split the scan")
        cpaths.append(str(_resolve_image(root, fr["file_path"], "colour", jpath)))
        dpaths.append(str(_resolve_image(root, fr["depth_file_path"], "depth", jpath))
                      if fr.get("depth_file_path") else "")
        Ks.append(K)
        T.append(Tgl @ CV_TO_GL)  # OpenGL -> OpenCV axes: the flip is its own inverse
        ids.append(i)
    if n_invalid:
        warn(f"{jpath}: skipped {n_invalid} of {len(frames)} frame(s) that have a non-finite (invalid) pose")
    if bad:
        warn(f"{jpath}: skipped {len(bad)} of {len(frames)} frame(s) that have a pose that is not a rigid "
             f"transform (first: {bad[0]})", BadFrameWarning)
    if not ids:
        raise InputError(f"{jpath}: no usable frame: 0 of {len(frames)} frame(s) have a valid pose "
                         f"({n_invalid} non-finite, {len(bad)} not a rigid transform); fix the poses")
    has_depth = [bool(p) for p in dpaths]
    if any(has_depth) and not all(has_depth):
        raise InputError(f"{jpath}: {has_depth.count(False)} frame(s) lack 'depth_file_path' while others "
                         f"have one; give every frame a depth map or none")
    w, h = size
    check_image_sizes(cpaths, (w, h), "colour")
    wd, hd = (w, h)
    if all(has_depth):
        wd, hd = check_image_sizes(dpaths, None, "depth", depth=True)
    Kd = np.stack(Ks).copy()
    if (wd, hd) != (w, h):
        Kd[:, 0] *= wd / w
        Kd[:, 1] *= hd / h
    meta = {"skipped": {"invalid_pose": n_invalid, "bad_pose": len(bad)}, "transforms_file": Path(os.path.relpath(jpath, root)).as_posix(),
            "registration": "depth assumed rendered from the colour camera (same pose and K)"}
    mesh = ""
    if doc.get("ply_file_path"):
        mp = root / str(doc["ply_file_path"])
        if not mp.is_file():
            raise InputError(f"{jpath}: ply_file_path {doc['ply_file_path']!r} does not exist; fix or remove it")
        mesh = str(mp.resolve())
        meta["mesh_may_be_point_cloud"] = True
    return Scan(name=root.name, root=str(root.resolve()), format=FORMAT,
                frame_ids=np.asarray(ids, dtype=np.int64), color_paths=tuple(cpaths), depth_paths=tuple(dpaths),
                width=w, height=h, K=np.stack(Ks), T_c2w=np.stack(T), depth_width=wd, depth_height=hd,
                depth_K=Kd, depth_scale=1.0 if dpaths[0].endswith(".npy") else scale,
                depth_registered=all(has_depth), up_w=np.zeros(3), mesh_path=mesh, meta=meta)
