"""Full-frame path tracing: every pixel, every surface (the room included), emitters seen directly.

:func:`pbr.render` traces object pixels only and treats the room as a light source of its captured
colours. This module renders a whole frame of a scene whose lights are real emitting triangles (a
synthetic room with ceiling panels and a window): unidirectional path tracing with next-event
estimation on the area lights and MIS against BSDF sampling (power heuristic), Russian roulette, and
ONE-SIDED emitters (a triangle emits only to the side its winding normal points to, like the
synthetic scan's Lambertian panels). The paths are traced by the object tracer's own bounce loop
(:func:`pipeline.trace.pbr.trace_paths`) with other :class:`~pipeline.trace.pbr.PathOptions`: every
first hit starts a path, emitters are one-sided, and the last scattering event ends the path.

Random numbers come only from the generator passed in and are drawn in a fixed order per chunk of
samples (:class:`~pipeline.trace.pbr.ChunkDraws`): the same scene, camera, settings and generator state
give the same bytes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from pipeline.camera import Camera
from pipeline.tolerances import TRACE_RAY_EPS_M
from pipeline.trace.pbr import ChunkDraws, PathOptions, RayCounter, add_rows, trace_paths
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
    counter = RayCounter()
    draws = ChunkDraws(rng)
    opts = PathOptions(max_depth=settings.max_depth, rr_depth=settings.rr_depth, ray_eps=settings.ray_eps,
                       objects_only=False, one_sided=True, trace_last=False,
                       cover_from=np.iinfo(np.int64).max if cover_from is None else cover_from)
    # samples are ordered pixel-major within a pass over all pixels, one pass per sample index
    chunk = max(int(settings.chunk_samples), W)
    flat = np.arange(H * W, dtype=np.int64)
    for start in range(0, total, chunk):
        sid = np.arange(start, min(total, start + chunk), dtype=np.int64)
        pix = flat[sid % (H * W)]
        r = trace_paths(scene, camera, pix, draws, opts, counter)
        add_rows(acc, pix, r["L"])
        add_rows(alb, pix, r["albedo"].astype(np.float64))
        add_rows(nrm, pix, r["normal"].astype(np.float64))
        cov += np.bincount(pix, weights=r["covered"].astype(np.float64), minlength=H * W)
    rad = (acc / spp).astype(np.float32).reshape(H, W, 3)
    log.debug("full frame %dx%d at %d spp: %d rays", W, H, spp, counter.rays)
    return FullFrame(radiance=rad, coverage=(cov / spp).astype(np.float32).reshape(H, W),
                     albedo=(alb / spp).astype(np.float32).reshape(H, W, 3),
                     normal=(nrm / spp).astype(np.float32).reshape(H, W, 3), rays=counter.rays)


__all__ = ["FullFrame", "FullFrameSettings", "render_full_frame"]
