"""Validation and frame reading shared by every scan layout reader.

A reader turns a scan folder into a :class:`~pipeline.types.Scan` in the pipeline's conventions (metres,
OpenCV camera axes, camera-to-world poses, one colour intrinsics matrix per frame) with ``mesh_path`` set
to the scan's own mesh file (or ``""`` when it has none) and ``up_w`` set from the scan's metadata (or
zeros when it gives none); :mod:`pipeline.ingest` then converts or reconstructs the mesh and finds the
up direction.

Decided behaviours for imperfect input (each has a test):

- a frame whose pose is missing or non-finite (ScanNet writes ``-inf`` rows for lost tracking), or that
  lacks its colour or depth image, is skipped; the skipped frames are counted in one
  :class:`IngestWarning` per cause and in ``Scan.meta["skipped"]``;
- irregular frame numbering (gaps in an otherwise regular step) is kept as is, with a warning;
- a frame whose pose file cannot be read as a 4x4 matrix or holds a finite pose that is not a rigid
  transform (a scaled or sheared rotation, a last row other than 0 0 0 1) is skipped the same way, with
  the first such file and its measured error named in the warning: one bad frame costs only itself;
- a scan fails only when no frame is left, with an :class:`InputError` that counts the frames seen and
  why each group was left out;
- a malformed calibration file (intrinsics, extrinsics), missing or zero-focal intrinsics, a missing or
  unreadable image, depth of the wrong size or dtype: :class:`InputError` naming the file and the fix;
  the whole scan fails (these concern every frame, not one).
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from pipeline.camera import image_plane, project_points, transform_points, unproject_points
from pipeline.errors import InputError
from pipeline.geometry import nearest_rotation
from pipeline.tolerances import POSE_ORTHONORMAL_TOL
from pipeline.types import Scan

DEPTH_INVALID_U16 = 65535  # 7-Scenes (and some Kinect tools) mark invalid depth with the uint16 maximum


class IngestWarning(UserWarning):
    """Input was usable but imperfect (skipped frames, gaps, implausible units); the message says what."""


class BadFrameWarning(IngestWarning):
    """Frames were left out because one of their files is broken (not merely absent, as a frame without
    a depth map or a lost-tracking pose is): ingest reports these as the scan's input problems."""


def warn(msg: str, category: type[IngestWarning] = IngestWarning) -> None:
    """Issue an :class:`IngestWarning` (also visible in the log through the warnings capture)."""
    warnings.warn(msg, category, stacklevel=3)


# ---------------------------------------------------------------------------------------------------
# Text matrices and poses
# ---------------------------------------------------------------------------------------------------

def read_numbers(path: Path, what: str) -> np.ndarray:
    """All whitespace-separated numbers of a text file, as float64 (``inf``/``nan`` allowed)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} file is missing; restore it from the original scan")
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
        return np.array([float(t) for t in text.replace(",", " ").split()], dtype=np.float64)
    except (UnicodeDecodeError, ValueError) as e:
        raise InputError(f"{path}: {what} file is not a list of numbers ({e}); "
                         f"restore it from the original scan") from None


def read_matrix(path: Path, rows: int, cols: int, what: str) -> np.ndarray:
    """A ``rows x cols`` matrix written as text (row-major); InputError when the count differs."""
    v = read_numbers(path, what)
    if v.size != rows * cols:
        raise InputError(f"{path}: {what} must hold {rows}x{cols} = {rows * cols} numbers, found {v.size}; "
                         f"restore the file from the original scan")
    return v.reshape(rows, cols)


def check_pose(T: np.ndarray, path: Path | str) -> np.ndarray | None:
    """Validate a camera-to-world pose read from ``path``.

    Returns the pose with its rotation projected onto SO(3) (removes text rounding), or ``None`` when the
    pose holds non-finite values (the "invalid pose" marker of ScanNet and others: the frame is skipped).
    Raises :class:`InputError` when it is finite but not a rigid transform.
    """
    T = np.asarray(T, dtype=np.float64)
    if not np.all(np.isfinite(T)):
        return None
    R, orth, det = nearest_rotation(T[:3, :3])
    if abs(det - 1.0) > POSE_ORTHONORMAL_TOL or orth > POSE_ORTHONORMAL_TOL or \
            np.abs(T[3] - [0, 0, 0, 1]).max() > POSE_ORTHONORMAL_TOL:
        raise InputError(f"{path}: pose is not a rigid transform (det R = {det:.4f}, |R^T R - I| = {orth:.2e}, "
                         f"last row {T[3].tolist()}); a camera-to-world pose needs an orthonormal rotation "
                         f"with det 1 and last row 0 0 0 1: fix or delete this pose file")
    out = T.copy()
    out[:3, :3] = R
    out[3] = [0.0, 0.0, 0.0, 1.0]
    return out


def read_frame_poses(pose_files: dict[int, Path]) -> dict[int, np.ndarray | str | None]:
    """Read and check each frame's camera-to-world pose file, by frame number.

    Returns, per frame, the pose (see :func:`check_pose`), ``None`` for a non-finite pose, or the
    one-line reason (a ``str``) when the file is malformed or its pose is not a rigid transform; such a
    frame is skipped by :func:`match_frames`, not the whole scan.
    """
    out: dict[int, np.ndarray | str | None] = {}
    for i, p in sorted(pose_files.items()):
        try:
            out[i] = check_pose(read_matrix(p, 4, 4, "pose"), p)
        except InputError as e:
            out[i] = str(e)
    return out


def check_extrinsic(E: np.ndarray, path: Path | str, what: str) -> np.ndarray:
    """A rigid 4x4 calibration transform (between a camera and the sensor rig); InputError otherwise."""
    T = check_pose(E, path)
    if T is None:
        raise InputError(f"{path}: {what} holds non-finite values; restore it from the original scan")
    return T


def check_intrinsics(K: np.ndarray, width: int, height: int, path: Path | str) -> np.ndarray:
    """Validate a 3x3 pinhole matrix for an image of ``width x height``; return it as float64."""
    K = np.asarray(K, dtype=np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not np.all(np.isfinite(K)) or fx <= 0 or fy <= 0:
        raise InputError(f"{path}: intrinsics have a zero, negative or non-finite focal length "
                         f"(fx = {fx}, fy = {fy}); write the camera's calibrated focal lengths in pixels")
    if not (0 < cx < width and 0 < cy < height):
        raise InputError(f"{path}: principal point ({cx}, {cy}) lies outside the {width}x{height} image; "
                         f"are these intrinsics for another resolution?")
    return K


# ---------------------------------------------------------------------------------------------------
# Image headers (sizes and types checked up front, without decoding every image)
# ---------------------------------------------------------------------------------------------------

def image_header(path: Path | str, what: str) -> tuple[int, int, str]:
    """``(width, height, PIL mode)`` of an image file; InputError when missing or unreadable."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: {what} image is missing; restore it or delete the frame's other files")
    try:
        with Image.open(path) as im:
            return int(im.size[0]), int(im.size[1]), str(im.mode)
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise InputError(f"{path}: {what} image cannot be read ({e}); re-export it or delete the frame") from None


DEPTH_MODES = ("I;16", "I;16B", "I;16L", "I")  # 16-bit single-channel


def check_image_sizes(paths: list[str], expect: tuple[int, int] | None, what: str,
                      depth: bool = False) -> tuple[int, int]:
    """The common size of the images ``paths`` (``expect`` when given), from their headers.

    One bad file does not fail the scan: a file that cannot be read, or has another size or (for depth)
    not 16 bits, is named in an :class:`IngestWarning` and stays in the scan's lists; ingest then leaves
    that frame out when it decodes it (``pipeline.ingest.readable_frames``), and the run reports it and
    exits 1. Without ``expect`` the size is the most common one. InputError only when no file is usable.

    Returns ``(width, height)``.
    """
    import collections

    sizes: dict[str, tuple[int, int]] = {}
    first_error = ""
    listed = [p for p in paths if p]
    for p in listed:
        try:
            w, h, mode = image_header(p, what)
        except InputError as e:
            first_error = first_error or str(e)
            warn(f"{e}; the frame is left out")
            continue
        if depth and not p.endswith(".npy") and mode not in DEPTH_MODES:
            msg = (f"{p}: depth image has pixel type {mode!r}, expected 16-bit single-channel (uint16 depth "
                   f"units, 0 = invalid); re-export the depth maps as 16-bit PNG")
            first_error = first_error or msg
            warn(f"{msg}; the frame is left out")
            continue
        sizes[p] = (w, h)
    if not listed:
        raise InputError(f"no {what} images found")
    if not sizes:
        raise InputError(f"none of the scan's {len(listed)} {what} images can be used (first: {first_error}); "
                         f"restore them")
    size = expect or collections.Counter(sizes.values()).most_common(1)[0][0]
    for p, (w, h) in sizes.items():
        if (w, h) != size:
            warn(f"{p}: {what} image is {w}x{h}, expected {size[0]}x{size[1]} like the scan's other {what} "
                 f"images / its intrinsics; re-export it at that size; the frame is left out")
    return size


# ---------------------------------------------------------------------------------------------------
# Matching per-frame files
# ---------------------------------------------------------------------------------------------------

def index_files(folder: Path, pattern: str) -> dict[int, Path]:
    """Files of ``folder`` whose name matches regex ``pattern`` (group 1 = frame number), by number."""
    rx = re.compile(pattern)
    out: dict[int, Path] = {}
    if not folder.is_dir():
        return out
    for p in folder.iterdir():
        m = rx.fullmatch(p.name)
        if m:
            out[int(m.group(1))] = p
    return out


def match_frames(root: Path, colors: dict[int, Path], depths: dict[int, Path] | None,
                 poses: dict[int, np.ndarray | None], pose_files: dict[int, Path], *,
                 regular_numbering: bool = True) -> tuple[list[int], dict]:
    """Frame numbers that have a colour image, a valid pose and (when the layout has depth) a depth map.

    Frames lacking any of these are skipped with one counted :class:`IngestWarning` per cause; gaps in
    the numbering are warned about too, unless ``regular_numbering`` is False (a layout whose frames are
    a selection, like a BOP scene's images).
    Returns ``(kept frame ids sorted, skipped counts by cause)``.
    """
    ids = sorted(set(colors) | set(pose_files) | (set(depths) if depths is not None else set()))
    skipped = {"no_color": [], "no_depth": [], "no_pose": [], "invalid_pose": [], "bad_pose": []}
    kept = []
    for i in ids:
        if i not in colors:
            skipped["no_color"].append(i)
        elif depths is not None and i not in depths:
            skipped["no_depth"].append(i)
        elif i not in pose_files:
            skipped["no_pose"].append(i)
        elif poses.get(i) is None:
            skipped["invalid_pose"].append(i)
        elif isinstance(poses[i], str):
            skipped["bad_pose"].append(i)
        else:
            kept.append(i)
    why = {"no_color": "have no colour image", "no_depth": "have no depth map",
           "no_pose": "have no pose file", "invalid_pose": "have a non-finite (invalid) pose",
           "bad_pose": "have a malformed pose or one that is not a rigid transform"}
    for cause, lst in skipped.items():
        if lst:
            first = f"frame {lst[0]}" + (f": {poses[lst[0]]}" if cause == "bad_pose" else "")
            warn(f"{root}: skipped {len(lst)} of {len(ids)} frame(s) that {why[cause]} (first: {first})",
                 BadFrameWarning if cause == "bad_pose" else IngestWarning)
    if not kept:
        causes = ", ".join(f"{len(lst)} {why[c]}" for c, lst in skipped.items() if lst)
        raise InputError(f"{root}: no usable frame: 0 of {len(ids)} frame number(s) seen have a colour image, "
                         f"a depth map and a valid pose ({causes or 'none seen'}); check the scan folder")
    if regular_numbering and len(ids) >= 3:  # gaps in the files' numbering (skipped frames are reported above)
        steps = np.diff(np.asarray(ids))
        step = int(np.median(steps))
        gaps = int(np.sum(steps != step))
        if gaps:
            first = int(np.asarray(ids)[:-1][steps != step][0])
            warn(f"{root}: frame numbering is irregular ({gaps} gap(s) in the step of {step}, first after "
                 f"frame {first}); using the frames present")
    return kept, {k: len(v) for k, v in skipped.items()}


def subsample(n: int, max_frames: int) -> np.ndarray:
    """Indices of at most ``max_frames`` of ``n`` frames, evenly spaced (all when ``max_frames`` is 0)."""
    if max_frames <= 0 or max_frames >= n:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, max_frames)).astype(np.int64))


def select_frames(scan: Scan, idx: np.ndarray) -> Scan:
    """A copy of ``scan`` with only frames ``idx``."""
    import dataclasses

    idx = np.asarray(idx, dtype=np.int64)
    return dataclasses.replace(
        scan, frame_ids=scan.frame_ids[idx], color_paths=tuple(scan.color_paths[i] for i in idx),
        depth_paths=tuple(scan.depth_paths[i] for i in idx), K=scan.K[idx], T_c2w=scan.T_c2w[idx],
        depth_K=scan.depth_K[idx])


# ---------------------------------------------------------------------------------------------------
# Reading frames
# ---------------------------------------------------------------------------------------------------

def read_color(scan: Scan, i: int) -> np.ndarray:
    """Colour image of frame ``i`` (index into the scan's arrays).

    Returns
    -------
    (height, width, 3) uint8 sRGB.
    """
    import cv2

    p = scan.color_paths[i]
    img = cv2.imread(p, cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(f"{p}: colour image cannot be read (missing or corrupt); restore it or delete "
                         f"the frame")
    if img.shape[:2] != (scan.height, scan.width):
        raise InputError(f"{p}: colour image is {img.shape[1]}x{img.shape[0]}, expected "
                         f"{scan.width}x{scan.height}; re-export it at the scan's resolution")
    return np.ascontiguousarray(img[..., ::-1])


def read_depth_raw(scan: Scan, i: int) -> np.ndarray:
    """Depth of frame ``i`` as stored, converted to metres: (depth_height, depth_width) float32, 0 = invalid."""
    import cv2

    p = scan.depth_paths[i]
    if not p:
        raise InputError(f"{scan.root}: frame {int(scan.frame_ids[i])} has no depth map")
    if p.endswith(".npy"):
        try:
            d = np.load(p, allow_pickle=False).astype(np.float32)
        except (OSError, ValueError) as e:
            raise InputError(f"{p}: depth array cannot be read ({e}); re-export it") from None
        d = d * np.float32(scan.depth_scale)
    else:
        raw = cv2.imread(p, cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise InputError(f"{p}: depth image cannot be read (missing or corrupt); restore it or delete "
                             f"the frame")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise InputError(f"{p}: depth image is {raw.dtype} with shape {raw.shape}, expected 16-bit "
                             f"single-channel depth units; re-export the depth maps as 16-bit PNG")
        d = raw.astype(np.float32) * np.float32(scan.depth_scale)
        d[raw == DEPTH_INVALID_U16] = 0.0
    if d.shape != (scan.depth_height, scan.depth_width):
        raise InputError(f"{p}: depth map is {d.shape[1]}x{d.shape[0]}, expected "
                         f"{scan.depth_width}x{scan.depth_height}; re-export it at the depth resolution")
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


def register_depth(depth: np.ndarray, K_d: np.ndarray, K_c: np.ndarray, T_d2c: np.ndarray,
                   width: int, height: int) -> np.ndarray:
    """Resample a depth map of the depth camera into the colour camera's pixels.

    When the two cameras share their centre and orientation (``T_d2c`` identity, as in ScanNet and
    3RScan exports) the mapping between pixels does not depend on depth: each colour pixel takes the
    nearest depth pixel along its own ray (exact, no hole filling). Otherwise depth points are
    back-projected, moved by ``T_d2c`` and splatted with a z-buffer (footprint of one depth pixel).

    Parameters
    ----------
    depth : (hd, wd) float32, metres, 0 = invalid.
    K_d, K_c : (3, 3) float64 intrinsics of depth and colour cameras.
    T_d2c : (4, 4) float64, depth camera to colour camera, metres.
    width, height : colour resolution.

    Returns
    -------
    (height, width) float32 metres along the colour camera's z axis, 0 = invalid.
    """
    hd, wd = depth.shape
    if np.allclose(T_d2c, np.eye(4), atol=1e-9):
        if hd == height and wd == width and np.allclose(K_d, K_c, atol=1e-9):
            return depth.astype(np.float32, copy=True)
        x, y = image_plane(K_c, width, height)          # each colour pixel's ray at z = 1 ...
        ui = np.round(K_d[0, 0] * x + K_d[0, 2]).astype(np.int64)   # ... seen by the depth camera
        vi = np.round(K_d[1, 1] * y + K_d[1, 2]).astype(np.int64)
        ok_u, ok_v = (ui >= 0) & (ui < wd), (vi >= 0) & (vi < hd)
        out = np.zeros((height, width), np.float32)
        out[np.ix_(ok_v, ok_u)] = depth[np.ix_(vi[ok_v], ui[ok_u])]
        return out
    vv, uu = np.nonzero(depth > 0)
    pts = transform_points(T_d2c, unproject_points(K_d, uu, vv, depth[vv, uu]))
    pts = pts[pts[:, 2] > 1e-6]
    uv, z = project_points(K_c, pts)
    # footprint: one depth pixel covers about this many colour pixels (one: the nearest pixel centre)
    r = max(1, int(np.ceil(max(K_c[0, 0] / K_d[0, 0], K_c[1, 1] / K_d[1, 1]) / 2)))
    base = np.round(uv) if r == 1 else np.floor(uv)
    out = np.full((height, width), np.inf, np.float32)
    zc = z.astype(np.float32)
    for dy in range(-r + 1, r + 1) if r > 1 else (0,):
        for dx in range(-r + 1, r + 1) if r > 1 else (0,):
            ui = base[:, 0].astype(np.int64) + dx
            vi = base[:, 1].astype(np.int64) + dy
            ok = (ui >= 0) & (ui < width) & (vi >= 0) & (vi < height)
            np.minimum.at(out, (vi[ok], ui[ok]), zc[ok])
    out[~np.isfinite(out)] = 0.0
    return out


def read_depth(scan: Scan, i: int) -> np.ndarray:
    """Depth of frame ``i`` at the colour resolution.

    Registered to the colour camera through ``scan.depth_K``, ``scan.K`` and ``scan.meta["T_d2c"]``: the
    format's calibration, or the one ingest estimated (:func:`pipeline.registration.register_scan`).

    Returns
    -------
    (height, width) float32, metres along the camera's z axis, 0 = invalid.
    """
    d = read_depth_raw(scan, i)
    T_d2c = np.asarray(scan.meta.get("T_d2c", np.eye(4)), dtype=np.float64)
    return register_depth(d, scan.depth_K[i], scan.K[i], T_d2c, scan.width, scan.height)
