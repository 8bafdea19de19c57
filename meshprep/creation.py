"""Closed, outward-oriented analytic meshes (box, sphere, cylinder, torus) as arrays.

Used by the tests (mass properties against formulas) and handy for users. All return
``(vertices (V,3) float64, faces (F,3) int32)`` centred at the origin.
"""

from __future__ import annotations

import numpy as np


def box(extents: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box with the given edge lengths (12 triangles)."""
    e = 0.5 * np.asarray(extents, dtype=np.float64)
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * e
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.int32)
    return v, f


def _grid_faces(rows: int, cols: int, wrap_cols: bool) -> np.ndarray:
    """Quads of a rows x cols vertex grid split into triangles (columns wrap when asked)."""
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols if wrap_cols else cols - 1), indexing="ij")
    c1 = (c + 1) % cols
    a, b, d, e = r * cols + c, r * cols + c1, (r + 1) * cols + c, (r + 1) * cols + c1
    return np.concatenate([np.stack([a, d, b], -1).reshape(-1, 3),
                           np.stack([b, d, e], -1).reshape(-1, 3)]).astype(np.int32)


def sphere(radius: float = 1.0, *, stacks: int = 128, slices: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """UV sphere with poles on the z axis (inscribed polyhedron: its volume is slightly smaller)."""
    th = np.linspace(0, np.pi, stacks + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, slices, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    v = np.vstack([ring, [[0, 0, 1]], [[0, 0, -1]]]) * radius
    f = _grid_faces(stacks - 1, slices, True)
    n = len(ring)
    top, bot = n, n + 1
    j = np.arange(slices)
    cap_t = np.stack([np.full(slices, top), j, (j + 1) % slices], -1)
    last = (stacks - 2) * slices
    cap_b = np.stack([np.full(slices, bot), last + (j + 1) % slices, last + j], -1)
    return v, np.vstack([f, cap_t, cap_b]).astype(np.int32)


def cylinder(radius: float = 1.0, height: float = 1.0, *, slices: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Capped cylinder along z, from -height/2 to height/2."""
    ph = np.linspace(0, 2 * np.pi, slices, endpoint=False)
    ring = np.stack([radius * np.cos(ph), radius * np.sin(ph)], -1)
    v = np.vstack([np.hstack([ring, np.full((slices, 1), height / 2)]),
                   np.hstack([ring, np.full((slices, 1), -height / 2)]),
                   [[0, 0, height / 2], [0, 0, -height / 2]]])
    side = _grid_faces(2, slices, True)
    j = np.arange(slices)
    ct, cb = 2 * slices, 2 * slices + 1
    top = np.stack([np.full(slices, ct), j, (j + 1) % slices], -1)
    bot = np.stack([np.full(slices, cb), slices + (j + 1) % slices, slices + j], -1)
    return v, np.vstack([side, top, bot]).astype(np.int32)


def torus(major: float = 1.0, minor: float = 0.25, *, major_segments: int = 256,
          minor_segments: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """Torus around the z axis."""
    u = np.linspace(0, 2 * np.pi, major_segments, endpoint=False)
    w = np.linspace(0, 2 * np.pi, minor_segments, endpoint=False)
    U, W = np.meshgrid(u, w, indexing="ij")
    rr = major + minor * np.cos(W)
    v = np.stack([rr * np.cos(U), rr * np.sin(U), minor * np.sin(W)], -1).reshape(-1, 3)
    # Grid rows = major index, columns = minor index; both wrap.
    f = _grid_faces(major_segments + 1, minor_segments, True)
    f = f % (major_segments * minor_segments)
    return v, f.astype(np.int32)
