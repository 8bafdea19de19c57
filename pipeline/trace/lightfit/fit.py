"""The light fit as one chain of steps, each a function of the records the previous ones made."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from pipeline.trace.lightfit.albedo import finite
from pipeline.trace.lightfit.capture import pin_capture
from pipeline.trace.lightfit.closure import close_room, facing_away
from pipeline.trace.lightfit.colour import say_edge_raise
from pipeline.trace.lightfit.observe import MIN_FIT_POINTS, observe, select_points
from pipeline.trace.lightfit.result import RoomLights, fallback, room_lights
from pipeline.trace.lightfit.settings import FitSettings
from pipeline.trace.lightfit.solve import make_problem
from pipeline.trace.lightfit.stages import solve_lights
from pipeline.trace.lightfit.transport import light_transport
from pipeline.trace.lightfit.unknowns import find_unknowns


def fit_room_lights(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None, frames, *,
                    up: np.ndarray, rng: np.random.Generator, settings: FitSettings = FitSettings(),
                    name: str = "scan", known_lights=(), threads: int = 1) -> RoomLights:
    """Recover the room's emitters from its photos (see :mod:`pipeline.trace.lightfit`).

    Parameters
    ----------
    vertices, faces : (V, 3) float metres and (T, 3) int, the room mesh
    colors : (V, 3) uint8 sRGB vertex colours (the radiance of what the scan saw), or None (then the
        photos' own observations give each vertex its radiance)
    frames : list of ``(photo (H, W, 3) uint8 sRGB, K (3, 3), T_c2w (4, 4))``
    up : (3,) world up
    rng : seeded generator (the fit is deterministic for a generator state)
    name : the scan's name, for messages
    known_lights : ``(corners (4, 3) metres, radiance (3,) linear, photo units)`` rectangles that are
        known to emit (``trace.lights_file``): added to the room as lights of that radiance; the fit
        then explains only what they leave unexplained
    threads : threads for the fit's shadow rays and its independent level searches (the result does not
        depend on it; BLAS is left as the caller set it): more than one where nothing else runs beside the
        fit (the trace stage's plan)

    Returns
    -------
    RoomLights; its ``summary["note"]`` says in one line what was assumed when the fit fell back
    """
    if threads <= 1:
        return _fit(vertices, faces, colors, frames, up=up, rng=rng, settings=settings, name=name,
                    known_lights=known_lights, pool=None)
    with ThreadPoolExecutor(max_workers=threads) as pool:
        return _fit(vertices, faces, colors, frames, up=up, rng=rng, settings=settings, name=name,
                    known_lights=known_lights, pool=pool)


def _fit(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None, frames, *, up: np.ndarray,
         rng: np.random.Generator, settings: FitSettings, name: str, known_lights,
         pool: ThreadPoolExecutor | None) -> RoomLights:
    """:func:`fit_room_lights`, its shadow rays and level searches on ``pool``'s threads (None: this one)."""
    t0 = time.process_time()
    st = settings
    frames = list(frames)
    room = close_room(vertices, faces, frames, known_lights, up, st.cell)
    obs = observe(room, frames, colors, st)
    summary: dict = {"frames": len(frames), "exposure": [round(e, 4) for e in obs.exposures],
                     "box_cells": int(len(room.box_centre)), "mesh_triangles": int(room.nt),
                     "known_lights": len(room.known_quads), "camera_sides": obs.sides.tolist()}
    if obs.edge_pixels is not None:
        summary["clipped_edge_pixels"] = obs.edge_pixels
        summary["clipped_edge_colour"] = None if obs.edge_colour is None else finite(obs.edge_colour)
    summary["seen_side"] = obs.seen_side
    backwards = facing_away(room, name)
    if backwards:
        summary["lights_facing_away"] = backwards
    if not frames:
        return fallback(room, obs.mesh_rad, summary, "no colour photos: lit by the mesh colours alone, holes at "
                        "their mean radiance", name, t0)
    if room.nt == 0:
        return fallback(room, obs.mesh_rad, summary, "no room mesh: nothing to fit", name, t0)
    unk = find_unknowns(room, obs, colors, st)
    summary.update(unk.summary)
    m = len(obs.points)
    if m == 0:
        return fallback(room, unk.mesh_rad, summary, "no unclipped, lit room pixel in the photos (all dark or all "
                        "clipped): lit by the mesh colours alone", name, t0)
    if m < MIN_FIT_POINTS:
        return fallback(room, unk.mesh_rad, summary, f"only {m} unclipped lit room pixels in the photos (need "
                        f"{MIN_FIT_POINTS}): lit by the mesh colours alone", name, t0)
    pts = select_points(obs, st.points, rng)
    tr = light_transport(room, unk, pts, obs.seen_side, st.gather_rays, st.emitter_samples, MIN_FIT_POINTS, rng,
                         pool)
    summary.update(tr.summary)
    pb = make_problem(room, unk, pts, tr, obs.edge_colour, st)
    summary.update(pb.summary)
    sol = solve_lights(pb, rng, pool)
    summary.update(sol.summary)
    if sol.raised is not None:      # the clipped lights took the edges' colour (not with every light given)
        summary["clipped_edge_raised"] = round(sol.raised, 3)
        say_edge_raise(name, obs.edge_colour, sol.raised)
    rl = room_lights(pb, sol, summary, name, t0)
    if len(frames) < st.capture_views and sol.level is not None and not room.known_quads:
        rl = pin_capture(rl, sol.rho[pb.patch], st.capture_albedo, len(frames), name)
    return rl
