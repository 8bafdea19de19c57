"""Independent references shared by the benchmarks and the tests: Open3D ray casting (not the pyrender
rasterizer the pipeline uses), mask IoU, and the distance from depth edges to photo edges measured with
OpenCV and NumPy only (not pipeline.registration's own measure)."""

from __future__ import annotations

import numpy as np


def raycast(meshes: list[tuple[np.ndarray, np.ndarray]], K: np.ndarray, T_c2w: np.ndarray, width: int,
            height: int, x0: int = 0, y0: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Z-depth and mesh index (-1 = none) of the nearest hit at each pixel centre of the window."""
    import warnings

    with warnings.catch_warnings():  # "built with CUDA support, but no suitable CUDA devices found"
        warnings.filterwarnings("ignore", message="Open3D was built with CUDA", category=ImportWarning)
        import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    ids = []
    for v, f in meshes:
        ids.append(scene.add_triangles(o3d.core.Tensor(np.asarray(v, np.float32)),
                                       o3d.core.Tensor(np.asarray(f, np.uint32))))
    u, v = np.meshgrid(np.arange(x0, x0 + width, dtype=np.float64), np.arange(y0, y0 + height, dtype=np.float64))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)  # z = 1
    d_w = d_cam @ T_c2w[:3, :3].T
    o_w = np.broadcast_to(T_c2w[:3, 3], d_w.shape)
    rays = np.concatenate([o_w, d_w], axis=-1).reshape(-1, 6).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    t = ans["t_hit"].numpy().reshape(height, width)
    gid = ans["geometry_ids"].numpy().reshape(height, width).astype(np.int64)
    hit = np.isfinite(t)
    lut = {int(g): i for i, g in enumerate(ids)}
    idx = np.full((height, width), -1, np.int64)
    for g, i in lut.items():
        idx[hit & (gid == g)] = i
    return np.where(hit, t, 0).astype(np.float32), idx


def masked_psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray, peak: float = 255.0) -> float:
    """PSNR (dB) of images ``a`` and ``b`` over the pixels in ``mask``: NaN for an empty mask, inf when equal."""
    if not mask.any():
        return float("nan")
    d = a[mask].astype(np.float64) - b[mask].astype(np.float64)
    mse = float(np.mean(d * d))
    return float("inf") if mse == 0 else float(10 * np.log10(peak ** 2 / mse))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    u = np.logical_or(a, b).sum()
    return 1.0 if u == 0 else float(np.logical_and(a, b).sum() / u)


def depth_photo_edge_distance(depth: np.ndarray, rgb: np.ndarray) -> float:
    """Median distance (px) from depth discontinuities to the photo's Canny edges, with OpenCV and NumPy
    only (not the module's own measure): a pixel is a depth edge when a 4-neighbour's depth is more than
    5 % + 3 cm farther away."""
    near = np.zeros(depth.shape, bool)
    for axis in (0, 1):
        a, b = (depth[:-1], depth[1:]) if axis == 0 else (depth[:, :-1], depth[:, 1:])
        ok = (a > 0) & (b > 0)
        jump = ok & (np.abs(a - b) > 0.05 * np.minimum(a, b) + 0.03)
        first = jump & (a < b)
        second = jump & (b < a)
        if axis == 0:
            near[:-1] |= first
            near[1:] |= second
        else:
            near[:, :-1] |= first
            near[:, 1:] |= second
    import cv2

    gray = cv2.GaussianBlur(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), (0, 0), 1.0)
    edges = cv2.Canny(gray, 20, 60)
    dist = cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 5)
    return float(np.median(dist[near])) if near.any() else float("nan")
