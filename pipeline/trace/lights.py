"""Lighting from the scan itself: the room mesh as an emitter, bright regions as lights, fallbacks.

The room mesh's vertex colours are what the camera saw, in sRGB. Converted to linear values they are
used as outgoing radiance (image-based lighting from the scan: a white object beside a white wall comes
out about as bright as the wall). Colours clipped at the sensor's maximum (lamps, windows) hide more
light than they show; triangles whose three vertices are all clipped are detected, their radiance is
multiplied by a gain, and they are sampled explicitly (next-event estimation, combined with BSDF
sampling by multiple importance sampling). Rays leaving through holes in the scan see a constant
environment radiance (by default the mean radiance of the room).

The "published" mode replaces all this by four point lights in a rectangle under the top of the room's
bounding box, with the room a diffuse reflector of its own colour, as the method was first described.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from pipeline.color import LUMINANCE
from pipeline.geometry import up_frame

log = logging.getLogger(__name__)

ENV_W, ENV_H = 32, 16   # equirectangular environment map size (azimuth x polar angle bins)


def env_bin(dirs: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Equirectangular bin (row, col) of unit world directions ``dirs (N, 3)`` about the ``up`` axis."""
    e1, e2, up = up_frame(up)
    d = np.asarray(dirs, np.float64)
    cz = np.clip(d @ up, -1.0, 1.0)
    phi = np.arctan2(d @ e2, d @ e1)
    row = np.clip(((1.0 - cz) * 0.5 * ENV_H).astype(np.int64), 0, ENV_H - 1)   # uniform in cos: equal solid angle
    col = np.clip(((phi + np.pi) / (2 * np.pi) * ENV_W).astype(np.int64), 0, ENV_W - 1)
    return row, col


def env_lookup(env: np.ndarray, up: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Radiance (N, 3) float32 of the environment map ``env (ENV_H, ENV_W, 3)`` in directions ``dirs (N, 3)``."""
    r, c = env_bin(dirs, up)
    return np.asarray(env, np.float32)[r, c]


def detect_bright_triangles(colors_u8: np.ndarray, faces: np.ndarray, *, threshold: int = 250) -> np.ndarray:
    """Triangles whose three vertices are clipped: every channel >= ``threshold`` (0..255).

    Parameters
    ----------
    colors_u8 : (V, 3) uint8 sRGB vertex colours
    faces : (T, 3) int

    Returns
    -------
    (T,) bool
    """
    bright_v = np.asarray(colors_u8).min(axis=1) >= threshold
    return bright_v[np.asarray(faces)].all(axis=1)


@dataclass(frozen=True)
class AreaLights:
    """Emitting triangles sampled explicitly (next-event estimation); indices into the scene's faces."""

    tri: np.ndarray       # (L,) int64, scene triangle index of each light triangle
    cdf: np.ndarray       # (L,) float64, cumulative selection probability (last = 1)
    prob: np.ndarray      # (L,) float64, selection probability (proportional to area x luminance)
    area: np.ndarray      # (L,) float64, m^2
    prob_of_tri: np.ndarray  # (T,) float64, selection probability / area per scene triangle (0 = not a light)

    @property
    def count(self) -> int:
        return int(self.tri.shape[0])


def build_area_lights(vertices: np.ndarray, faces: np.ndarray, emission: np.ndarray,
                      light_mask: np.ndarray) -> AreaLights:
    """Area lights from the scene triangles in ``light_mask``, selected by power (area x luminance).

    Parameters
    ----------
    vertices : (V, 3) float, metres
    faces : (T, 3) int
    emission : (V, 3) float32 linear radiance per vertex
    light_mask : (T,) bool
    """
    tri = np.flatnonzero(light_mask)
    p = np.asarray(vertices, np.float64)[np.asarray(faces)[tri]]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    lum = (np.asarray(emission)[np.asarray(faces)[tri]].mean(axis=1) @ LUMINANCE).astype(np.float64)
    w = area * lum
    keep = w > 0
    tri, area, w = tri[keep], area[keep], w[keep]
    prob_of_tri = np.zeros(len(faces), np.float64)
    if tri.size == 0:
        return AreaLights(tri=tri, cdf=np.zeros(0), prob=np.zeros(0), area=area, prob_of_tri=prob_of_tri)
    prob = w / w.sum()
    prob_of_tri[tri] = prob / area
    return AreaLights(tri=tri, cdf=np.cumsum(prob), prob=prob, area=area, prob_of_tri=prob_of_tri)


def sample_area_lights(lights: AreaLights, vertices: np.ndarray, faces: np.ndarray, u0: np.ndarray,
                       u1: np.ndarray, u2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points on the area lights, chosen by power then uniformly by area.

    Returns
    -------
    tri : (R,) int64 scene triangle index
    b1, b2 : (R,) barycentric weights of vertices 1 and 2
    pdf_area : (R,) float64 pdf per unit area (1/m^2)
    """
    k = np.minimum(np.searchsorted(lights.cdf, u0, side="right"), lights.count - 1)
    su = np.sqrt(u1)
    b1 = su * (1.0 - u2)
    b2 = su * u2
    tri = lights.tri[k]
    return tri, b1, b2, lights.prob_of_tri[tri]


@dataclass(frozen=True)
class PointLights:
    """Isotropic point lights (published lighting mode)."""

    position: np.ndarray   # (L, 3) float64, metres, world
    intensity: np.ndarray  # (L, 3) float64, linear radiant intensity (radiance x m^2 units)

    @property
    def count(self) -> int:
        return int(self.position.shape[0])


def published_lights(room_vertices: np.ndarray, up: np.ndarray, *, power: float = 1.0) -> PointLights:
    """Four point lights in a rectangle under the top of the room's bounding box (published lighting).

    The rectangle is the room's horizontal extent shrunk to half about its centre, placed at 90 % of the
    room's height. Each light's intensity is set so the four together give an irradiance of ``power * pi``
    at the floor's centre (a white Lambertian floor there would have radiance ``power``).

    Parameters
    ----------
    room_vertices : (V, 3) float, metres, world
    up : (3,) unit up vector, world
    """
    e1, e2, up = up_frame(up)
    v = np.asarray(room_vertices, np.float64)
    c = np.stack([v @ e1, v @ e2, v @ up], axis=1)
    lo, hi = c.min(axis=0), c.max(axis=0)
    mid = 0.5 * (lo + hi)
    half = 0.25 * (hi - lo)
    h = lo[2] + 0.9 * (hi[2] - lo[2])
    corners = np.array([[mid[0] + sx * half[0], mid[1] + sy * half[1], h]
                        for sx in (-1, 1) for sy in (-1, 1)])
    pos = corners[:, :1] * e1 + corners[:, 1:2] * e2 + corners[:, 2:3] * up
    floor = mid[0] * e1 + mid[1] * e2 + lo[2] * up
    d = pos - floor
    dist = np.linalg.norm(d, axis=1)
    cos = (d @ up) / dist
    irr_per_unit = float(np.sum(cos / dist ** 2))
    inten = power * np.pi / max(irr_per_unit, 1e-12)
    return PointLights(position=pos, intensity=np.full((4, 3), inten))


def mean_radiance(vertices: np.ndarray, faces: np.ndarray, emission: np.ndarray) -> np.ndarray:
    """Area-weighted mean of per-vertex radiance over a mesh: (3,) float32 (zeros for an empty mesh)."""
    f = np.asarray(faces)
    if f.size == 0:
        return np.zeros(3, np.float32)
    p = np.asarray(vertices, np.float64)[f]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    e = np.asarray(emission, np.float64)[f].mean(axis=1)
    return (area @ e / max(area.sum(), 1e-12)).astype(np.float32)
