"""The one place that loads pyrender.

``PYOPENGL_PLATFORM`` must be set before PyOpenGL is first imported, or pyrender picks a windowed
platform that does not exist on a headless machine. Import pyrender through :func:`pyrender_module`
only; never ``import pyrender`` elsewhere.
"""

from __future__ import annotations

import os
import sys


def pyrender_module():
    """Import and return pyrender on OSMesa (or EGL when ``PYOPENGL_PLATFORM=egl`` is already set)."""
    if "OpenGL" not in sys.modules:
        os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
    elif os.environ.get("PYOPENGL_PLATFORM") not in ("osmesa", "egl"):
        raise RuntimeError("PyOpenGL was imported before pipeline.gl chose a headless platform; "
                           "import pipeline.gl.pyrender_module() before anything that imports OpenGL")
    import pyrender

    return pyrender
