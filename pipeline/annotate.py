"""Annotations from raster passes: pure NumPy, no renderer.

Everything here works on arrays a renderer produced (metric z-depth per instance, the room's depth,
the real sensor depth) and returns masks, labels, boxes and pixel counts with the meaning BOP gives
them (bop_toolkit ``scripts/calc_gt_info.py``):

- ``px_count_all``: pixels of the whole silhouette of the object alone, including the part outside
  the image (counted on a canvas three times the image size in each direction, as BOP does);
- ``px_count_valid``: silhouette pixels inside the image with a valid depth in the written depth image;
- ``px_count_visib``: pixels where the object is the nearest surface (of objects, room and real depth);
- ``visib_fract = px_count_visib / px_count_all`` (0 when ``px_count_all`` is 0);
- ``bbox_obj``: ``[x, y, w, h]`` of the whole silhouette, not clipped to the image; ``bbox_visib``:
  of the visible pixels; both ``[-1, -1, -1, -1]`` when nothing is visible. Here ``w, h`` are pixel
  extents (COCO's convention, ``last - first + 1``); the BOP writer converts to bop_toolkit's
  ``last - first`` (:func:`pipeline.export_bop.bop_box`).

Pixel centres are at integer coordinates (OpenCV): pixel ``(r, c)`` samples ``u = c, v = r``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.camera import image_plane, project_points

NO_BOX = (-1, -1, -1, -1)


# ---------------------------------------------------------------------------------------------------
# Poses and projection bounds
# ---------------------------------------------------------------------------------------------------

def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) float64 rigid transform from a (3, 3) rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def canvas(width: int, height: int) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)`` of the BOP counting canvas: the image plus one image size on every side."""
    return (-width, -height, 2 * width, 2 * height)


def projected_window(K: np.ndarray, R_m2c: np.ndarray, t_m2c: np.ndarray, points: np.ndarray,
                     width: int, height: int, znear: float) -> tuple[int, int, int, int] | None:
    """Pixel window that contains every pixel centre the posed model can cover, clipped to the canvas.

    Parameters
    ----------
    K : (3, 3) float64
        Intrinsics, pixels.
    R_m2c, t_m2c : (3, 3), (3,) float64
        Camera-from-model pose, metres.
    points : (P, 3) float64
        Model vertices (or any set whose convex hull contains the model), metres.
    width, height : int
        Image size, pixels.
    znear : float
        Near clip plane of the renderer, metres.

    Returns
    -------
    (x0, y0, x1, y1) or None
        Half-open pixel ranges ``[x0, x1) x [y0, y1)`` within :func:`canvas`; None when the model is
        entirely behind the near plane or outside the canvas. When part of the model crosses the near
        plane the projection is unbounded and the whole canvas is returned.
    """
    p = np.asarray(points, dtype=np.float64) @ np.asarray(R_m2c).T + np.asarray(t_m2c).reshape(3)
    z = p[:, 2]
    cx0, cy0, cx1, cy1 = canvas(width, height)
    if not np.any(z > znear):
        return None
    if np.any(z <= znear):
        return (cx0, cy0, cx1, cy1)
    uv, _ = project_points(K, p)
    u, v = uv[:, 0], uv[:, 1]
    # Pixel c covers centre u = c; one pixel of margin for rounding in the rasterizer.
    x0 = max(cx0, math.ceil(u.min()) - 1)
    x1 = min(cx1, math.floor(u.max()) + 2)
    y0 = max(cy0, math.ceil(v.min()) - 1)
    y1 = min(cy1, math.floor(v.max()) + 2)
    if x0 >= x1 or y0 >= y1:
        return None
    return (int(x0), int(y0), int(x1), int(y1))


def window_area_in_image(window: tuple[int, int, int, int] | None, width: int, height: int) -> int:
    """Pixels of ``window`` inside the image (0 for None)."""
    if window is None:
        return 0
    x0, y0, x1, y1 = window
    return max(0, min(x1, width) - max(x0, 0)) * max(0, min(y1, height) - max(y0, 0))


def split_window(window: tuple[int, int, int, int] | None, width: int, height: int
                 ) -> tuple[tuple[int, int, int, int] | None, list[tuple[int, int, int, int]]]:
    """Split a window into its part inside the image and up to four disjoint parts outside it.

    Returns
    -------
    inside : (x0, y0, x1, y1) or None
    outside : list of (x0, y0, x1, y1)
        Bands above and below the image (full window width), then left and right of it (image rows).
    """
    if window is None:
        return None, []
    x0, y0, x1, y1 = window
    ix0, iy0, ix1, iy1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    inside = (ix0, iy0, ix1, iy1) if ix0 < ix1 and iy0 < iy1 else None
    out = []
    if y0 < 0:
        out.append((x0, y0, x1, min(y1, 0)))
    if y1 > height:
        out.append((x0, max(y0, height), x1, y1))
    ry0, ry1 = max(y0, 0), min(y1, height)
    if ry0 < ry1:
        if x0 < 0:
            out.append((x0, ry0, min(x1, 0), ry1))
        if x1 > width:
            out.append((max(x0, width), ry0, x1, ry1))
    return inside, [r for r in out if r[0] < r[2] and r[1] < r[3]]


# ---------------------------------------------------------------------------------------------------
# Masks and labels
# ---------------------------------------------------------------------------------------------------

def compose_front(depths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest instance at each pixel from per-instance depth maps (each object rendered alone).

    Parameters
    ----------
    depths : (N, H, W) float32
        Metres; 0 where the instance does not cover the pixel.

    Returns
    -------
    depth : (H, W) float32
        Depth of the nearest instance, 0 where none.
    front : (H, W) uint16
        Index + 1 of the nearest instance (the lowest index wins exact ties), 0 where none.
    """
    n, h, w = depths.shape
    if n >= np.iinfo(np.uint16).max:
        raise ValueError(f"{n} instances: at most {np.iinfo(np.uint16).max - 1} fit uint16 labels")
    if n == 0:
        return np.zeros((h, w), np.float32), np.zeros((h, w), np.uint16)
    d = np.where(depths > 0, depths, np.inf)
    idx = np.argmin(d, axis=0)
    depth = np.take_along_axis(d, idx[None], axis=0)[0]
    hit = np.isfinite(depth)
    front = np.where(hit, idx + 1, 0).astype(np.uint16)
    return np.where(hit, depth, 0).astype(np.float32), front


def compose_front_crops(crops: list[tuple[np.ndarray, int, int] | None], width: int,
                        height: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`compose_front` from per-instance depth crops (a running minimum over each crop only).

    Parameters
    ----------
    crops : list of ((h, w) float32 depth, x0, y0) or None
        Instance ``i``'s depth over the image pixels ``[y0, y0+h) x [x0, x0+w)`` (inside the image);
        None when it covers no image pixel.
    """
    if len(crops) >= np.iinfo(np.uint16).max:
        raise ValueError(f"{len(crops)} instances: at most {np.iinfo(np.uint16).max - 1} fit uint16 labels")
    depth = np.zeros((height, width), np.float32)
    front = np.zeros((height, width), np.uint16)
    for i, c in enumerate(crops):
        if c is None:
            continue
        d, x0, y0 = c
        h, w = d.shape
        sub = depth[y0:y0 + h, x0:x0 + w]
        fsub = front[y0:y0 + h, x0:x0 + w]
        m = (d > 0) & ((sub == 0) | (d < sub))
        sub[m] = d[m]
        fsub[m] = i + 1
    return depth, front


def real_depth_tolerance(depth: np.ndarray, tol_abs: float, tol_rel: float) -> np.ndarray:
    """How much nearer (metres) the real depth must be than the object's to occlude it."""
    return tol_abs + tol_rel * depth


@dataclass(frozen=True)
class Visibility:
    """Result of :func:`visible_labels`."""

    labels: np.ndarray          # (H, W) uint16, visible instance index + 1, 0 = none
    occluded_by_room: np.ndarray  # (H, W) bool, object pixels behind the room mesh
    occluded_by_real: np.ndarray  # (H, W) bool, object pixels in front of the room mesh but behind real depth


def visible_labels(depth: np.ndarray, front: np.ndarray, scene_depth: np.ndarray,
                   real_depth: np.ndarray | None, *, tol_abs: float, tol_rel: float) -> Visibility:
    """Visible-instance label map: object pixels in front of the room and of the real depth.

    Parameters
    ----------
    depth, front : (H, W) float32, (H, W) uint16
        From :func:`compose_front`.
    scene_depth : (H, W) float32
        Depth of the room mesh, metres, 0 where the room was not hit.
    real_depth : (H, W) float32 or None
        Real sensor depth at the render resolution, metres, 0 = invalid; None = no fusion.
    tol_abs, tol_rel : float
        The real depth occludes where it is valid and nearer than the object's depth by more than
        ``tol_abs + tol_rel * depth`` metres (sensor noise and misregistration must not eat objects
        resting on real surfaces).
    """
    obj = front > 0
    by_room = obj & (scene_depth > 0) & (scene_depth < depth)
    if real_depth is None:
        by_real = np.zeros_like(obj)
    else:
        tol = real_depth_tolerance(depth, tol_abs, tol_rel)
        by_real = obj & ~by_room & (real_depth > 0) & (real_depth < depth - tol)
    labels = np.where(obj & ~by_room & ~by_real, front, 0).astype(np.uint16)
    return Visibility(labels=labels, occluded_by_room=by_room, occluded_by_real=by_real)


def compose_depth(labels: np.ndarray, depth: np.ndarray, background: np.ndarray | None) -> np.ndarray:
    """Depth image of the composite: the objects' depth where visible, ``background`` elsewhere.

    Parameters
    ----------
    labels : (H, W) uint16
        Visible instance labels.
    depth : (H, W) float32
        Nearest object depth, metres.
    background : (H, W) float32 or None
        Real (or room) depth, metres, 0 = invalid; None = zeros.
    """
    bg = np.zeros_like(depth) if background is None else background.astype(np.float32)
    return np.where(labels > 0, depth, bg).astype(np.float32)


def written_depth(labels: np.ndarray, depth: np.ndarray, real_depth: np.ndarray | None,
                  room_depth: np.ndarray | None, hidden_by_room: np.ndarray | None,
                  fill_room: bool) -> np.ndarray:
    """The dataset's depth image, metres (0 = invalid): what ``depth/`` holds and visibility is judged on.

    The objects' depth where they are visible; elsewhere the real sensor depth where it is valid; where it
    is not, the room mesh's rendered depth at the pixels where the room hides an object (so the depth
    says why the object is not visible there, and bop_toolkit's rule, which counts missing depth as
    visible, agrees with ``mask_visib``), and everywhere else when ``fill_room`` (``composite.depth_fill
    = "room"``, or a scan without sensor depth).
    """
    d = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    room = None if room_depth is None else np.nan_to_num(np.asarray(room_depth, np.float32), nan=0.0,
                                                         posinf=0.0, neginf=0.0)
    bg = np.zeros_like(d) if real_depth is None else np.nan_to_num(
        np.asarray(real_depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    if room is not None:
        fill = np.ones(bg.shape, bool) if fill_room else (
            np.zeros(bg.shape, bool) if hidden_by_room is None else np.asarray(hidden_by_room, bool))
        bg = np.where((bg <= 0) & fill, room, bg)
    return np.maximum(compose_depth(np.asarray(labels), d, bg), 0.0).astype(np.float32)


def quantize_depth(depth_m: np.ndarray, depth_scale_mm: float) -> np.ndarray:
    """``depth_m`` as the uint16 PNG stores it and a reader gets it back, metres (0 = invalid).

    ``round(depth_mm / depth_scale)``; values of 0 or beyond 65535 are stored as 0 (invalid), exactly as
    :func:`pipeline.export_bop.depth_png` writes them.
    """
    v = np.round(np.asarray(depth_m, np.float64) * 1000.0 / depth_scale_mm)
    ok = (v > 0) & (v <= np.iinfo(np.uint16).max)
    return np.where(ok, v * depth_scale_mm / 1000.0, 0.0).astype(np.float32)


def ray_length_factor(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) float64 distance / z-depth along each pixel centre's ray (bop_toolkit's
    ``misc.depth_im_to_dist_im_fast``, which turns depth into distance from the camera centre)."""
    u, v = image_plane(K, width, height)
    return np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)


def bop_visib_masks(crops: list, shape: tuple[int, int], n: int, depth_written: np.ndarray,
                    K: np.ndarray, delta: float) -> np.ndarray:
    """(N, H, W) bool ``mask_visib`` by bop_toolkit's rule (``visibility.estimate_visib_mask_gt``,
    ``bop19``), as its ``calc_gt_info.py`` applies it: an object pixel is visible where its distance from
    the camera is at most ``delta`` metres beyond the written depth's, or where the written depth is
    missing (0).

    Parameters
    ----------
    crops : list of N ``(depth (h, w) float32, x0, y0)`` or None
        Each instance's own depth (alone, amodal) over its window; 0 = not covered.
    shape : (H, W)
    depth_written : (H, W) float32 metres, as read back from the dataset (:func:`quantize_depth`).
    """
    h, w = shape
    out = np.zeros((n, h, w), bool)
    f = ray_length_factor(np.asarray(K, np.float64), w, h)
    dist_w = depth_written.astype(np.float64) * f
    for i, c in enumerate(crops):
        if c is None:
            continue
        d, x0, y0 = c
        hh, ww = d.shape
        fi = f[y0:y0 + hh, x0:x0 + ww]
        dw = dist_w[y0:y0 + hh, x0:x0 + ww]
        dist_i = d.astype(np.float64) * fi
        out[i, y0:y0 + hh, x0:x0 + ww] = (d > 0) & ((dist_i - dw <= delta) | (dw == 0))
    return out


def bbox_xywh(mask: np.ndarray, x_off: int = 0, y_off: int = 0) -> tuple[int, int, int, int] | None:
    """``(x, y, w, h)`` of the True pixels of ``mask`` shifted by the mask's origin; None if empty."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    return (int(cols[0] + x_off), int(rows[0] + y_off), int(cols[-1] - cols[0] + 1),
            int(rows[-1] - rows[0] + 1))


def union_box(a: tuple[int, int, int, int] | None,
              b: tuple[int, int, int, int] | None) -> tuple[int, int, int, int] | None:
    """Smallest ``(x, y, w, h)`` box containing both (None = empty)."""
    if a is None:
        return b
    if b is None:
        return a
    x0, y0 = min(a[0], b[0]), min(a[1], b[1])
    x1, y1 = max(a[0] + a[2], b[0] + b[2]), max(a[1] + a[3], b[1] + b[3])
    return (x0, y0, x1 - x0, y1 - y0)


def pack_masks(masks: np.ndarray) -> np.ndarray:
    """(N, H, W) bool -> (N, H, ceil(W/8)) uint8 bit-packed along rows."""
    return np.packbits(masks.astype(bool), axis=-1)


def unpack_masks(packed: np.ndarray, width: int) -> np.ndarray:
    """Inverse of :func:`pack_masks`: (N, H, ceil(W/8)) uint8 -> (N, H, W) bool."""
    return np.unpackbits(packed, axis=-1, count=width).astype(bool)


# ---------------------------------------------------------------------------------------------------
# Per-instance annotations
# ---------------------------------------------------------------------------------------------------

def instance_annotations(*, obj_ids: np.ndarray, R_m2c: np.ndarray, t_m2c: np.ndarray,
                         amodal: np.ndarray, px_outside: np.ndarray, box_outside: list,
                         visib: np.ndarray, valid_depth: np.ndarray, visib_threshold: float,
                         rects: list | None = None) -> list[dict]:
    """BOP ``scene_gt`` + ``scene_gt_info`` entries of every instance (metres; mm only in the writer).

    Parameters
    ----------
    obj_ids : (N,) int
    R_m2c, t_m2c : (N, 3, 3), (N, 3) float64
        Camera-from-model poses, metres.
    amodal : (N, H, W) bool
        Silhouette of each object alone, inside the image.
    px_outside : (N,) int
        Silhouette pixels outside the image (on the BOP canvas).
    box_outside : list of N ``(x, y, w, h)`` or None
        Box of the silhouette part outside the image, image pixel coordinates.
    visib : (N, H, W) bool
        Each instance's visible mask (``mask_visib``, :func:`bop_visib_masks`).
    valid_depth : (H, W) bool
        Pixels with a valid depth in the written depth image (as read back).
    visib_threshold : float
        An instance counts as visible (``"visible": true``) from this visible fraction on.
    rects : list of N ``(x0, y0, x1, y1)`` or None, optional
        Image rectangle holding each instance's silhouette (None = empty); counting is restricted to
        it (same result, less work). Default: the whole image.

    Returns
    -------
    list of dict
        Keys: ``inst_id, obj_id, R_m2c, t_m2c, bbox_obj, bbox_visib, px_count_all, px_count_valid,
        px_count_visib, visib_fract, visible``.
    """
    out = []
    h, w = valid_depth.shape
    for i in range(len(obj_ids)):
        r = (0, 0, w, h) if rects is None else rects[i]
        if r is None:
            r = (0, 0, 0, 0)
        x0, y0, x1, y1 = r
        m = amodal[i, y0:y1, x0:x1]
        vis = visib[i, y0:y1, x0:x1]
        px_in = int(m.sum())
        px_all = px_in + int(px_outside[i])
        px_visib = int(vis.sum())
        fract = px_visib / px_all if px_all > 0 else 0.0
        box_obj = union_box(bbox_xywh(m, x0, y0), box_outside[i]) if px_visib > 0 else None
        box_vis = bbox_xywh(vis, x0, y0) if px_visib > 0 else None
        out.append({
            "inst_id": i,
            "obj_id": int(obj_ids[i]),
            "R_m2c": np.asarray(R_m2c[i], dtype=np.float64).tolist(),
            "t_m2c": np.asarray(t_m2c[i], dtype=np.float64).tolist(),
            "bbox_obj": list(box_obj or NO_BOX),
            "bbox_visib": list(box_vis or NO_BOX),
            "px_count_all": px_all,
            "px_count_valid": int((m & valid_depth[y0:y1, x0:x1]).sum()),
            "px_count_visib": px_visib,
            "visib_fract": float(fract),
            "visible": bool(px_visib > 0 and fract >= visib_threshold),
        })
    return out
