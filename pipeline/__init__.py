"""scansynth: synthetic training data from real RGB-D room scans.

The import package is ``pipeline`` (stages, types, CLI); ``meshprep`` is a separate, standalone
package for mesh repair and simplification.
"""

__version__ = "0.1.0"
