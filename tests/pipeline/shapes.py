"""Tiny analytic meshes for the tests' reference scenes, and the closed forms they are checked against (NumPy
only; a test helper, not part of the product).

Triangles are counter-clockwise seen from the side their normal points to.
"""

from __future__ import annotations

import numpy as np

from pipeline.geometry import look_at  # noqa: F401  (re-exported: the tests build cameras with it)


def uv_sphere(radius: float = 1.0, center=(0.0, 0.0, 0.0), *, n_lat: int = 48, n_lon: int = 96,
              inward: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed UV sphere.

    Returns
    -------
    vertices : (V, 3) float64
    faces : (T, 3) int32, outward (or inward when ``inward``) facing
    normals : (V, 3) float32 unit vertex normals, same orientation as the faces
    """
    th = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1).reshape(-1, 3)
    n = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]])
    top, bot = 0, n.shape[0] - 1
    faces = []
    idx = lambda i, j: 1 + i * n_lon + (j % n_lon)  # noqa: E731
    for j in range(n_lon):
        faces.append([top, idx(0, j), idx(0, j + 1)])
        faces.append([bot, idx(n_lat - 2, j + 1), idx(n_lat - 2, j)])
    for i in range(n_lat - 2):
        for j in range(n_lon):
            a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1)
            faces += [[a, c, b], [b, c, d]]
    f = np.asarray(faces, np.int32)
    if inward:
        f = f[:, ::-1].copy()
        n = -n
    return n * radius + np.asarray(center, np.float64), f, n.astype(np.float32)


def quad(center, u, v) -> tuple[np.ndarray, np.ndarray]:
    """A parallelogram ``center +- u +- v``, normal ``u x v``: (4, 3) float64 vertices, (2, 3) int32 faces."""
    c, u, v = (np.asarray(x, np.float64) for x in (center, u, v))
    verts = np.stack([c - u - v, c + u - v, c + u + v, c - u + v])
    return verts, np.array([[0, 1, 2], [0, 2, 3]], np.int32)


def grid_quad(center, u, v, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A parallelogram like :func:`quad` split into ``n x n`` cells (``2 n^2`` triangles)."""
    c, u, v = (np.asarray(x, np.float64) for x in (center, u, v))
    s = np.linspace(-1.0, 1.0, n + 1)
    A, B = np.meshgrid(s, s, indexing="ij")
    verts = (c + A[..., None] * u + B[..., None] * v).reshape(-1, 3)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    a, b, cc, d = i, i + (n + 1), i + (n + 1) + 1, i + 1
    faces = np.concatenate([np.stack([a, b, cc], -1).reshape(-1, 3), np.stack([a, cc, d], -1).reshape(-1, 3)])
    return verts, faces.astype(np.int32)


def box_room(lo, hi, *, n: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """A closed box whose faces look inward (a room seen from inside), each side ``n x n`` cells."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    c = 0.5 * (lo + hi)
    h = 0.5 * (hi - lo)
    ex, ey, ez = np.eye(3)
    sides = [  # (centre, u, v) with u x v pointing inward
        (c - h[2] * ez, h[0] * ex, h[1] * ey), (c + h[2] * ez, h[1] * ey, h[0] * ex),
        (c - h[1] * ey, h[2] * ez, h[0] * ex), (c + h[1] * ey, h[0] * ex, h[2] * ez),
        (c - h[0] * ex, h[1] * ey, h[2] * ez), (c + h[0] * ex, h[2] * ez, h[1] * ey),
    ]
    vs, fs, off = [], [], 0
    for cen, u, v in sides:
        vv, ff = grid_quad(cen, u, v, n)
        vs.append(vv)
        fs.append(ff + off)
        off += len(vv)
    return np.concatenate(vs), np.concatenate(fs).astype(np.int32)


def parallel_rectangle_factor(a: float, b: float, h: float) -> float:
    """Form factor from a small upward-facing patch to a parallel a x b rectangle h above, the patch under one
    of its corners (Howell's catalogue of configuration factors, B-3)."""
    X, Y = a / h, b / h
    sx, sy = np.sqrt(1 + X * X), np.sqrt(1 + Y * Y)
    return float((X / sx * np.arctan(Y / sx) + Y / sy * np.arctan(X / sy)) / (2 * np.pi))
