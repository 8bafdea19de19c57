"""The room's light sources recovered from its photos by inverse rendering (``trace.lighting = "fit"``).

A scan's photos show the room's surfaces, not its lamps (above the views, a window the depth sensor never saw,
a lamp clipped at sensor white), so the mesh's colours alone miss the main light. The fit finds what emits and
how much so that rendering the room reproduces the photos, after Yu et al., "Inverse Global Illumination"
(SIGGRAPH 1999), reduced to what a CPU does in seconds. :func:`fit_room_lights` chains the steps:

1. :mod:`.closure` closes the mesh with a box of cells, so light no photo saw has a place in the room.
2. :mod:`.observe` casts the photos' pixel grids: lit points to explain, clipped pixels as lower bounds.
3. :mod:`.unknowns` lists what may emit: box cells no photo saw, mesh regions seen clipped.
4. :mod:`.transport` gathers the known irradiance at the points and samples each unknown's light there.
5. :mod:`.solve` fits the emission (NNLS, an L1 prior for few bright emitters) alternated with patch albedo,
   whose per-channel level (:mod:`.albedo`) is searched on a grid; :mod:`.stages` finds where the light is,
   keeps the few emitters that carry it, and :mod:`.lamps` refines them into lamps smaller than a cell.
6. :mod:`.colour` makes the emitters one colour per kind; :mod:`.result` builds :class:`RoomLights`.
"""

from pipeline.trace.lightfit.closure import box_extent, closing_box, read_lights_file
from pipeline.trace.lightfit.fit import fit_room_lights
from pipeline.trace.lightfit.result import RoomLights
from pipeline.trace.lightfit.settings import FitSettings

__all__ = ["FitSettings", "RoomLights", "box_extent", "closing_box", "fit_room_lights", "read_lights_file"]
