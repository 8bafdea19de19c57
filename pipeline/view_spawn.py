"""Where the selected cameras look: spawn regions for drops that the kept frames actually see.

A real scan's cameras are fixed, so a drop spread over the whole room (the published recipe) leaves
most frames with one small object or none, and the raster stage rejects them. This module votes, over
the kept frames, for horizontal cells of the room whose upward-facing surface (floor, table, shelf) is
seen near the image centre and not too far away; a drop then spawns above one such cell (sampled with
probability growing with its votes), so its objects come to rest where many kept frames see them.

The votes come from the scan's own depth maps (what the camera sees, not the room mesh): each kept
frame is back-projected on a coarse pixel grid, normals come from neighbouring grid points, and every
cell a frame sees counts once for that frame, weighted by ``(near / depth)^2`` (capped at 1), i.e. by
how large an object there appears.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from pipeline.camera import unproject_points

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ViewMap:
    """Votes of the kept frames for horizontal cells of the room.

    Attributes
    ----------
    R_w2g
        (3, 3) float64 world -> gravity frame (z = up); cells are in its x/y.
    cell
        Cell edge, metres.
    centers
        (C, 2) float64 cell centres (gravity-frame x, y), metres.
    score
        (C,) float64 summed per-frame weights (0..number of frames).
    frames
        Number of frames that voted.
    top
        (C,) float64 height (gravity-frame z) of the highest upward-facing surface a frame saw in the
        cell, metres: what a drop over the cell lands on first (a table, the clutter on it).
    """

    R_w2g: np.ndarray
    cell: float
    centers: np.ndarray
    score: np.ndarray
    frames: int
    top: np.ndarray


def frame_support_points(depth: np.ndarray, K: np.ndarray, T_c2w: np.ndarray, *, stride: int,
                         margin: float, max_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """World points and unit normals of one depth map on a coarse grid, inside the central window.

    Parameters
    ----------
    depth
        (H, W) float32 metres along camera z, 0 = invalid.
    K
        (3, 3) intrinsics of ``depth``.
    T_c2w
        (4, 4) camera-to-world.
    stride
        Grid step, pixels.
    margin
        Share of width/height left out on each side (objects near the border are cut off).
    max_depth
        Points farther than this are ignored, metres.

    Returns
    -------
    points (P, 3) float64 world metres, normals (P, 3) float64 (facing the camera).
    """
    H, W = depth.shape
    v0, v1 = int(margin * H), int((1 - margin) * H)
    u0, u1 = int(margin * W), int((1 - margin) * W)
    vs = np.arange(v0, v1, stride)
    us = np.arange(u0, u1, stride)
    if len(vs) < 3 or len(us) < 3:
        return np.zeros((0, 3)), np.zeros((0, 3))
    z = depth[np.ix_(vs, us)].astype(np.float64)
    P = unproject_points(K, us[None, :], vs[:, None], z)          # (h, w, 3) camera frame
    valid = (z > 0) & (z < max_depth)
    dx = P[1:-1, 2:] - P[1:-1, :-2]
    dy = P[2:, 1:-1] - P[:-2, 1:-1]
    n = np.cross(dx, dy)
    nn = np.linalg.norm(n, axis=-1, keepdims=True)
    ok = (valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
          & (nn[..., 0] > 0))
    # depth jumps (silhouettes) give steep false normals: neighbours must be at similar depth
    zc = z[1:-1, 1:-1]
    jump = np.maximum.reduce([np.abs(z[1:-1, 2:] - zc), np.abs(z[1:-1, :-2] - zc), np.abs(z[2:, 1:-1] - zc),
                              np.abs(z[:-2, 1:-1] - zc)])
    ok &= jump < 0.05 + 0.05 * zc
    pc = P[1:-1, 1:-1][ok]
    nc = (n / np.maximum(nn, 1e-12))[ok]
    flip = np.einsum("ij,ij->i", nc, pc) > 0                      # face the camera
    nc[flip] *= -1
    R, t = T_c2w[:3, :3], T_c2w[:3, 3]
    return pc @ R.T + t, nc @ R.T


def view_map(scan, frames, R_w2g: np.ndarray, *, cell: float = 0.2, stride: int | None = None,
             margin: float = 0.15, near: float = 1.5, max_depth: float = 4.0, min_up: float = 0.85,
             min_points: int = 3, surface_distance=None, max_off_surface: float = 0.05) -> ViewMap:
    """Vote the kept ``frames`` of ``scan`` for horizontal cells with upward-facing visible surface.

    Frames without depth, or whose depth cannot be read, do not vote (logged).

    Parameters
    ----------
    scan
        :class:`~pipeline.types.Scan`.
    frames
        Kept frame indices.
    R_w2g
        (3, 3) world -> gravity frame (z = up).
    cell
        Cell edge, metres.
    stride
        Pixel grid step; default: about 80 samples across the width.
    margin
        Share of the image border ignored on each side.
    near
        Depth up to which a cell gets the full weight 1, metres (beyond: ``(near / depth)^2``).
    max_depth
        Points farther away do not vote, metres.
    min_up
        Smallest dot product of the surface normal with up for a supporting surface.
    min_points
        Grid points a frame needs in a cell for the cell to count as seen.
    surface_distance
        Optional function of (P, 3) world points giving their distance to the room mesh, metres: points
        farther than ``max_off_surface`` do not vote (the depth sees a surface the mesh lacks, e.g. a
        capture's mesh cropped to a table: nothing to land on there).
    """
    from pipeline.errors import UserError
    from pipeline.scanformats.common import read_depth

    R_w2g = np.asarray(R_w2g, float)
    up = R_w2g[2]
    votes: dict[tuple[int, int], float] = {}
    tops: dict[tuple[int, int], float] = {}
    voted = 0
    for f in frames:
        f = int(f)
        if not scan.depth_paths[f]:
            continue
        try:
            depth = read_depth(scan, f)
        except (UserError, OSError, ValueError) as e:
            log.warning("%s frame %d: depth not readable for the spawn view map (%s)", scan.name, f, e)
            continue
        s = stride or max(1, depth.shape[1] // 80)
        pts, nrm = frame_support_points(depth, scan.K[f], scan.T_c2w[f], stride=s, margin=margin,
                                        max_depth=max_depth)
        keep = nrm @ up > min_up
        if surface_distance is not None and np.any(keep):
            keep[keep] = surface_distance(pts[keep]) <= max_off_surface
        if not np.any(keep):
            voted += 1
            continue
        pts = pts[keep]
        g = pts @ R_w2g.T
        cam = R_w2g @ scan.T_c2w[f][:3, 3]
        dist = np.linalg.norm(g - cam, axis=1)
        ij = np.floor(g[:, :2] / cell).astype(np.int64)
        keys, inv, counts = np.unique(ij, axis=0, return_inverse=True, return_counts=True)
        inv = inv.reshape(-1)
        dmin = np.full(len(keys), np.inf)
        np.minimum.at(dmin, inv, dist)
        zmax = np.full(len(keys), -np.inf)
        np.maximum.at(zmax, inv, g[:, 2])
        w = np.minimum(1.0, (near / np.maximum(dmin, 1e-6)) ** 2)
        for k, c, wk, zk in zip(map(tuple, keys.tolist()), counts, w, zmax):
            if c >= min_points:
                votes[k] = votes.get(k, 0.0) + float(wk)
                tops[k] = max(tops.get(k, -np.inf), float(zk))
        voted += 1
    if not votes:
        return ViewMap(R_w2g, cell, np.zeros((0, 2)), np.zeros(0), voted, np.zeros(0))
    ks = sorted(votes)
    centers = (np.asarray(ks, float) + 0.5) * cell
    return ViewMap(R_w2g, cell, centers, np.asarray([votes[k] for k in ks], float), voted,
                   np.asarray([tops[k] for k in ks], float))


def sample_focus(vm: ViewMap, rng: np.random.Generator, *, power: float = 2.0) -> int | None:
    """The index of a cell sampled with probability ``score ** power`` (None when no cell was seen)."""
    if len(vm.score) == 0 or not np.any(vm.score > 0):
        return None
    p = vm.score ** power
    return int(rng.choice(len(p), p=p / p.sum()))


def focus_bounds(center_xy: np.ndarray, half_width: float, room_lo: np.ndarray, room_hi: np.ndarray,
                 spawn_z: tuple[float, float], lowest: float = -np.inf
                 ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[float, float]]:
    """Spawn bounds (lo, hi) (3,) in the gravity frame and the spawn slab (fractions of their height) for
    a drop over ``center_xy``: a square of ``half_width`` around it horizontally; vertically the slab
    ``spawn_z`` of the room's floor-to-top range, raised (same thickness) where its bottom is below
    ``lowest`` (a height clear of the surfaces seen there).

    A whole room's slab is far above its tables; a capture that is not a room (a table cropped out of a
    scan, one view of a counter) has a height range of a few decimetres, and its slab would lie inside
    the clutter on the table. The bounds' bottom stays the room's floor, so the spawn check finds the
    surface below a spawn point either way.
    """
    c = np.asarray(center_xy, float)
    lo = np.array([c[0] - half_width, c[1] - half_width, room_lo[2]])
    hi = np.array([c[0] + half_width, c[1] + half_width, room_hi[2]])
    ext = hi[2] - lo[2]
    z0, z1 = lo[2] + spawn_z[0] * ext, lo[2] + spawn_z[1] * ext
    if z0 >= lowest:
        return (lo, hi), tuple(spawn_z)
    hi[2] = lowest + (z1 - z0)
    return (lo, hi), ((lowest - lo[2]) / (hi[2] - lo[2]), 1.0)
