"""meshprep: repair, simplification, solids and collision proxies for scans and object models.

Standalone: imports nothing from ``pipeline``.
"""

__version__ = "0.1.0"
