"""Step 9, what few views cannot pin: the light's level and colour of a capture of one or two photos.

A photo of a table and a wall shows little of what lights it: its brightness is albedo x light with either
free (the level search's objective is nearly flat), and a coloured surface passes for coloured light, so the
fitted level and colour follow the priors and change with whatever else changes in the mesh (another object
cut out of it). What such a photo does pin:

- the camera's white balance: the light that dominates a photo is white in the photo's colour space, so the
  fitted emitters take white at the luminance the fit found;
- the camera's auto exposure: it puts the average scene at a known grey, so the light's level is pinned to
  the world's average reflectance (``AVERAGE_ALBEDO``, the 18 % grey card an exposure meter assumes): the
  emitters are scaled by the fitted mean albedo of the photographed surfaces over it, the level at which
  those surfaces would average it if the emitters carried all of their light (the light the scan's own
  surfaces send stays as the photos show it, so their mean albedo comes out somewhat above it). The fitted
  albedo is divided by the same gain per channel, for the shadow pass that takes objects' shadows out of it.

The emitters the fit made (the closing box's cells and the lamps) keep their places and shapes; a light a photo
saw keeps its own radiance, and with lights handed in (``trace.lights_file``) the user's level stands and nothing
is pinned. The summary's emitters and albedo figures are those of the light the tracer uses; ``capture_prior``
keeps the gain from the fit's own. One warning line says what was assumed.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from pipeline.color import LUMINANCE_F64

log = logging.getLogger(__name__)

AVERAGE_ALBEDO = 0.18         # mean reflectance of an average scene (the exposure meter's grey card), linear


def pin_capture(rl, rho_points: np.ndarray, albedo: float, views: int, name: str):
    """``rl`` (a fitted :class:`~pipeline.trace.lightfit.RoomLights`) with its emitters white at their
    luminance, scaled by the mean luminance of the fitted albedo ``rho_points (n, 3)`` of the photographed points
    over ``albedo``; ``views`` is the number of photos the fit had (for the message). The summary records it
    under ``capture_prior``."""
    nv = rl.num_mesh_vertices
    rad = rl.radiance.astype(np.float64)
    emit = rad[nv:]
    if not len(emit) or not len(rho_points):
        return rl
    mean_albedo = float(np.mean(rho_points @ LUMINANCE_F64))
    if not np.isfinite(mean_albedo) or mean_albedo <= 0:
        return rl
    scale = mean_albedo / albedo
    lum = emit @ LUMINANCE_F64
    white = np.repeat(lum[:, None], 3, axis=1) * scale
    gain = white.sum(axis=0) / np.maximum(emit.sum(axis=0), 1e-12)    # (3,) light after over before, per channel
    rad[nv:] = white
    alb = None if rl.albedo is None else (rl.albedo / np.maximum(gain, 1e-6)).astype(np.float32)
    note = (f"{views} view{'s' if views != 1 else ''} cannot pin the light's level or colour: white light (the "
            f"camera's white balance), {scale:.2f}x the fit's (its surfaces' mean albedo {mean_albedo:.2f} over "
            f"{albedo:.2f}, the average scene's reflectance the camera's auto exposure assumes; "
            f"trace.fit_capture_albedo)")
    log.warning("light fit of %s: %s", name, note)
    emitters = [dict(e, radiance=[round(float(np.asarray(e["radiance"], np.float64) @ LUMINANCE_F64) * scale, 4)] * 3)
                for e in rl.summary.get("emitters", [])]
    per_channel = {k: [round(float(x) / float(g), 4) for x, g in zip(rl.summary[k], gain)]
                   for k in ("albedo_level", "albedo_mean") if rl.summary.get(k) is not None}
    summary = dict(rl.summary, emitters=emitters, **per_channel, capture_prior={"views": views, "albedo": albedo,
                                              "fitted_mean_albedo": round(mean_albedo, 4),
                                              "gain_rgb": [round(float(g), 4) for g in gain]},
                   capture_note=note)
    return dataclasses.replace(rl, radiance=rad.astype(np.float32), albedo=alb, summary=summary)
