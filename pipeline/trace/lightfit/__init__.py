"""The room's light sources recovered from its photos by inverse rendering (``trace.lighting = "fit"``).

The photos show the room's surfaces, not its lamps, so the fit finds what emits and how much so that the room
rendered with it reproduces them (after Yu et al., "Inverse Global Illumination", SIGGRAPH 1999, reduced to a
CPU's seconds). :func:`fit_room_lights` chains the steps, each a module:

1. ``closure``: the mesh closed by a box of cells, so light no photo saw has a place in the room.
2. ``observe``: the photos' pixel grids; lit points to explain, clipped pixels as lower bounds.
3. ``unknowns``: what may emit: box cells no photo saw, mesh regions seen clipped.
4. ``transport``: the known irradiance at the points, and each unknown's light there per unit radiance.
5. ``solve``: emission by NNLS with an L1 prior (few bright emitters), alternated with patch albedo at each
   channel's albedo level (``albedo``: patches by material, level searches); ``stages`` finds where the light
   is, keeps the few emitters that carry it, and ``lamps`` refines them into lamps smaller than a cell.
6. ``colour``: one light colour per kind of emitter; ``result``: :class:`RoomLights`, kept per scan.
"""

from pipeline.trace.lightfit.closure import box_extent, closing_box, read_lights_file
from pipeline.trace.lightfit.fit import fit_room_lights
from pipeline.trace.lightfit.result import RoomLights
from pipeline.trace.lightfit.settings import FitSettings

__all__ = ["FitSettings", "RoomLights", "box_extent", "closing_box", "fit_room_lights", "read_lights_file"]
