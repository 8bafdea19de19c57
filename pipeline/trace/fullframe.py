"""Full-frame path tracing: every pixel, every surface (the room included), emitters seen directly.

:func:`pbr.render` traces object pixels only and treats the room as a light source of its captured
colours. This module renders a whole frame of a scene whose lights are real emitting triangles (a
synthetic room with ceiling panels and a window): unidirectional path tracing with next-event
estimation on the area lights and MIS against BSDF sampling (power heuristic), Russian roulette, and
ONE-SIDED emitters (a triangle emits only to the side its winding normal points to, like the
synthetic scan's Lambertian panels). It reuses the tracer's building blocks unchanged: the Embree
intersector and :class:`~pipeline.trace.scene.TraceScene`, :func:`pbr.interact` (hit points, textures),
the metallic-roughness BSDF (:mod:`pipeline.trace.bsdf`), area-light sampling
(:func:`~pipeline.trace.lights.sample_area_lights`) and ray offsets.

Random numbers come only from the generator passed in and are drawn in a fixed order per chunk of
samples: the same scene, camera, settings and generator state give the same bytes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from pipeline.camera import Camera
from pipeline.tolerances import TRACE_RAY_EPS_M
from pipeline.trace import bsdf
from pipeline.trace.intersect import Hits, offset_origins
from pipeline.trace.pbr import (Surface, add_rows, area_light_nee, emission_at, emission_mis_weight, interact,
                                material, sample_continuation)
from pipeline.trace.sampling import frame_to_local, local_frame
from pipeline.trace.scene import TraceScene

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FullFrameSettings:
    """Quality knobs of :func:`render_full_frame`."""

    spp: int = 16                 # samples per pixel (fixed, no adaptive stop: equal noise everywhere)
    max_depth: int = 5            # scattering events per path (direct light counts as the first)
    rr_depth: int = 3             # Russian roulette from this scattering event on
    chunk_samples: int = 1 << 18  # camera samples traced together (bounds memory: ~1 kB per sample)
    ray_eps: float = TRACE_RAY_EPS_M  # metres, origin offset off surfaces


@dataclass(frozen=True)
class FullFrame:
    """What :func:`render_full_frame` returns."""

    radiance: np.ndarray   # (H, W, 3) float32 linear radiance, mean over the pixel's samples
    coverage: np.ndarray   # (H, W) float32 share of samples whose first hit has tri_inst >= cover_from
    albedo: np.ndarray     # (H, W, 3) float32 mean first-hit base colour (denoiser guide)
    normal: np.ndarray     # (H, W, 3) float32 mean first-hit shading normal, world frame (denoiser guide)
    rays: int              # rays cast in total


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _front_emission(scene: TraceScene, prim: np.ndarray, u: np.ndarray, v: np.ndarray,
                    dirs: np.ndarray) -> np.ndarray:
    """(R, 3) emitted radiance towards rays ``dirs`` that hit ``prim``; 0 from an emitter's back side."""
    Le = emission_at(scene, prim, u, v)
    front = _dot(scene.tri_normal[prim], dirs) < 0
    return np.where(front[:, None], Le, np.float32(0)).astype(np.float32)


def _direct_and_sample(scene: TraceScene, s: Surface, wo: np.ndarray, beta: np.ndarray,
                       u: np.ndarray, eps: float, rays: list[int]
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """NEE to one point on the (one-sided) area lights, MIS-weighted, and a BSDF-sampled direction.

    ``u (6, R)`` float32 uniforms: three for the light point, three for the BSDF.
    Returns ``(L_direct x beta (R, 3), wi (R, 3), f cos / pdf (R, 3), pdf (R,))``.
    """
    n = s.p.shape[0]
    frame = local_frame(s.ns)
    wo_l = frame_to_local(wo, frame)
    lobes = bsdf.prepare(material(scene, s), wo_l[:, 2])
    L = np.zeros((n, 3), np.float32)
    if scene.area_lights.count and n:
        L, k = area_light_nee(scene, s, lobes, wo_l, frame, beta, u[0].astype(np.float64), u[1].astype(np.float64),
                              u[2].astype(np.float64), eps, one_sided=True)
        rays[0] += k
    wi, weight, pdf = sample_continuation(lobes, wo_l, frame, s.ng, u[3], u[4], u[5])
    return L, wi, weight, pdf


def _trace_chunk(scene: TraceScene, camera: Camera, pixels: np.ndarray, settings: FullFrameSettings,
                 rng: np.random.Generator, cover_from: int | None, rays: list[int]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One camera sample per pixel entry: radiance (R, 3) float64, first-hit coverage flags (R,), first-hit
    albedo (R, 3) and shading normal (R, 3, world; zero on a miss or an emitter).

    Every sample draws the same uniforms in the same order whatever happens to the other samples
    (all bounces draw for the whole chunk and index by sample): a path that meets none of the scene's
    changes keeps its exact value when objects are inserted (correlated sampling).
    """
    n = pixels.shape[0]
    eps = settings.ray_eps
    L = np.zeros((n, 3))
    o, d = camera.rays(pixels, rng.random((n, 2), dtype=np.float32))
    h = scene.intersector.intersect(o, d)
    rays[0] += n
    hit = h.hit
    alb0 = np.zeros((n, 3), np.float32)
    nrm0 = np.zeros((n, 3), np.float32)
    covered = np.zeros(n, bool)
    if cover_from is not None:
        covered[hit] = scene.tri_inst[h.prim[hit]] >= cover_from
    miss = np.flatnonzero(~hit)
    if miss.size:
        add_rows(L, miss, np.broadcast_to(scene.env_radiance, (miss.size, 3)))
    idx = np.flatnonzero(hit)
    if idx.size == 0:
        return L, covered, alb0, nrm0
    em = idx[scene.tri_emits[h.prim[idx]]]
    if em.size:
        add_rows(L, em, _front_emission(scene, h.prim[em], h.u[em], h.v[em], d[em]))
    idx = idx[scene.tri_scatters[h.prim[idx]]]
    s = interact(scene, Hits(t=h.t[idx], prim=h.prim[idx], u=h.u[idx], v=h.v[idx]), d[idx])
    alb0[idx] = s.albedo
    nrm0[idx] = s.ns
    wo = -d[idx]
    beta = np.ones((idx.size, 3), np.float32)
    for depth in range(settings.max_depth):
        U = rng.random((7, n), dtype=np.float32)
        if idx.size == 0:
            continue  # keep drawing: the stream position must not depend on the scene
        Ld, wi, weight, pdf = _direct_and_sample(scene, s, wo, beta, U[:6, idx], eps, rays)
        add_rows(L, idx, Ld)
        if depth + 1 >= settings.max_depth:
            continue
        beta = beta * weight
        alive = beta.max(axis=1) > 0
        if depth + 1 >= settings.rr_depth:
            q = np.clip(beta.max(axis=1), np.float32(0.05), np.float32(1.0))
            alive &= U[6, idx] < q
            beta = beta / q[:, None]
        k = np.flatnonzero(alive)
        idx, beta, pdf, wi = idx[k], beta[k], pdf[k], wi[k]
        org = offset_origins(s.p[k], s.ng[k], wi, eps)
        h = scene.intersector.intersect(org, wi)
        rays[0] += k.size
        m = np.flatnonzero(~h.hit)
        if m.size:
            add_rows(L, idx[m], beta[m] * scene.env_radiance)
        hk = np.flatnonzero(h.hit)
        prim = h.prim[hk]
        em = hk[scene.tri_emits[prim]]
        if em.size:
            pe = h.prim[em]
            Le = _front_emission(scene, pe, h.u[em], h.v[em], wi[em])
            w = emission_mis_weight(scene, pe, h.t[em], wi[em], pdf[em])
            add_rows(L, idx[em], beta[em] * Le * w[:, None])
        sc = hk[scene.tri_scatters[prim]]
        idx, beta, wi = idx[sc], beta[sc], wi[sc]
        s = interact(scene, Hits(t=h.t[sc], prim=h.prim[sc], u=h.u[sc], v=h.v[sc]), wi)
        wo = -wi
    return L, covered, alb0, nrm0


def render_full_frame(scene: TraceScene, camera: Camera, settings: FullFrameSettings, rng: np.random.Generator,
                      *, cover_from: int | None = None) -> FullFrame:
    """Path-trace every pixel of ``camera``; see the module docstring.

    Parameters
    ----------
    scene : geometry, materials, emitters (``emission`` per vertex, ``area_lights`` for NEE)
    camera : pinhole camera (OpenCV axes, pixel centres at integers)
    settings : samples per pixel, path depth, chunking
    rng : the only source of random numbers
    cover_from : when given, :attr:`FullFrame.coverage` counts the samples whose first hit is a
        triangle with ``tri_inst >= cover_from`` (e.g. inserted objects); zeros otherwise

    Returns
    -------
    FullFrame with (H, W, 3) float32 linear radiance
    """
    H, W = int(camera.height), int(camera.width)
    spp = int(settings.spp)
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    total = H * W * spp
    acc = np.zeros((H * W, 3))
    cov = np.zeros(H * W)
    alb = np.zeros((H * W, 3))
    nrm = np.zeros((H * W, 3))
    rays = [0]
    # samples are ordered pixel-major within a pass over all pixels, one pass per sample index
    chunk = max(int(settings.chunk_samples), W)
    flat = np.arange(H * W, dtype=np.int64)
    for start in range(0, total, chunk):
        sid = np.arange(start, min(total, start + chunk), dtype=np.int64)
        pix = flat[sid % (H * W)]
        Lc, cc, ac, nc = _trace_chunk(scene, camera, pix, settings, rng, cover_from, rays)
        add_rows(acc, pix, Lc)
        add_rows(alb, pix, ac.astype(np.float64))
        add_rows(nrm, pix, nc.astype(np.float64))
        cov += np.bincount(pix, weights=cc.astype(np.float64), minlength=H * W)
    rad = (acc / spp).astype(np.float32).reshape(H, W, 3)
    log.debug("full frame %dx%d at %d spp: %d rays", W, H, spp, rays[0])
    return FullFrame(radiance=rad, coverage=(cov / spp).astype(np.float32).reshape(H, W),
                     albedo=(alb / spp).astype(np.float32).reshape(H, W, 3),
                     normal=(nrm / spp).astype(np.float32).reshape(H, W, 3), rays=rays[0])


__all__ = ["FullFrame", "FullFrameSettings", "render_full_frame"]
