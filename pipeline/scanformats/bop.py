"""BOP scene layout: the real test scenes of a BOP dataset (or any scene written the BOP way) as a scan.

Files (one scene folder, e.g. ``lmo/test/000002``)::

    rgb/NNNNNN.png|jpg      colour
    depth/NNNNNN.png        uint16, depth_scale x value = millimetres, 0 = invalid; registered to rgb
    scene_camera.json       per image id: cam_K (9 numbers, row-major), depth_scale (mm per unit) and,
                            where the dataset has them, cam_R_w2c (9) and cam_t_w2c (3, mm): the camera's
                            pose in a world frame common to the scene's images

The depth is registered to the colour image (one ``cam_K`` for both). No mesh is shipped: ingest
reconstructs one from the depth, so the objects already in the scene stay in it and occlude and light
the inserted ones as a room does.

Images with a world pose form one scan. Images without one share no frame with the others, so each is
a scan on its own (one frame, its camera at the world origin): :func:`units` lists them, and ingest makes
one scene per unit (``<scene>-NNNNNN``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from pipeline.errors import InputError
from pipeline.scanformats.common import (BadFrameWarning, check_image_sizes, check_intrinsics, check_pose,
                                         index_files, match_frames, warn)
from pipeline.types import Scan

FORMAT = "bop"
IMAGE_RX = r"(\d+)\.(?:png|jpg|jpeg)"
DEPTH_RX = r"(\d+)\.png"


def looks_like(root: Path) -> bool:
    return (root / "scene_camera.json").is_file() or ((root / "rgb").is_dir() and (root / "depth").is_dir())


def read_cameras(root: Path) -> dict[int, dict]:
    """``scene_camera.json`` of ``root`` by image id; InputError (one line) when missing or malformed."""
    path = root / "scene_camera.json"
    if not path.is_file():
        raise InputError(f"{root}: BOP scene folder without scene_camera.json (it holds each image's cam_K and "
                         f"depth_scale); copy it from the dataset next to rgb/ and depth/")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise InputError(f"{path}: not valid JSON ({e}); restore it from the dataset") from None
    if not isinstance(doc, dict) or not doc:
        raise InputError(f"{path}: expected an object of image ids, found {type(doc).__name__} "
                         f"{str(doc)[:40]}; restore it from the dataset")
    out: dict[int, dict] = {}
    for key, cam in doc.items():
        if not str(key).isdigit() or not isinstance(cam, dict):
            raise InputError(f"{path}: entry {key!r} is not an image id with an object of camera values; "
                             f"restore the file from the dataset")
        out[int(key)] = cam
    return out


def _numbers(cam: dict, key: str, n: int, path: Path, im_id: int) -> np.ndarray | None:
    v = cam.get(key)
    if v is None:
        return None
    try:
        a = np.asarray(v, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if a.size != n or not np.all(np.isfinite(a)):
        raise InputError(f"{path}: image {im_id}: {key} must be {n} finite numbers, found {str(v)[:60]}; "
                         f"restore the file from the dataset")
    return a


def _camera(cam: dict, path: Path, im_id: int) -> tuple[np.ndarray, float]:
    """``cam_K`` (3, 3) and ``depth_scale`` (mm per unit, 1 when absent) of one image's entry."""
    k = _numbers(cam, "cam_K", 9, path, im_id)
    if k is None:
        raise InputError(f"{path}: image {im_id} has no cam_K; restore the file from the dataset")
    s = cam.get("depth_scale", 1.0)
    if not isinstance(s, (int, float)) or isinstance(s, bool) or not math.isfinite(s) or s <= 0:
        raise InputError(f"{path}: image {im_id}: depth_scale is {s!r}, not a positive number of millimetres "
                         f"per depth unit; restore the file from the dataset")
    return k.reshape(3, 3), float(s)


def _posed(cam: dict) -> bool:
    return "cam_R_w2c" in cam or "cam_t_w2c" in cam


def units(root: Path) -> list[int | None]:
    """The scans a BOP scene folder makes: ``None`` for the images with a world pose (one scan), and the
    id of each image without one (a scan each)."""
    cams = read_cameras(Path(root))
    out: list[int | None] = [None] if any(_posed(c) for c in cams.values()) else []
    return out + sorted(i for i, c in cams.items() if not _posed(c))


def read(root: Path, frame: int | None = None) -> Scan:
    """Read a BOP scene folder: its images with a world pose (``frame`` None), or image ``frame`` alone
    (an image without a world pose; its camera is the world frame)."""
    root = Path(root)
    path = root / "scene_camera.json"
    cams = read_cameras(root)
    colors = index_files(root / "rgb", IMAGE_RX)
    depths = index_files(root / "depth", DEPTH_RX)
    if frame is None:
        ids = {i for i, c in cams.items() if _posed(c)}
        if not ids:
            raise InputError(f"{path}: no image has a world pose (cam_R_w2c, cam_t_w2c); each image is a scan "
                             f"of its own (ingest lists them as <scene>-NNNNNN)")
    else:
        if frame not in cams:
            raise InputError(f"{path}: no entry for image {frame}; restore the file from the dataset")
        if frame not in depths:
            raise InputError(f"{root / 'depth' / f'{frame:06d}.png'}: the depth of image {frame} is missing (a "
                             f"scan of one image needs it for its room mesh); restore it from the dataset")
        ids = {frame}
    poses: dict[int, np.ndarray | str | None] = {}
    for i in ids:
        if frame is not None:
            poses[i] = np.eye(4)
            continue
        try:
            R = _numbers(cams[i], "cam_R_w2c", 9, path, i)
            t = _numbers(cams[i], "cam_t_w2c", 3, path, i)
            if R is None or t is None:
                raise InputError(f"{path}: image {i} has {'cam_R_w2c' if t is None else 'cam_t_w2c'} without "
                                 f"{'cam_t_w2c' if t is None else 'cam_R_w2c'}")
            T_w2c = np.eye(4)
            T_w2c[:3, :3], T_w2c[:3, 3] = R.reshape(3, 3), t / 1000.0
            T = check_pose(T_w2c, f"{path} image {i} (cam_R_w2c, cam_t_w2c)")
            poses[i] = None if T is None else np.linalg.inv(T)
        except InputError as e:
            poses[i] = str(e)
    # an image whose camera entry is malformed costs only itself
    cam_K, scale, bad = {}, {}, {}
    for i in sorted(ids):
        try:
            cam_K[i], scale[i] = _camera(cams[i], path, i)
        except InputError as e:
            bad[i] = str(e)
    if frame is not None and bad:
        raise InputError(bad[frame])
    if bad:
        warn(f"{root}: skipped {len(bad)} of {len(ids)} image(s) whose camera is malformed (first: {bad[min(bad)]})",
             BadFrameWarning)
        if len(bad) == len(ids):
            raise InputError(f"{path}: no image with a usable camera (first: {bad[min(bad)]})")
    ids = ids - set(bad)
    kept, skipped = match_frames(root, {i: p for i, p in colors.items() if i in ids},
                                 {i: p for i, p in depths.items() if i in ids}, poses, {i: path for i in ids},
                                 regular_numbering=False)
    skipped["bad_camera"] = len(bad)
    K = [cam_K[i] for i in kept]
    scales = {scale[i] for i in kept}
    if len(scales) > 1:
        raise InputError(f"{path}: the posed images' depth_scale differs ({', '.join(map(str, sorted(scales)))} "
                         f"mm per unit); scansynth reads one scale per scan: re-save the depth maps at one scale")
    cpaths = [str(colors[i].resolve()) for i in kept]
    dpaths = [str(depths[i].resolve()) for i in kept]
    w, h = check_image_sizes(cpaths, None, "colour")
    for i, k in zip(kept, K):
        check_intrinsics(k, w, h, f"{path} image {i} cam_K")
    check_image_sizes(dpaths, (w, h), "depth", depth=True)
    Ks = np.stack(K)
    meta: dict = {"skipped": skipped, "scene_camera": "scene_camera.json", "world_poses": frame is None,
                  "registration": "BOP depth is registered to rgb (one cam_K for both)"}
    if frame is not None:
        meta["bop_image"] = int(frame)
    return Scan(name=root.name, root=str(root.resolve()), format=FORMAT,
                frame_ids=np.asarray(kept, dtype=np.int64), color_paths=tuple(cpaths), depth_paths=tuple(dpaths),
                width=w, height=h, K=Ks, T_c2w=np.stack([poses[i] for i in kept]), depth_width=w,
                depth_height=h, depth_K=Ks.copy(), depth_scale=scales.pop() / 1000.0, depth_registered=True,
                up_w=np.zeros(3), mesh_path="", meta=meta)
