"""meshprep: repair, simplification, solids and collision proxies for scans and object models.

Standalone: imports nothing from ``pipeline``. Command line: ``meshprep --help``. Python API
(functions named like the commands, each reading a file and writing outputs plus a JSON report)::

    from meshprep import inspect, repair, simplify, solid, proxy
    stats = inspect("room.ply")
    repair("room.ply", "room_fixed.ply", kind="scan", cameras="cams.npy")

Array-level functions live in the modules: :func:`meshprep.inspect.inspect_arrays`,
:func:`meshprep.mass.mass_properties`, :func:`meshprep.metrics.surface_deviation`,
:func:`meshprep.solid.solid_arrays`, :func:`meshprep.proxy.room_distance_grid`,
:func:`meshprep.proxy.object_proxy_arrays`. Note that ``meshprep.repair`` etc. name the functions
(import the modules' other names with ``from meshprep.repair import repair_meshset``).
"""

from meshprep.errors import InputError, MeshprepError, RepairError
from meshprep.inspect import inspect
from meshprep.mass import mass_properties
from meshprep.proxy import proxy
from meshprep.repair import repair
from meshprep.simplify import simplify
from meshprep.solid import solid

__version__ = "0.1.0"

__all__ = ["InputError", "MeshprepError", "RepairError", "inspect", "mass_properties", "proxy",
           "repair", "simplify", "solid"]
