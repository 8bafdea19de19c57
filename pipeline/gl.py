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


def offscreen_renderer(width: int, height: int):
    """A pyrender ``OffscreenRenderer`` that reuses its compiled shader programs.

    pyrender 0.1.45 keys its program cache on ``OpenGL.contextdata.getContext()``, which under OSMesa
    returns a new object on every call: every render missed the cache, compiled and linked a fresh
    program (a few ms of llvmpipe JIT, most of the cost of drawing a small object) and kept the old one,
    so memory grew with every frame. A renderer owns its context, so a cache keyed on the shader files
    and defines alone is correct. Depends on pyrender's private ``_renderer._program_cache`` (pinned
    version); ``tests/pipeline/test_raster.py`` catches the leak if that changes.
    """
    pr = pyrender_module()
    base = pr.renderer.ShaderProgramCache

    class StableProgramCache(base):
        def __init__(self, shader_dir=None):
            super().__init__(shader_dir)
            self._stable: dict = {}

        def get_program(self, vertex_shader, fragment_shader, geometry_shader=None, defines=None):
            key = (vertex_shader, fragment_shader, geometry_shader, tuple(sorted((defines or {}).items())))
            if key not in self._stable:
                self._stable[key] = super().get_program(vertex_shader, fragment_shader, geometry_shader,
                                                        defines)
            return self._stable[key]

        def clear(self):
            super().clear()
            self._stable = {}

    renderer = pr.OffscreenRenderer(width, height)
    inner = renderer._renderer
    inner._program_cache = StableProgramCache(inner._program_cache.shader_dir)
    return renderer
