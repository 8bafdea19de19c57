"""Colour camera from the data: intrinsics and ``T_d2c`` that line depth edges up with the photos' edges.

Some scans ship the depth camera's calibration only (7-Scenes: one K of 585 px, poses of the depth
camera) although the photos come from another camera (shorter focal length, a few centimetres away).
This module estimates the colour camera from the frames themselves:

1. **Depth edges.** In each frame's depth map, every pair of valid neighbours whose depths differ by a
   jump (:data:`JUMP_REL` of the nearer depth plus :data:`JUMP_ABS`) gives one 3D point: the midpoint
   of the two pixel centres in the image, at the *nearer* depth (the silhouette belongs to the
   foreground), unprojected with the depth intrinsics. Pixels without depth give no points.
2. **Photo edges.** The photo's gray image, lightly blurred, through ``cv2.Canny`` and
   ``cv2.distanceTransform``: each pixel's distance to the nearest photo edge, in pixels.
3. **Score.** For a candidate colour camera (``fx, fy, cx, cy`` and a small rigid ``T_d2c``), the depth
   edge points are moved into the colour camera, projected, and the distance transform is read there
   (bilinear). Points outside the photo count as the truncation distance.
4. **Fit.** A coarse grid on focal scale about the principal point and a pixel shift (the dominant
   effect), then Gauss-Newton on all ten parameters (``fx, fy, cx, cy``, rotation, translation): each
   depth edge point is paired with its nearest photo edge pixel (within a shrinking radius) and its
   residual is the distance along that edge's normal to the edge's sub-pixel position (Huber weights),
   with weak priors holding rotation and translation near zero (rotation and principal point,
   translation and principal point are nearly interchangeable; the priors settle what the data cannot).

The per-frame figure is the median distance (pixels) from the projected depth edge points inside the
photo to the nearest photo edge, before (the scan's own colour camera) and after the fit.

Examples
--------
>>> from pipeline.scanformats.detect import read_scan   # doctest: +SKIP
>>> reg = estimate_color_camera(read_scan("scans/7scenes-redkitchen"))   # doctest: +SKIP
>>> reg.reliable, reg.color_K[0, 0], reg.median_before_px, reg.median_after_px   # doctest: +SKIP
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.camera import project_points, transform_points, unproject_points
from pipeline.types import Scan

__all__ = ["Registration", "FrameEdges", "frame_edges", "depth_edge_points", "photo_edges", "edge_distances",
           "fit_color_camera", "estimate_color_camera", "pose_from_params", "register_scan", "registration_figures",
           "fit_frames"]

JUMP_REL = 0.04          # a depth jump is at least 4 % of the nearer depth ...
JUMP_ABS = 0.03          # ... plus 3 cm (Kinect noise at 3 m is ~1-2 cm)
TRUNC_PX = 6.0           # the fine fit pairs points with photo edges this close (pixels) at first ...
TRUNC_MIN_PX = 2.0       # ... shrinking to this
HUBER_PX = 0.5           # Huber threshold of the fine fit's point-to-edge residuals, pixels
COARSE_TRUNC_PX = 15.0   # ... and here in the coarse grid
MIN_POINTS_PER_FRAME = 50
MIN_FRAMES = 2
MAX_MEDIAN_PX = 4.0      # a fit whose median edge distance stays above this did not find the photos' edges
PRIOR_ROT_DEG = 5.0      # weak priors on T_d2c (1 sigma): a rig's cameras are near-parallel ...
PRIOR_T_M = 0.05         # ... and a few centimetres apart


@dataclass(frozen=True)
class Registration:
    """The colour camera found from the data, and how well depth edges then meet the photos' edges."""

    color_K: np.ndarray            # (3, 3) float64, colour intrinsics at the photo size, pixels
    T_d2c: np.ndarray              # (4, 4) float64, depth camera -> colour camera, metres
    frames: np.ndarray             # (F,) int64, indices (into the scan) of the frames used in the fit
    before_px: np.ndarray          # (F,) float64, per-frame median edge distance with the initial camera
    after_px: np.ndarray           # (F,) float64, per-frame median edge distance with the fitted camera
    median_before_px: float        # median of before_px (nan when no frame could be measured)
    median_after_px: float         # median of after_px
    reliable: bool                 # True when the fit can be used
    reason: str = ""               # one line, why not reliable ("" when reliable)


@dataclass(frozen=True)
class FrameEdges:
    """One frame's material for the fit: depth edge points and the photo's edge distance."""

    points_d: np.ndarray   # (N, 3) float64, depth edge points, depth camera frame, metres
    dist: np.ndarray       # (H, W) float32, distance to the nearest photo edge, pixels
    nearest: np.ndarray    # (H, W) int32, index into edge_uv of each pixel's nearest photo edge pixel
    edge_uv: np.ndarray    # (E, 2) float64, sub-pixel photo edge positions (u, v), pixels
    edge_n: np.ndarray     # (E, 2) float64, unit normals of the photo edges (image gradient direction)


def depth_edge_points(depth: np.ndarray, K_d: np.ndarray, *, max_points: int | None = None,
                      rng: np.random.Generator | None = None) -> np.ndarray:
    """3D points on the depth map's discontinuities, on the foreground side.

    Parameters
    ----------
    depth : (H, W) float32 metres, 0 = invalid.
    K_d : (3, 3) depth intrinsics.
    max_points : keep at most this many (a random subset drawn with ``rng``; required then).

    Returns
    -------
    (N, 3) float64, depth camera frame, metres: for each horizontal or vertical pair of valid neighbours
    across a jump, the midpoint of the two pixel centres at the nearer depth.
    """
    d = np.asarray(depth, np.float32)
    pts = []
    for axis in (1, 0):
        a = d[:, :-1] if axis == 1 else d[:-1, :]
        b = d[:, 1:] if axis == 1 else d[1:, :]
        near = np.minimum(a, b)
        jump = (a > 0) & (b > 0) & (np.abs(a - b) > JUMP_REL * near + JUMP_ABS)
        r, c = np.nonzero(jump)
        u = c + (0.5 if axis == 1 else 0.0)
        v = r + (0.5 if axis == 0 else 0.0)
        pts.append(unproject_points(K_d, u, v, near[r, c]))
    p = np.concatenate(pts, axis=0) if pts else np.zeros((0, 3))
    if max_points is not None and len(p) > max_points:
        p = p[np.sort(rng.choice(len(p), max_points, replace=False))]
    return p


def photo_edges(rgb: np.ndarray, *, blur_sigma: float = 1.0, canny: tuple[float, float] = (20.0, 60.0)
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The photo's edges: Canny edges of the lightly blurred gray photo ``rgb (H, W, 3) uint8``.

    Returns
    -------
    dist : (H, W) float32, distance (pixels) from each pixel to the nearest edge pixel; ``inf`` everywhere
        when the photo has no edge.
    nearest : (H, W) int32, index of that nearest edge pixel into the next two arrays.
    edge_uv : (E, 2) float64, each edge pixel moved to the gradient maximum along the gradient (sub-pixel,
        a parabola through three samples).
    edge_n : (E, 2) float64, unit gradient direction at each edge pixel.
    """
    import cv2

    gray = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    if blur_sigma > 0:
        gray = cv2.GaussianBlur(gray, (0, 0), blur_sigma)
    edges = cv2.Canny(gray, canny[0], canny[1], L2gradient=True)
    H, W = gray.shape
    r, c = np.nonzero(edges)
    if not len(r):
        return (np.full((H, W), np.inf, np.float32), np.zeros((H, W), np.int32), np.zeros((0, 2)),
                np.zeros((0, 2)))
    dist, labels = cv2.distanceTransformWithLabels(np.where(edges > 0, 0, 255).astype(np.uint8), cv2.DIST_L2,
                                                   cv2.DIST_MASK_PRECISE, labelType=cv2.DIST_LABEL_PIXEL)
    lab2edge = np.zeros(int(labels.max()) + 1, np.int32)
    lab2edge[labels[r, c]] = np.arange(len(r), dtype=np.int32)
    g = gray.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.hypot(gx, gy)
    n = np.stack([gx[r, c], gy[r, c]], axis=1).astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    uv = np.stack([c, r], axis=1).astype(np.float64)
    m0 = mag[r, c].astype(np.float64)
    mm = _sample(mag, uv - n, m0)
    mp = _sample(mag, uv + n, m0)
    den = mm - 2 * m0 + mp
    off = np.where(den < -1e-6, 0.5 * (mm - mp) / np.where(den < -1e-6, den, -1.0), 0.0)
    uv = uv + np.clip(off, -0.5, 0.5)[:, None] * n
    return dist, lab2edge[labels], uv, n


def pose_from_params(rvec: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4, 4) rigid transform of a rotation vector ``rvec (3,)`` (radians) and translation ``t (3,)``."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.asarray(rvec, np.float64)).as_matrix()
    T[:3, 3] = t
    return T


def _sample(dist: np.ndarray, uv: np.ndarray, fill: float) -> np.ndarray:
    """Bilinear samples of ``dist (H, W)`` at ``uv (N, 2)``; ``fill`` outside the image."""
    H, W = dist.shape
    u, v = uv[:, 0], uv[:, 1]
    ok = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (v >= 0) & (u <= W - 1) & (v <= H - 1)
    out = np.full(len(uv), fill, np.float64)
    if ok.any():
        u, v = u[ok], v[ok]
        u0 = np.minimum(np.floor(u).astype(np.int64), W - 2)
        v0 = np.minimum(np.floor(v).astype(np.int64), H - 2)
        fu, fv = u - u0, v - v0
        d00, d01 = dist[v0, u0], dist[v0, u0 + 1]
        d10, d11 = dist[v0 + 1, u0], dist[v0 + 1, u0 + 1]
        out[ok] = (d00 * (1 - fu) + d01 * fu) * (1 - fv) + (d10 * (1 - fu) + d11 * fu) * fv
    return out


def _project(points_d: np.ndarray, K_c: np.ndarray, T_d2c: np.ndarray) -> np.ndarray:
    uv, z = project_points(K_c, transform_points(T_d2c, points_d))
    uv[z <= 1e-6] = np.nan
    return uv


def edge_distances(frames: list[FrameEdges], K_c: np.ndarray, T_d2c: np.ndarray) -> np.ndarray:
    """Per frame, the median distance (pixels) from the depth edge points seen through the colour camera
    ``K_c``, ``T_d2c`` (those landing inside the photo) to the nearest photo edge; ``nan`` when none lands
    inside. Returns (F,) float64."""
    out = np.full(len(frames), np.nan)
    for k, f in enumerate(frames):
        if not len(f.points_d) or not np.isfinite(f.dist).any():
            continue
        s = _sample(f.dist, _project(f.points_d, K_c, T_d2c), np.nan)
        s = s[np.isfinite(s)]
        if len(s):
            out[k] = float(np.median(s))
    return out


def _coarse_grid(cost, K0: np.ndarray) -> np.ndarray:
    """Best ``(dfx, dfy, dcx, dcy)`` of a scale about the principal point and a pixel shift, on a grid
    refined twice around its best cell; ``cost(K)`` is the mean truncated distance at ``K``."""

    def c(s, du, dv):
        K = K0.copy()
        K[:2, :2] *= s
        K[0, 2] += du
        K[1, 2] += dv
        return cost(K)

    s0, u0, v0 = 1.0, 0.0, 0.0
    for ds, n_s, dp, n_p in ((0.02, 8, 4.0, 6), (0.005, 3, 1.0, 3), (0.002, 2, 0.5, 2)):
        grid = [(s0 + i * ds, u0 + j * dp, v0 + k * dp) for i in range(-n_s, n_s + 1)
                for j in range(-n_p, n_p + 1) for k in range(-n_p, n_p + 1)]
        s0, u0, v0 = min(grid, key=lambda g: c(*g))
    return np.array([(s0 - 1) * K0[0, 0], (s0 - 1) * K0[1, 1], u0, v0])


def fit_color_camera(frames: list[FrameEdges], K0: np.ndarray, T0: np.ndarray | None = None, *,
                     coarse: bool = True, prior_weight: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Fit ``(K_c, T_d2c)`` so that depth edges land on the photos' edges, starting from ``K0``, ``T0``.

    Parameters
    ----------
    frames : per-frame depth edge points and photo edge distances (:class:`FrameEdges`), all photos of
        one size.
    K0 : (3, 3) initial colour intrinsics; T0 : (4, 4) initial ``T_d2c`` (identity when None).
    coarse : first search focal scale about the principal point and a pixel shift on a grid.
    prior_weight : strength of the priors holding rotation and translation near ``T0`` (0 = none).

    Returns
    -------
    K_c (3, 3) float64, T_d2c (4, 4) float64.
    """
    K0 = np.asarray(K0, np.float64)
    T0 = np.eye(4) if T0 is None else np.asarray(T0, np.float64)
    # All frames' points moved into the initial colour camera once; the fit moves them further.
    pts = [transform_points(T0, f.points_d) for f in frames]
    P = np.concatenate(pts, axis=0)
    fid = np.concatenate([np.full(len(p), k) for k, p in enumerate(pts)])
    H, W = frames[0].dist.shape
    Dc = np.stack([np.minimum(f.dist, 4 * COARSE_TRUNC_PX) for f in frames]).astype(np.float32)

    def coarse_cost(K, sel):
        """Mean truncated distance at the points ``sel`` seen through ``K`` (and T = identity)."""
        uv, z = project_points(K, P[sel])
        u, v = uv[:, 0], uv[:, 1]
        ok = (z > 1e-6) & (u >= 0) & (v >= 0) & (u <= W - 1) & (v <= H - 1)
        r = np.full(len(z), COARSE_TRUNC_PX)
        u, v, k = u[ok], v[ok], fid[sel][ok]
        u0 = np.minimum(u.astype(np.int64), W - 2)
        v0 = np.minimum(v.astype(np.int64), H - 2)
        fu, fv = u - u0, v - v0
        s = ((Dc[k, v0, u0] * (1 - fu) + Dc[k, v0, u0 + 1] * fu) * (1 - fv)
             + (Dc[k, v0 + 1, u0] * (1 - fu) + Dc[k, v0 + 1, u0 + 1] * fu) * fv)
        r[ok] = np.minimum(s, COARSE_TRUNC_PX)
        return float(np.mean(r))

    K = K0.copy()
    if coarse:
        sub = np.random.default_rng(0).permutation(len(P))[:3000]
        K[0, 0], K[1, 1], K[0, 2], K[1, 2] = np.array([K0[0, 0], K0[1, 1], K0[0, 2], K0[1, 2]]) + _coarse_grid(
            lambda Kc: coarse_cost(Kc, sub), K0)
    K, T = _refine(frames, pts, K, prior_weight)
    return K, T @ T0


def _refine(frames: list[FrameEdges], pts: list[np.ndarray], K: np.ndarray, prior_weight: float,
            iters: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on point-to-edge-line distances (ICP with the photos' sub-pixel edges): each projected
    depth edge point is paired with its nearest photo edge pixel within a shrinking distance, its residual
    is the signed distance along that edge's normal (Huber weights); unknowns are ``fx, fy, cx, cy`` and an
    increment of ``T`` (left-multiplied), with weak priors holding ``T`` near the identity."""
    H, W = frames[0].dist.shape
    T = np.eye(4)
    n_pts = sum(len(p) for p in pts)
    wp = prior_weight * 0.05 * np.sqrt(n_pts)
    sig_r, sig_t = np.deg2rad(PRIOR_ROT_DEG), PRIOR_T_M
    for it in range(iters):
        trunc = max(TRUNC_MIN_PX, TRUNC_PX * 0.85 ** it)
        J, res = [], []
        for f, p in zip(frames, pts):
            pc = transform_points(T, p)
            X, Y, Z = pc[:, 0], pc[:, 1], np.maximum(pc[:, 2], 1e-9)
            u, v = K[0, 0] * X / Z + K[0, 2], K[1, 1] * Y / Z + K[1, 2]
            ok = (pc[:, 2] > 1e-6) & (u >= 0) & (v >= 0) & (u <= W - 1) & (v <= H - 1)
            ui, vi = np.rint(u[ok]).astype(np.int64), np.rint(v[ok]).astype(np.int64)
            near = f.dist[vi, ui] <= trunc
            sel = np.nonzero(ok)[0][near]
            if not len(sel):
                continue
            e = f.nearest[vi[near], ui[near]]
            n, q = f.edge_n[e], f.edge_uv[e]
            X, Y, Z, P = X[sel], Y[sel], Z[sel], pc[sel]
            res.append(n[:, 0] * (u[sel] - q[:, 0]) + n[:, 1] * (v[sel] - q[:, 1]))
            a = np.stack([n[:, 0] * K[0, 0] / Z, n[:, 1] * K[1, 1] / Z,
                          -(n[:, 0] * K[0, 0] * X + n[:, 1] * K[1, 1] * Y) / Z ** 2], axis=1)
            J.append(np.column_stack([n[:, 0] * X / Z, n[:, 1] * Y / Z, n[:, 0], n[:, 1], np.cross(P, a), a]))
        if not res:
            break
        r, A = np.concatenate(res), np.concatenate(J)
        w = np.sqrt(np.minimum(1.0, HUBER_PX / np.maximum(np.abs(r), 1e-12)))
        rot = _rotvec(T)
        prior_A = np.zeros((6, 10))
        prior_A[:3, 4:7] = np.eye(3) * wp / sig_r
        prior_A[3:, 7:] = np.eye(3) * wp / sig_t
        prior_r = np.concatenate([rot * wp / sig_r, T[:3, 3] * wp / sig_t])
        dx = np.linalg.lstsq(np.vstack([A * w[:, None], prior_A]), -np.concatenate([r * w, prior_r]),
                             rcond=None)[0]
        K = K.copy()
        K[0, 0] += dx[0]
        K[1, 1] += dx[1]
        K[0, 2] += dx[2]
        K[1, 2] += dx[3]
        T = pose_from_params(dx[4:7], dx[7:10]) @ T
        if trunc <= TRUNC_MIN_PX and np.abs(dx[:4]).max() < 1e-3 and np.abs(dx[4:]).max() < 1e-6:
            break
    return K, T


def _rotvec(T: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(T[:3, :3]).as_rotvec()


def frame_edges(scan: Scan, i: int, *, max_points: int, rng: np.random.Generator) -> FrameEdges | None:
    """Frame ``i``'s :class:`FrameEdges`; None when it has no depth map or it cannot be read."""
    from pipeline.errors import InputError
    from pipeline.scanformats.common import read_color, read_depth_raw

    if not scan.depth_paths[i]:
        return None
    try:
        depth = read_depth_raw(scan, i)
        rgb = read_color(scan, i)
    except InputError:
        return None
    return FrameEdges(points_d=depth_edge_points(depth, scan.depth_K[i], max_points=max_points, rng=rng),
                      **dict(zip(("dist", "nearest", "edge_uv", "edge_n"), photo_edges(rgb))))


def estimate_color_camera(scan: Scan, frames: np.ndarray | None = None, *, max_points: int = 2000,
                          seed: int = 0, prior_weight: float = 1.0) -> Registration:
    """Estimate the colour camera of ``scan`` from its frames (see the module docstring).

    Parameters
    ----------
    scan : the scan; its ``K`` (frame ``frames[0]``) and ``meta["T_d2c"]`` are the starting camera.
    frames : indices of the frames to fit on (all frames when None).
    max_points : depth edge points kept per frame (a random subset drawn from ``seed``).
    prior_weight : strength of the weak priors keeping ``T_d2c`` near the start (0 = none).

    Returns
    -------
    :class:`Registration`; never raises on bad input: ``reliable`` is False with a one-line reason
    (too few frames with depth or edge points, photos without edges, no improvement, edges that do not
    line up).
    """
    idx = np.arange(scan.num_frames) if frames is None else np.asarray(frames, np.int64)
    K0 = np.asarray(scan.K[idx[0]] if len(idx) else np.eye(3), np.float64)
    T0 = np.asarray(scan.meta.get("T_d2c", np.eye(4)), np.float64)
    rng = np.random.default_rng(seed)
    used, data = [], []
    no_depth = no_points = no_edges = 0
    for i in idx:
        fe = frame_edges(scan, int(i), max_points=max_points, rng=rng)
        if fe is None:
            no_depth += 1
        elif len(fe.points_d) < MIN_POINTS_PER_FRAME:
            no_points += 1
        elif not np.isfinite(fe.dist).any():
            no_edges += 1
        else:
            used.append(int(i))
            data.append(fe)

    def fail(reason, before=np.zeros(0), after=np.zeros(0), K=K0, T=T0):
        return Registration(color_K=K, T_d2c=T, frames=np.asarray(used, np.int64), before_px=before,
                            after_px=after, median_before_px=_nanmedian(before),
                            median_after_px=_nanmedian(after), reliable=False, reason=reason)

    if len(data) < MIN_FRAMES:
        return fail(f"{len(data)} usable frame(s) of {len(idx)}, need {MIN_FRAMES} (without depth: "
                    f"{no_depth}; under {MIN_POINTS_PER_FRAME} depth edge points: {no_points}; photo without "
                    f"edges: {no_edges})")
    before = edge_distances(data, K0, T0)
    K, T = fit_color_camera(data, K0, T0, prior_weight=prior_weight)
    after = edge_distances(data, K, T)
    mb, ma = _nanmedian(before), _nanmedian(after)
    if not np.isfinite(ma):
        return fail("no overlap: no depth edge point lands inside the photos", before, after, K, T)
    if ma > MAX_MEDIAN_PX:
        return fail(f"no match: depth edges stay {ma:.2f} px from the photos' edges after the fit (limit "
                    f"{MAX_MEDIAN_PX} px)", before, after, K, T)
    if ma > mb + 0.05:
        return fail(f"no improvement: median edge distance {mb:.2f} px before, {ma:.2f} px after",
                    before, after, K, T)
    return Registration(color_K=K, T_d2c=T, frames=np.asarray(used, np.int64), before_px=before,
                        after_px=after, median_before_px=mb, median_after_px=ma, reliable=True)


def _nanmedian(x: np.ndarray) -> float:
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    return float(np.median(x)) if len(x) else float("nan")


# ---------------------------------------------------------------------------------------------------
# Applying the fit to a scan (ingest)
# ---------------------------------------------------------------------------------------------------

MIN_GAIN_PX = 0.2        # the data must beat the scan's own colour camera by this much (median) to replace it
MISALIGNED_PX = 2.0      # a scan whose median edge distance stays above this is reported as misaligned


def fit_frames(scan: Scan, n: int) -> np.ndarray:
    """Up to ``n`` frames with a depth map, evenly spread over the scan (indices, ascending)."""
    with_depth = np.flatnonzero([bool(p) for p in scan.depth_paths])
    if len(with_depth) <= n:
        return with_depth.astype(np.int64)
    return with_depth[np.unique(np.linspace(0, len(with_depth) - 1, n).round().astype(np.int64))]


def register_scan(scan: Scan, *, frames: int = 30) -> tuple[Scan, dict]:
    """Give ``scan`` the colour camera its data support, and say how well depth then meets the photos.

    The scan's own colour camera (the format's calibration, or for formats without one the depth
    camera's) stands unless :func:`estimate_color_camera` on up to ``frames`` frames is reliable and
    lowers the median edge distance by at least :data:`MIN_GAIN_PX`: a correctly calibrated scan is
    left alone, byte for byte. When the fit is used, every frame gets its intrinsics, ``meta["T_d2c"]``
    becomes the fitted offset, and the poses become the colour camera's: the depth camera stays where
    the scan put it (``T_c2w @ T_d2c`` before and after).

    Returns
    -------
    The scan (a new one when the fit is used) and the record for ``scan.json``: ``source`` ("format" or
    "estimated"), ``note`` (one line: what was done, or what could not be and why), the median edge
    distances before and after, the frames measured, and the colour camera in use.
    """
    import dataclasses

    K_all = np.asarray(scan.K, np.float64)
    T0 = np.asarray(scan.meta.get("T_d2c", np.eye(4)), np.float64)
    rec: dict = {"source": "format", "frames_max": int(frames)}
    idx = fit_frames(scan, frames)
    if not len(idx):
        rec["note"] = "not checked: the scan has no depth maps; the format's colour camera is used"
        return scan, rec
    if not np.allclose(K_all, K_all[:1], atol=1e-9):
        rec["note"] = "not estimated: the frames have different intrinsics; the format's colour camera is used"
        return scan, rec
    reg = estimate_color_camera(scan, idx)
    mb, ma = reg.median_before_px, reg.median_after_px
    rec.update({"frame_ids": [int(scan.frame_ids[i]) for i in reg.frames],
                "before_px": [round(float(x), 4) for x in reg.before_px],
                "median_before_px": _finite_or_none(mb), "median_fitted_px": _finite_or_none(ma)})
    use = reg.reliable and mb - ma >= MIN_GAIN_PX
    if use:
        rec["source"] = "estimated"
        rec["after_px"] = [round(float(x), 4) for x in reg.after_px]
        rec["median_after_px"] = _finite_or_none(ma)
        rec["note"] = (f"colour camera estimated from {len(reg.frames)} frames: median edge distance "
                       f"{mb:.2f} px -> {ma:.2f} px")
        T_new = np.asarray(reg.T_d2c, np.float64)
        F = scan.num_frames
        T_c2w = scan.T_c2w @ T0 @ np.linalg.inv(T_new)   # the depth camera stays put
        meta = dict(scan.meta, T_d2c=T_new.tolist())
        scan = dataclasses.replace(scan, K=np.repeat(np.asarray(reg.color_K, np.float64)[None], F, axis=0),
                                   T_c2w=T_c2w, depth_registered=False, meta=meta)
    else:
        rec["median_after_px"] = _finite_or_none(mb)
        why = reg.reason if not reg.reliable else (
            f"the fit ({ma:.2f} px) gains less than {MIN_GAIN_PX} px over the format's camera ({mb:.2f} px)")
        rec["note"] = f"format's colour camera kept: {why}"
    K = scan.K[0]
    dT = np.asarray(scan.meta.get("T_d2c", np.eye(4)), np.float64)
    rec.update({"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
                "T_d2c": dT.tolist(), "t_d2c_mm": float(np.linalg.norm(dT[:3, 3]) * 1000),
                "rot_d2c_deg": float(np.degrees(np.linalg.norm(_rotvec(dT))))})
    rec["misaligned"] = rec["median_after_px"] is not None and rec["median_after_px"] > MISALIGNED_PX
    return scan, rec


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def registration_figures(rec: dict) -> dict:
    """The few figures of a :func:`register_scan` record that the run report shows."""
    out = {"colour camera": rec.get("source", "format"), "median edge distance before, px": rec.get("median_before_px"),
           "median edge distance after, px": rec.get("median_after_px"), "frames measured": len(rec.get("frame_ids", []))}
    for k in ("fx", "fy", "cx", "cy", "t_d2c_mm", "rot_d2c_deg"):
        if k in rec:
            out[k] = rec[k]
    return out
