"""Ray-triangle intersection behind one small interface.

:class:`EmbreeIntersector` (embreex) is the production backend; :class:`NumPySlowIntersector` is an
exact Moller-Trumbore reference used only by the tests to check it. Both take a triangle soup given as
``vertices (V, 3)`` and ``faces (T, 3)`` and answer batched queries on float32 rays:

- :meth:`Intersector.intersect` -> :class:`Hits` (nearest hit distance, triangle id, barycentrics);
- :meth:`Intersector.occluded` -> bool per ray (any hit in ``(0, tmax)``).

Rays are never offset here: callers move origins off surfaces (see :func:`offset_origins`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol

import numpy as np

log = logging.getLogger(__name__)

MISS = -1  # triangle id of a ray that hit nothing


@dataclass(frozen=True)
class Hits:
    """Nearest hits of a batch of rays."""

    t: np.ndarray      # (R,) float32, distance along the (unit) direction; inf on a miss
    prim: np.ndarray   # (R,) int32, triangle index, MISS (-1) on a miss
    u: np.ndarray      # (R,) float32, barycentric weight of vertex 1 of the triangle
    v: np.ndarray      # (R,) float32, barycentric weight of vertex 2 of the triangle

    @property
    def hit(self) -> np.ndarray:
        """(R,) bool, the ray hit a triangle."""
        return self.prim >= 0


class Intersector(Protocol):
    """What the tracer needs from a ray-casting backend."""

    num_triangles: int

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, tmax: np.ndarray | None = None) -> Hits:
        """Nearest hit of each ray ``origins + t * dirs`` with ``0 < t < tmax`` (``dirs`` unit)."""
        ...

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, tmax: np.ndarray | float) -> np.ndarray:
        """(R,) bool: the ray hits any triangle with ``0 < t < tmax``."""
        ...


def _as_rays(origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    o = np.ascontiguousarray(origins, dtype=np.float32).reshape(-1, 3)
    d = np.ascontiguousarray(dirs, dtype=np.float32).reshape(-1, 3)
    if o.shape != d.shape:
        raise ValueError(f"origins {o.shape} and dirs {d.shape} differ in shape")
    return o, d


def _tmax_array(tmax: np.ndarray | float | None, n: int) -> np.ndarray:
    if tmax is None:
        return np.full(n, np.inf, np.float32)
    t = np.asarray(tmax, dtype=np.float32)
    return np.ascontiguousarray(np.broadcast_to(t, (n,)), dtype=np.float32).copy()


def _empty_hits(n: int) -> Hits:
    return Hits(t=np.full(n, np.inf, np.float32), prim=np.full(n, MISS, np.int32),
                u=np.zeros(n, np.float32), v=np.zeros(n, np.float32))


class EmbreeIntersector:
    """Embree (embreex) ray casting on one triangle mesh; the production backend.

    Parameters
    ----------
    vertices : (V, 3) float array, metres
    faces : (T, 3) int array, indices into ``vertices``

    Notes
    -----
    embreex casts about 4 M rays/s per process; callers batch every query. An empty mesh is allowed
    and answers "miss" to every ray without touching Embree.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        faces = np.ascontiguousarray(faces, dtype=np.int32).reshape(-1, 3)
        self.num_triangles = int(faces.shape[0])
        self._scene = None
        if self.num_triangles:
            from embreex import rtcore_scene
            from embreex.mesh_construction import TriangleMesh

            self._scene = rtcore_scene.EmbreeScene()
            TriangleMesh(scene=self._scene, vertices=np.ascontiguousarray(vertices, dtype=np.float32),
                         indices=faces)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, tmax: np.ndarray | None = None) -> Hits:
        o, d = _as_rays(origins, dirs)
        n = o.shape[0]
        if self._scene is None or n == 0:
            return _empty_hits(n)
        r = self._scene.run(o, d, dists=_tmax_array(tmax, n), output=1)
        prim = r["primID"].astype(np.int32, copy=False)
        miss = prim < 0
        t = r["tfar"].astype(np.float32, copy=True)
        t[miss] = np.inf
        return Hits(t=t, prim=prim, u=r["u"].astype(np.float32, copy=False),
                    v=r["v"].astype(np.float32, copy=False))

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, tmax: np.ndarray | float) -> np.ndarray:
        o, d = _as_rays(origins, dirs)
        n = o.shape[0]
        if self._scene is None or n == 0:
            return np.zeros(n, bool)
        r = self._scene.run(o, d, dists=_tmax_array(tmax, n), query="OCCLUDED")
        return np.asarray(r) >= 0


class NumPySlowIntersector:
    """Exact Moller-Trumbore intersection in float64 NumPy; a test reference, O(rays x triangles).

    Parameters
    ----------
    vertices : (V, 3) float array
    faces : (T, 3) int array
    chunk : int
        Rays processed per block (memory ~ ``chunk * T * 8`` bytes per temporary).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, chunk: int = 256) -> None:
        tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64).reshape(-1, 3)]
        self.num_triangles = int(tri.shape[0])
        self._p0 = tri[:, 0]
        self._e1 = tri[:, 1] - tri[:, 0]
        self._e2 = tri[:, 2] - tri[:, 0]
        self._chunk = chunk

    def _all_hits(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(R, T) distances (inf where no hit) and barycentrics for a block of rays."""
        pvec = np.cross(d[:, None, :], self._e2[None])
        det = np.einsum("tk,rtk->rt", self._e1, pvec)
        ok = np.abs(det) > 1e-300
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tvec = o[:, None, :] - self._p0[None]
        u = np.einsum("rtk,rtk->rt", tvec, pvec) * inv
        qvec = np.cross(tvec, self._e1[None])
        v = np.einsum("rk,rtk->rt", d, qvec) * inv
        t = np.einsum("tk,rtk->rt", self._e2, qvec) * inv
        valid = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        return np.where(valid, t, np.inf), u, v

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, tmax: np.ndarray | None = None) -> Hits:
        o = np.asarray(origins, np.float64).reshape(-1, 3)
        d = np.asarray(dirs, np.float64).reshape(-1, 3)
        n = o.shape[0]
        out = _empty_hits(n)
        tm = _tmax_array(tmax, n).astype(np.float64)
        if self.num_triangles == 0:
            return out
        for s in range(0, n, self._chunk):
            t, u, v = self._all_hits(o[s:s + self._chunk], d[s:s + self._chunk])
            t = np.where(t < tm[s:s + self._chunk, None], t, np.inf)
            k = np.argmin(t, axis=1)
            rows = np.arange(k.shape[0])
            best = t[rows, k]
            hit = np.isfinite(best)
            sl = slice(s, s + k.shape[0])
            out.t[sl] = np.where(hit, best, np.inf)
            out.prim[sl] = np.where(hit, k, MISS)
            out.u[sl] = np.where(hit, u[rows, k], 0.0)
            out.v[sl] = np.where(hit, v[rows, k], 0.0)
        return out

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, tmax: np.ndarray | float) -> np.ndarray:
        return self.intersect(origins, dirs, _tmax_array(tmax, np.asarray(origins).reshape(-1, 3).shape[0])).hit


def offset_origins(points: np.ndarray, normals: np.ndarray, dirs: np.ndarray, eps: float) -> np.ndarray:
    """Move ray origins off a surface along its geometric normal, to the side the ray leaves by.

    Parameters
    ----------
    points : (R, 3) float32, surface points, metres
    normals : (R, 3) float32, unit geometric normals
    dirs : (R, 3) float32, unit ray directions leaving the surface
    eps : float, offset, metres

    Returns
    -------
    (R, 3) float32 origins
    """
    side = np.sign(np.einsum("ij,ij->i", normals, dirs)).astype(np.float32)
    side[side == 0] = 1.0
    return (points + (eps * side)[:, None] * normals).astype(np.float32)
