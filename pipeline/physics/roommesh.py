"""The room's surface for exact contact distances: :class:`RoomMesh` (Open3D's BVH, built once per room).

Its own module so that :mod:`pipeline.physics.io` (which builds a model around one) and
:mod:`pipeline.physics.collide` (which queries it) both import it without importing each other.
"""

from __future__ import annotations

import numpy as np


class RoomMesh:
    """Exact closest-point queries on the room surface mesh (Open3D's BVH; built once per room).

    The trilinear unsigned distance grid is only a broad phase: across a cell that the surface passes
    through its value is too large by up to a quarter of the spacing and its gradient can point the
    wrong way, so contacts taken from it let points sink mm into the surface shell. Contact candidates
    (grid distance within reach) are therefore re-measured against the mesh.

    Parameters
    ----------
    vertices
        (V, 3) float world vertices, m.
    faces
        (T, 3) int triangle indices.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        from meshprep.metrics import open3d_module

        o3d = open3d_module()
        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, np.float32)),
                                  o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))

    def closest(self, points: np.ndarray, centres: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """Distance to the surface and the contact normal of ``points``.

        Parameters
        ----------
        points
            (N, 3) float64 world points, m.
        centres
            (N, 3) float64 world centres of the bodies owning the points, or None. A scan surface has
            no inside, so a point has crossed a sheet when the sheet cuts the segment from its body's
            centre to it (the segment lies inside the convex body): then its distance is minus its
            depth behind the sheet that was cut, and its normal that sheet's face normal towards the
            centre. Without centres, distances are unsigned.

        Returns
        -------
        dist : (N,) float64, m (< 0: crossed the surface)
        normal : (N, 3) float64 unit direction in which the point leaves the surface
        """
        if len(points) == 0:
            return np.zeros(0), np.zeros((0, 3))
        o3d = self._o3d
        r = self._scene.compute_closest_points(o3d.core.Tensor(np.ascontiguousarray(points, np.float32)))
        cp = r["points"].numpy().astype(float)
        v = points - cp
        d = np.linalg.norm(v, axis=1)
        fn = r["primitive_normals"].numpy().astype(float)
        fn *= np.where(np.sum(fn * v, axis=1) < 0, -1.0, 1.0)[:, None]     # towards the point
        n = np.where((d > 1e-6)[:, None], v / np.maximum(d, 1e-300)[:, None], fn)
        if centres is None:
            return d, n
        seg = points - centres
        hit = self._scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(
            np.concatenate([centres, seg], axis=1), np.float32)))
        t = hit["t_hit"].numpy().astype(float)
        crossed = t < 1.0
        if np.any(crossed):
            hn = hit["primitive_normals"].numpy().astype(float)[crossed]
            sg = seg[crossed]
            hn *= np.where(np.sum(hn * sg, axis=1) > 0, -1.0, 1.0)[:, None]   # towards the centre
            depth = np.abs(np.sum((1.0 - t[crossed])[:, None] * sg * hn, axis=1))
            d = d.copy()
            d[crossed] = -depth
            n[crossed] = hn
        return d, n


    def cast(self, origins: np.ndarray, segments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First crossing of the surface along segments.

        Parameters
        ----------
        origins, segments
            (N, 3) float64 world start points and segment vectors, m.

        Returns
        -------
        t : (N,) float64 fraction of the segment at the first hit (``inf``: none within the segment)
        normal : (N, 3) float64 unit face normal at the hit (either orientation)
        """
        if len(origins) == 0:
            return np.zeros(0), np.zeros((0, 3))
        o3d = self._o3d
        hit = self._scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(
            np.concatenate([origins, segments], axis=1), np.float32)))
        t = hit["t_hit"].numpy().astype(float)
        t[~(t <= 1.0)] = np.inf
        return t, hit["primitive_normals"].numpy().astype(float)
