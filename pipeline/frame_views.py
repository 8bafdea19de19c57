"""Which frames see a drop: the raster stage's three rejection checks, predicted without rendering.

The raster stage rejects a frame when the dropped objects cover less than ``raster.min_visible_area`` of
it, by three checks in turn (:func:`pipeline.raster.render_frame`): "bound" (the objects' projected
windows), "amodal" (their silhouettes) and "visible" (their pixels in front of the room). Its plan asks
this module which kept frames would pass, so that no raster work goes to frames that cannot.

* **bound** is computed exactly as the raster stage computes it: :func:`pipeline.annotate.projected_window`
  of each object's convex-hull vertices (:func:`pipeline.geometry.hull_mesh`, the rasterizer's own
  hull), summed with :func:`pipeline.annotate.window_area_in_image`.
* **amodal** is estimated by the union of the objects' convex silhouettes (the projected hull's 2-D
  convex hull), filled at half the render resolution: an upper bound up to the objects' concavities.
* **visible** is estimated from the sensor depth, the measurement the room mesh was fused from: a
  sample of each object's surface points is projected into the frame's depth camera; the share of the
  points inside the image that lie in front of the measured surface (within the fusion tolerance)
  scales that object's silhouette. The depth image is read as stored (no registration), once per frame.

Everything depends only on the run's inputs (no cache that a previous run may or may not have left), so
a plan is the same whether the raster stage ran before or not.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from pipeline import annotate
from pipeline.camera import Camera
from pipeline.geometry import hull_mesh
from pipeline.types import ObjectModel, Placement, Scan

PLAN_DOWNSCALE = 2     # silhouette masks at 1/this of the render resolution (a coarser grid inflates
                       # small silhouettes by its half-cell border)
SURFACE_SAMPLES = 256  # surface points per object tested against the sensor depth (every k-th vertex)
SUBPIXEL_BITS = 4      # fractional bits of the polygon corners handed to cv2.fillConvexPoly
# The estimated shares must clear raster.min_visible_area by this factor. Convex silhouettes filled on the
# coarse grid overestimate the raster's pixel counts: on configs/7scenes.toml (LM-O objects) the ratio of
# estimate to raster count is 1.15 / 1.24 / 1.38 (10th / 50th / 90th percentile) for the silhouettes and
# 1.16 / 1.25 / 1.42 for the visible pixels, so few frames that pass are estimated below this.
PLAN_MARGIN = 1.15


@dataclass(frozen=True)
class ObjectShape:
    """What the prediction needs of an object model."""

    hull: np.ndarray     # (H, 3) float64, convex-hull vertices, model frame, metres
    edges: np.ndarray    # (E, 2) int64, vertex pairs of ``hull`` spanning its edges (every pair when flat)
    samples: np.ndarray  # (S, 3) float64, surface points (a stride of the vertices), model frame, metres
    center: np.ndarray   # (3,) float64, centre of a sphere holding ``hull``, model frame, metres
    radius: float        # that sphere's radius, metres


def object_shape(obj: ObjectModel) -> ObjectShape:
    """The hull (the rasterizer's :meth:`~pipeline.render_gl.MeshRasterizer.hull_vertices`), its edges,
    a bounding sphere and surface samples of ``obj``."""
    v = np.asarray(obj.vertices, dtype=np.float64)
    hull, tri = hull_mesh(v)
    if tri is None:
        i, j = np.triu_indices(len(hull), 1)
        edges = np.stack([i, j], axis=1)
    else:
        e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
        edges = np.unique(np.sort(e, axis=1), axis=0)
    center = 0.5 * (hull.min(axis=0) + hull.max(axis=0))
    stride = max(1, -(-len(v) // SURFACE_SAMPLES))
    return ObjectShape(hull=hull, edges=edges.astype(np.int64), samples=v[::stride], center=center,
                       radius=float(np.linalg.norm(hull - center, axis=1).max()))


@dataclass(frozen=True)
class SensorDepth:
    """A frame's depth image as stored, with the camera that took it."""

    depth: np.ndarray    # (h, w) float32, metres along the depth camera's z axis, 0 = invalid
    K: np.ndarray        # (3, 3) float64, depth intrinsics at (w, h)
    T_c2d: np.ndarray    # (4, 4) float64, colour camera -> depth camera, metres


def sensor_depth(scan: Scan, frame: int) -> SensorDepth | None:
    """The stored depth of ``frame`` (None when the frame has none)."""
    from pipeline.scanformats.common import read_depth_raw

    if not scan.depth_paths[frame]:
        return None
    T_d2c = np.asarray(scan.meta.get("T_d2c", np.eye(4)), dtype=np.float64)
    return SensorDepth(depth=read_depth_raw(scan, frame), K=np.asarray(scan.depth_K[frame], np.float64),
                       T_c2d=np.linalg.inv(T_d2c))


@dataclass(frozen=True)
class FrameView:
    """How much of a frame one drop's objects cover, as the raster stage's checks measure it."""

    frame: int
    bound: float     # share of the image inside the objects' projected windows (exact)
    amodal: float    # estimated share covered by the objects' silhouettes
    visible: float   # estimated share of object pixels in front of the room

    def check(self, min_area: float) -> str:
        """The raster check predicted to reject the frame at ``min_area``, or "" when it passes (the
        estimates must clear it by :data:`PLAN_MARGIN`)."""
        if self.bound < min_area:
            return "bound"
        for name, share in (("amodal", self.amodal), ("visible", self.visible)):
            if share < min_area * PLAN_MARGIN:
                return name
        return ""


def _in_front(points_c: np.ndarray, sensor: SensorDepth | None, tol_abs: float, tol_rel: float) -> np.ndarray:
    """(P,) bool: the colour-camera points not behind the measured surface (True where unmeasured)."""
    if sensor is None:
        return np.ones(len(points_c), bool)
    p = points_c @ sensor.T_c2d[:3, :3].T + sensor.T_c2d[:3, 3]
    z = p[:, 2]
    h, w = sensor.depth.shape
    ok = z > 1e-6
    uv = p[:, :2] / np.where(ok, z, 1.0)[:, None] @ sensor.K[:2, :2].T + sensor.K[:2, 2]
    c, r = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
    ok &= (c >= 0) & (c < w) & (r >= 0) & (r < h)
    d = np.zeros(len(p), np.float32)
    d[ok] = sensor.depth[r[ok], c[ok]]
    return ~((d > 0) & (z > d + tol_abs + tol_rel * d))


def _clip_near(points_c: np.ndarray, edges: np.ndarray, znear: float) -> np.ndarray:
    """Points whose convex hull is that of ``points_c`` cut by the near plane ``z = znear`` (the part
    the renderer draws): the points in front of it and the plane's crossings of the hull's ``edges``."""
    front = points_c[:, 2] > znear
    if front.all() or not front.any():
        return points_c[front]
    a, b = points_c[edges[:, 0]], points_c[edges[:, 1]]
    crossing = front[edges[:, 0]] != front[edges[:, 1]]
    a, b = a[crossing], b[crossing]
    s = (a[:, 2] - znear) / (a[:, 2] - b[:, 2])
    cut = a + s[:, None] * (b - a)
    cut[:, 2] = znear
    return np.concatenate([points_c[front], cut])


def _side_planes(K: np.ndarray, width: int, height: int, margin: float) -> np.ndarray:
    """(4, 3) unit normals of the frustum's side planes through the camera centre, pointing out of it,
    placed ``margin`` pixels beyond the image's outer pixel edges (left, right, top, bottom)."""
    u0, u1 = (-0.5 - margin - K[0, 2]) / K[0, 0], (width - 0.5 + margin - K[0, 2]) / K[0, 0]
    v0, v1 = (-0.5 - margin - K[1, 2]) / K[1, 1], (height - 0.5 + margin - K[1, 2]) / K[1, 1]
    n = np.array([[-1.0, 0.0, u0], [1.0, 0.0, -u1], [0.0, -1.0, v0], [0.0, 1.0, -v1]])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _outside_frustum(points_c: np.ndarray, planes: np.ndarray) -> bool:
    """Whether every point lies beyond one of the side ``planes``: nothing of their hull reaches the image."""
    return bool(np.any(np.all(points_c @ planes.T > 0.0, axis=0)))


def _silhouette(uv: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) bool: the convex hull of image points ``uv`` (render pixels) filled on the coarse grid."""
    import cv2

    s = 1.0 / PLAN_DOWNSCALE
    g = ((uv + 0.5) * s - 0.5) * (1 << SUBPIXEL_BITS)
    g = np.clip(g, -1e6, 1e6)    # cv2 takes int32 corners; far-off corners only need to stay far off
    hull = cv2.convexHull(np.rint(g).astype(np.int32).reshape(-1, 1, 2))
    mask = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(mask, hull, 1, lineType=cv2.LINE_8, shift=SUBPIXEL_BITS)
    return mask.astype(bool)


def frame_view(*, frame: int, K: np.ndarray, T_c2w: np.ndarray, width: int, height: int, placement: Placement,
               shapes: dict[int, ObjectShape], sensor: Callable[[], SensorDepth | None], znear: float,
               tol_abs: float, tol_rel: float, min_area: float = 0.0) -> FrameView:
    """Predict the raster checks' shares for one frame of one drop.

    Parameters
    ----------
    K, T_c2w, width, height
        The frame's camera at the render resolution (as the raster stage renders it).
    shapes
        ``obj_id -> ObjectShape`` of every object in ``placement``.
    sensor
        Returns the frame's stored depth (:func:`sensor_depth`), or None (no occlusion is predicted);
        called only when the silhouettes pass.
    znear
        The rasterizer's near clip plane, metres.
    tol_abs, tol_rel
        A surface point counts as hidden when the measured depth is nearer by more than
        ``tol_abs + tol_rel * depth`` (``raster.fusion_tol_abs``, ``raster.fusion_tol_rel``): the points
        of an object resting on a surface lie within noise of it.
    min_area
        The shares after the first one below it (with :data:`PLAN_MARGIN` for the estimates) are not
        estimated and reported as 0: the frame is rejected anyway.
    """
    cam = Camera(K=np.asarray(K, np.float64), T_c2w=np.asarray(T_c2w, np.float64), width=width, height=height)
    R_m2c, t_m2c = cam.poses_m2c(placement.R_m2w, placement.t_m2w)
    area = float(width * height)
    # projected_window's rounding reaches 2 pixels beyond the image: a sphere beyond these planes has none
    cull = _side_planes(cam.K, width, height, 2.0)
    sides = _side_planes(cam.K, width, height, 0.0)
    bound, posed = 0.0, []
    for i, oid in enumerate(placement.obj_ids):
        shape = shapes[int(oid)]
        c = R_m2c[i] @ shape.center + t_m2c[i]
        if c[2] + shape.radius <= znear:                       # behind the near plane: no window
            continue
        if c[2] - shape.radius > znear and np.any(cull @ c > shape.radius):
            continue                                           # wholly beside the image: window outside it
        window = annotate.projected_window(cam.K, R_m2c[i], t_m2c[i], shape.hull, width, height, znear)
        inside = annotate.window_area_in_image(window, width, height)
        bound += inside
        hull_c = shape.hull @ R_m2c[i].T + t_m2c[i]
        if inside and not _outside_frustum(hull_c, sides):
            posed.append((shape, i, hull_c))
    if bound / area < min_area:
        return FrameView(frame=int(frame), bound=bound / area, amodal=0.0, visible=0.0)
    grid = (-(-height // PLAN_DOWNSCALE), -(-width // PLAN_DOWNSCALE))
    masks = [_silhouette(cam.project_cam(_clip_near(hull_c, shape.edges, znear))[0], grid)
             for shape, _, hull_c in posed]
    cover = np.zeros(grid, bool)
    for m in masks:
        cover |= m
    cell = area / cover.size
    amodal = min(1.0, float(cover.sum()) * cell / area)
    if amodal < min_area * PLAN_MARGIN:
        return FrameView(frame=int(frame), bound=bound / area, amodal=amodal, visible=0.0)
    depth = sensor()
    seen = np.zeros(grid, np.float32)
    for (shape, i, _), m in zip(posed, masks):
        pts = shape.samples @ R_m2c[i].T + t_m2c[i]
        uv, z = cam.project_cam(pts)
        inside = (z > znear) & (uv[:, 0] > -0.5) & (uv[:, 0] < width - 0.5) & (uv[:, 1] > -0.5) \
            & (uv[:, 1] < height - 0.5)
        frac = float(_in_front(pts[inside], depth, tol_abs, tol_rel).mean()) if inside.any() else 1.0
        seen[m] = np.maximum(seen[m], np.float32(frac))
    return FrameView(frame=int(frame), bound=bound / area, amodal=amodal,
                     visible=min(1.0, float(seen.sum()) * cell / area))


def seeing_frames(views: list[FrameView], min_area: float, limit: int = 0) -> list[int]:
    """Frames predicted to pass every raster check, in frame order; with ``limit`` > 0 only the ``limit``
    with the largest predicted visible share (ties: the lower frame index)."""
    ok = [v for v in views if not v.check(min_area)]
    if limit > 0:
        ok = sorted(ok, key=lambda v: (-v.visible, v.frame))[:limit]
    return sorted(v.frame for v in ok)
