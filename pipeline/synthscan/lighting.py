"""Direct light from rectangular Lambertian emitters, evaluated at surface points.

The irradiance from a uniformly emitting polygon is exact (Lambert's polygon formula); shadows are
optional and estimated by casting rays to points spread over each emitter. The raster photo mode bakes
this irradiance into the vertices of a finely tessellated room ("light map on vertices"); the scanner
mesh's colours are baked with the same function, so photos and scan mesh see the same lighting.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from pipeline.synthscan.room import Light

log = logging.getLogger(__name__)


def polygon_irradiance_vector(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Lambert's irradiance vector of a unit-radiance polygon at ``points``.

    ``E = n . Phi`` for a surface with unit normal ``n`` that sees the whole polygon; the vector is
    oriented towards the polygon.

    Parameters
    ----------
    points : (N, 3) float, metres
    corners : (C, 3) float, polygon corners in order (either winding)

    Returns
    -------
    (N, 3) float64, irradiance vector for radiance 1 (W/m^2 per W/(m^2 sr))
    """
    v = corners[None, :, :] - points[:, None, :]                 # (N, C, 3)
    v /= np.maximum(np.linalg.norm(v, axis=2, keepdims=True), 1e-12)
    w = np.roll(v, -1, axis=1)
    cos = np.clip(np.einsum("ncd,ncd->nc", v, w), -1.0, 1.0)
    theta = np.arccos(cos)                                       # (N, C)
    g = np.cross(v, w)
    g /= np.maximum(np.linalg.norm(g, axis=2, keepdims=True), 1e-12)
    phi = 0.5 * np.einsum("nc,ncd->nd", theta, g)
    centre = corners.mean(axis=0)
    flip = np.einsum("nd,nd->n", phi, centre[None, :] - points) < 0
    phi[flip] *= -1.0
    return phi


def direct_irradiance(points: np.ndarray, normals: np.ndarray, lights: tuple[Light, ...],
                      visibility=None) -> np.ndarray:
    """Irradiance from every light at surface points, RGB.

    Parameters
    ----------
    points : (N, 3) float, metres
    normals : (N, 3) float, unit surface normals
    lights : the room's emitters
    visibility : callable ``(points, normals, light) -> (N,) float in [0, 1]`` or None (no shadows)

    Returns
    -------
    (N, 3) float64, irradiance in the lights' relative units (W/m^2)
    """
    E = np.zeros((len(points), 3))
    for light in lights:
        phi = polygon_irradiance_vector(points, light.corners)
        e = np.maximum(np.einsum("nd,nd->n", phi, normals), 0.0)
        front = (points - light.corners.mean(0)) @ light.normal > 1e-6  # one-sided emitter
        e = np.where(front, e, 0.0)
        if visibility is not None:
            lit = e > 0
            if lit.any():
                vis = np.zeros(len(points))
                vis[lit] = visibility(points[lit], normals[lit], light)
                e = e * vis
        E += e[:, None] * light.radiance[None, :]
    return E


class EmbreeShadows:
    """Fraction of an emitter visible from surface points, by rays to a fixed grid of emitter points.

    Parameters
    ----------
    vertices : (V, 3) float, occluder mesh vertices, metres
    faces : (T, 3) int, occluder triangles (emitter quads may be included: rays stop short of them)
    samples : int, emitter points per side (samples**2 rays per surface point)
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, samples: int = 3) -> None:
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        self._scene = rtcs.EmbreeScene()
        TriangleMesh(self._scene, np.ascontiguousarray(vertices[faces], dtype=np.float32))
        self._s = samples

    def __call__(self, points: np.ndarray, normals: np.ndarray, light: Light) -> np.ndarray:
        s = self._s
        u = (np.arange(s) + 0.5) / s
        c = light.corners
        e1, e2 = c[1] - c[0], c[3] - c[0]
        targets = (c[0] + u[:, None, None] * e1 + u[None, :, None] * e2).reshape(-1, 3)  # (S, 3)
        origins = points + 1e-3 * normals
        d = targets[None, :, :] - origins[:, None, :]                                    # (N, S, 3)
        dist = np.linalg.norm(d, axis=2)
        d = d / np.maximum(dist[..., None], 1e-12)
        # Start a little along the ray too: a vertex on an edge where two surfaces meet (floor and wall)
        # must not be shadowed by the surface it touches.
        o = (origins[:, None, :] + 4e-3 * d).reshape(-1, 3).astype(np.float32)
        dist = dist - 4e-3
        dd = d.reshape(-1, 3).astype(np.float32)
        tfar = (dist.reshape(-1) - 5e-3).astype(np.float32)
        hit = self._scene.run(o, dd, dists=tfar, query="OCCLUDED")
        occluded = np.asarray(hit).reshape(len(points), len(targets)) != -1
        return 1.0 - occluded.mean(axis=1)

    def ambient_occlusion(self, points: np.ndarray, normals: np.ndarray, *, rays: int = 16,
                          max_distance: float = 0.6) -> np.ndarray:
        """Unoccluded fraction of the cosine-weighted hemisphere within ``max_distance`` (1 = open).

        Directions are a fixed Fibonacci set (no random numbers), turned into each point's normal frame.

        Parameters
        ----------
        points : (N, 3) float, metres
        normals : (N, 3) float, unit
        rays : int, directions per point
        max_distance : float, metres; farther occluders do not count

        Returns
        -------
        (N,) float64 in [0, 1]
        """
        k = np.arange(rays) + 0.5
        r = np.sqrt(k / rays)                       # cosine-weighted: uniform on the disk, lifted
        phi = k * math.pi * (3.0 - math.sqrt(5.0))
        local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1.0 - r * r)], 1)   # (S, 3)
        n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        helper = np.where(np.abs(n[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
        t1 = np.cross(helper, n)
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(n, t1)
        d = (local[None, :, 0:1] * t1[:, None, :] + local[None, :, 1:2] * t2[:, None, :]
             + local[None, :, 2:3] * n[:, None, :])                                       # (N, S, 3)
        o = (points + 1e-3 * n)[:, None, :] + 4e-3 * d
        hit = self._scene.run(o.reshape(-1, 3).astype(np.float32), d.reshape(-1, 3).astype(np.float32),
                              dists=np.full(o.shape[0] * rays, max_distance, np.float32), query="OCCLUDED")
        return 1.0 - (np.asarray(hit).reshape(len(points), rays) != -1).mean(axis=1)
