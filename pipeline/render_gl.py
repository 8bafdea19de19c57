"""Depth rasterizer for posed triangle meshes: the OpenGL backend (pyrender on OSMesa, EGL optional).

A small interface: :class:`MeshRasterizer` keeps named meshes uploaded in its GL contexts and renders the
metric z-depth of any subset of them, placed by 4x4 model-to-world poses, seen by an OpenCV pinhole
camera, over the whole image or a rectangular window of it (possibly outside the image: the window is
only a shift of the principal point). Labels and masks are derived from depth by
:mod:`pipeline.annotate`; nothing here knows about scans or annotations.

The platform is OSMesa (software, any machine); with ``PYOPENGL_PLATFORM=egl`` in the environment
before scansynth starts, :mod:`pipeline.gl` loads pyrender on EGL instead (GPU machines). Nothing
else changes.

The OpenCV -> OpenGL camera conversion comes from :mod:`pipeline.camera` (:func:`~pipeline.camera.gl_camera_pose`,
:func:`~pipeline.camera.gl_intrinsics`). Pixel ``(row r, column c)`` of a rendered image samples the OpenCV image point
``u = c, v = r`` (the pixel centre): OpenGL samples at ``c + 0.5``, so the principal point passed to
GL is shifted by half a pixel.

Renderers are reused deliberately: creating and destroying OSMesa contexts per frame leaks memory in
pyrender and costs tens of milliseconds, and resizing one re-creates its framebuffers (~0.1 s), so a
:class:`MeshRasterizer` keeps one OffscreenRenderer per viewport size it is asked for (the image size
for the room, a fixed small tile for objects: reading back and linearising a full frame per object
would cost more than drawing it), at most ``max_views`` of them. :func:`shared_rasterizer` builds one
rasterizer lazily and keeps it for the life of the process (stage workers are spawned processes,
each with its own). Meshes stay uploaded between frames; the least recently used ones are released
beyond a budget of triangles, so memory stays flat over long runs.
"""

from __future__ import annotations

import functools
import logging
from collections import OrderedDict
from typing import Sequence

import numpy as np

from pipeline.camera import gl_camera_pose, gl_intrinsics
from pipeline.geometry import hull_points
from pipeline.gl import offscreen_renderer, pyrender_module

log = logging.getLogger(__name__)

ZNEAR = 0.01   # m, default near clip plane: geometry nearer than this is not drawn


class _View:
    """One OffscreenRenderer (GL context) of a fixed viewport size, with its own uploaded meshes.

    pyrender stores GL buffer ids on the mesh objects, so a mesh lives in exactly one context; and
    changing a renderer's size re-creates its framebuffers (~0.1 s on OSMesa). So each viewport size
    gets its own context and never changes size.
    """

    def __init__(self, pr, width: int, height: int, znear: float, zfar: float):
        self.pr = pr
        self.renderer = offscreen_renderer(width, height)
        self.scene = pr.Scene(bg_color=(0.0, 0.0, 0.0, 0.0), ambient_light=(0.0, 0.0, 0.0))
        self.camera = pr.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=znear, zfar=zfar)
        self.cam_node = self.scene.add(self.camera, pose=np.eye(4))
        self.meshes: dict[str, tuple] = {}  # key -> (pyrender.Mesh, anchor node keeping it uploaded)

    def ensure(self, key: str, vertices: np.ndarray, faces: np.ndarray) -> None:
        if key in self.meshes:
            return
        pr = self.pr
        mat = pr.MetallicRoughnessMaterial(doubleSided=True)
        prim = pr.Primitive(positions=np.ascontiguousarray(vertices, dtype=np.float32),
                            indices=np.ascontiguousarray(faces, dtype=np.uint32),
                            mode=pr.constants.GLTF.TRIANGLES, material=mat)
        mesh = pr.Mesh([prim])
        self.meshes[key] = (mesh, self.scene.add(mesh, pose=np.eye(4)))

    def drop(self, key: str) -> None:
        entry = self.meshes.pop(key, None)
        if entry is not None:
            self.scene.remove_node(entry[1])

    def draw(self, K, T_c2w, instances, x0, y0, with_ids: bool):
        pr = self.pr
        fx, fy, cx, cy = gl_intrinsics(K, x0, y0)
        cam = self.camera
        cam.fx, cam.fy, cam.cx, cam.cy = fx, fy, cx, cy
        self.scene.set_pose(self.cam_node, gl_camera_pose(T_c2w))
        nodes = {}
        for i, (key, T_m2w) in enumerate(instances):
            node = self.scene.add(self.meshes[key][0], pose=np.asarray(T_m2w, dtype=np.float64))
            n = i + 1  # instance index + 1 as a 24-bit flat colour, so 0 (black) is "nothing"
            nodes[node] = (n & 0xFF, (n >> 8) & 0xFF, (n >> 16) & 0xFF)
        flags = pr.RenderFlags.SEG if with_ids else pr.RenderFlags.DEPTH_ONLY | pr.RenderFlags.SEG
        try:
            # SEG restricts drawing to the listed nodes, draws flat colours and disables multisampling,
            # so depth and ids are sampled exactly at pixel centres.
            return self.renderer.render(self.scene, flags=flags, seg_node_map=nodes)
        finally:
            for node in nodes:
                self.scene.remove_node(node)

    def release(self) -> None:
        for key in list(self.meshes):
            self.drop(key)
        self.renderer.delete()


class MeshRasterizer:
    """Metric depth of posed meshes through pyrender OffscreenRenderers (one per viewport size).

    Parameters
    ----------
    znear, zfar : float
        Clip planes, metres. Geometry nearer than ``znear`` is clipped (not drawn).
    max_triangles : int
        Triangle budget of the meshes kept; least recently used meshes beyond it are released.
    max_views : int
        Viewport sizes kept (each is a GL context with its own copy of the meshes it drew).

    Examples
    --------
    >>> r = MeshRasterizer()                                          # doctest: +SKIP
    >>> r.add_mesh("cube", vertices, faces)                           # doctest: +SKIP
    >>> depth = r.render_depth(K, T_c2w, 640, 480, [("cube", T_m2w)])  # doctest: +SKIP
    """

    def __init__(self, *, znear: float = ZNEAR, zfar: float = 100.0, max_triangles: int = 8_000_000,
                 max_views: int = 3):
        self._pr = pyrender_module()
        self.znear, self.zfar = float(znear), float(zfar)
        self.max_triangles = int(max_triangles)
        self.max_views = int(max_views)
        self._views: OrderedDict[tuple[int, int], _View] = OrderedDict()
        # key -> (vertices (V,3) float64, faces (T,3) int64); uploaded lazily into each view that draws it
        self._meshes: OrderedDict[str, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._hulls: dict[str, np.ndarray] = {}

    # -- meshes ------------------------------------------------------------------------------------
    def has_mesh(self, key: str) -> bool:
        """Whether a mesh named ``key`` is held."""
        return key in self._meshes

    def add_mesh(self, key: str, vertices: np.ndarray, faces: np.ndarray) -> None:
        """Hold a triangle mesh under ``key`` (replacing one of the same name).

        Parameters
        ----------
        vertices : (V, 3) float
            Metres, model frame.
        faces : (T, 3) int
            Vertex indices. Both sides are drawn (scan meshes are open and inconsistently wound).
        """
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"mesh {key!r}: expected (V,3) vertices and (T,3) faces, got {v.shape} and {f.shape}")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise ValueError(f"mesh {key!r}: face indices outside 0..{len(v) - 1}")
        self.remove_mesh(key)
        self._meshes[key] = (v, f)
        self._evict(keep=key)

    def remove_mesh(self, key: str) -> None:
        """Release the mesh ``key`` (its GL buffers are freed at the next render of each view)."""
        self._hulls.pop(key, None)
        if self._meshes.pop(key, None) is not None:
            for view in self._views.values():
                view.drop(key)

    def mesh_vertices(self, key: str) -> np.ndarray:
        """(V, 3) float64 vertices of the mesh ``key`` (model frame, metres)."""
        return self._meshes[key][0]

    def hull_vertices(self, key: str) -> np.ndarray:
        """(H, 3) float64 convex-hull vertices of the mesh ``key`` (computed once): projecting these
        bounds the mesh's silhouette as tightly as projecting every vertex."""
        hull = self._hulls.get(key)
        if hull is None:
            hull = self._hulls[key] = hull_points(self._meshes[key][0])
        return hull

    def _evict(self, keep: str) -> None:
        total = sum(len(f) for _, f in self._meshes.values())
        for key in list(self._meshes):
            if total <= self.max_triangles:
                break
            if key == keep:
                continue
            total -= len(self._meshes[key][1])
            log.debug("releasing mesh %s (triangle budget %d)", key, self.max_triangles)
            self.remove_mesh(key)

    def _view(self, width: int, height: int) -> _View:
        size = (int(width), int(height))
        view = self._views.get(size)
        if view is None:
            while len(self._views) >= self.max_views:
                _, old = self._views.popitem(last=False)
                old.release()
            view = self._views[size] = _View(self._pr, size[0], size[1], self.znear, self.zfar)
        self._views.move_to_end(size)
        return view

    # -- rendering ---------------------------------------------------------------------------------
    def _draw(self, K, T_c2w, width, height, instances, x0, y0, with_ids):
        view = self._view(width, height)
        for key, _ in instances:
            v, f = self._meshes[key]
            self._meshes.move_to_end(key)
            view.ensure(key, v, f)
        return view.draw(np.asarray(K, dtype=np.float64), np.asarray(T_c2w, dtype=np.float64), instances,
                         x0, y0, with_ids)

    def render_depth(self, K: np.ndarray, T_c2w: np.ndarray, width: int, height: int,
                     instances: Sequence[tuple[str, np.ndarray]], *, x0: int = 0, y0: int = 0) -> np.ndarray:
        """Z-depth of the given mesh instances in the window ``[x0, x0+width) x [y0, y0+height)``.

        Parameters
        ----------
        K : (3, 3) float64
            OpenCV intrinsics of the full image, pixels.
        T_c2w : (4, 4) float64
            Camera-to-world, metres, OpenCV axes.
        width, height : int
            Window size, pixels. Each distinct size is a GL context of its own (see :class:`_View`):
            use few sizes (the image size, a fixed tile size).
        instances : sequence of (key, (4, 4) float64 T_m2w)
            Meshes (by key) and their model-to-world poses; only these are drawn.
        x0, y0 : int
            Window origin in the image's pixel grid (pixel centres at integers; may be negative or
            beyond the image: the window is only a shift of the principal point).

        Returns
        -------
        (height, width) float32
            Metres along the camera z axis at each pixel centre; 0 where nothing was hit.
        """
        depth = self._draw(K, T_c2w, width, height, instances, x0, y0, with_ids=False)
        return np.ascontiguousarray(depth, dtype=np.float32)

    def render_ids(self, K: np.ndarray, T_c2w: np.ndarray, width: int, height: int,
                   instances: Sequence[tuple[str, np.ndarray]], *, x0: int = 0,
                   y0: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Z-depth and the index of the front-most instance at each pixel, in one pass.

        Same parameters as :meth:`render_depth`; at most 2**24 - 1 instances.

        Returns
        -------
        depth : (height, width) float32
            Metres along the camera z axis; 0 where nothing was hit.
        ids : (height, width) int32
            Index into ``instances`` plus one of the front-most instance; 0 where nothing was hit.
        """
        if len(instances) >= 1 << 24:
            raise ValueError(f"{len(instances)} instances: at most {(1 << 24) - 1} per pass")
        color, depth = self._draw(K, T_c2w, width, height, instances, x0, y0, with_ids=True)
        c = color.astype(np.int32)
        ids = c[..., 0] | (c[..., 1] << 8) | (c[..., 2] << 16)
        return np.ascontiguousarray(depth, dtype=np.float32), ids

    def release(self) -> None:
        """Free the GL contexts (the object is unusable afterwards)."""
        while self._views:
            self._views.popitem()[1].release()
        self._meshes.clear()


@functools.lru_cache(maxsize=1)
def shared_rasterizer() -> MeshRasterizer:
    """The process's one :class:`MeshRasterizer` (created on first use, kept for reuse; see module doc)."""
    return MeshRasterizer()
