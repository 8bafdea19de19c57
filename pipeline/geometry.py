"""Small pose and frame helpers shared by the scan generator, the tracer and the tests."""

from __future__ import annotations

import math

import numpy as np


def nearest_rotation(R: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The rotation nearest to ``R (3, 3)`` in the Frobenius norm (SVD, ``U V^T``), with how far ``R`` was
    from one: ``(rotation, max |R^T R - I|, det R)``. A reflection (det < 0) stays one: check ``det``."""
    R = np.asarray(R, np.float64)
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt, float(np.abs(R.T @ R - np.eye(3)).max()), float(np.linalg.det(R))


def look_at(eye, target, up=(0.0, 0.0, 1.0), roll: float = 0.0) -> np.ndarray:
    """(4, 4) float64 camera-to-world pose at ``eye`` looking at ``target``, OpenCV camera axes.

    z points at ``target``, y down and x right with ``up`` up in the image, then the camera is rolled by
    ``roll`` radians about z. Units are those of ``eye`` and ``target`` (metres in the pipeline).
    """
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    if roll:
        c, s = math.cos(roll), math.sin(roll)
        x, y = c * x + s * y, -s * x + c * y
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def up_frame(up) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Right-handed orthonormal frame ``(e1, e2, up)`` (each (3,) float64) with ``up`` normalised.

    ``e1`` is horizontal (perpendicular to ``up``), built from the world x axis, or y when ``up`` is
    close to x; ``e2 = up x e1``. Used for horizontal extents and azimuths about the room's up axis.
    """
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1), up


def hull_mesh(vertices: np.ndarray, *, min_vertices: int = 64) -> tuple[np.ndarray, np.ndarray | None]:
    """Convex hull of a point set: ``(points (H, 3) float64, triangles (T, 3) int64 into points or None)``.

    All the points and no triangles when there are ``min_vertices`` or fewer, or when the set is flat or
    degenerate."""
    v = np.asarray(vertices, dtype=np.float64)
    if len(v) <= min_vertices:
        return v, None
    from scipy.spatial import ConvexHull, QhullError

    try:
        h = ConvexHull(v)
    except (QhullError, ValueError):
        return v, None
    index = np.full(len(v), -1, np.int64)
    index[h.vertices] = np.arange(len(h.vertices))
    return v[h.vertices], index[h.simplices]


def hull_points(vertices: np.ndarray, *, min_vertices: int = 64) -> np.ndarray:
    """(H, 3) float64 convex-hull vertices of a point set (all of them when ``min_vertices`` or fewer, or
    when the set is flat or degenerate): projecting these bounds the set's silhouette as tightly as
    projecting every point, at a fraction of the cost."""
    return hull_mesh(vertices, min_vertices=min_vertices)[0]
