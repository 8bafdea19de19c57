"""Depth rasterizer for posed triangle meshes: the OpenGL backend (pyrender on OSMesa, EGL optional).

A small interface: :class:`MeshRasterizer` keeps named meshes uploaded in one GL context and renders the
metric z-depth of any subset of them, placed by 4x4 model-to-world poses, seen by an OpenCV pinhole
camera, over the whole image or a rectangular window of it (possibly outside the image: the window is
only a shift of the principal point). Labels and masks are derived from depth by
:mod:`pipeline.annotate`; nothing here knows about scans or annotations.

The OpenCV -> OpenGL camera conversion lives in this module only (:func:`gl_camera_pose`,
:func:`gl_intrinsics`). Pixel ``(row r, column c)`` of a rendered image samples the OpenCV image point
``u = c, v = r`` (the pixel centre): OpenGL samples at ``c + 0.5``, so the principal point passed to
GL is shifted by half a pixel.

One OffscreenRenderer per process, deliberately: creating and destroying OSMesa contexts per frame
leaks memory in pyrender and costs tens of milliseconds, so :func:`shared_rasterizer` builds one
lazily and keeps it for the life of the process (stage workers are spawned processes, each with its
own). Meshes stay uploaded between frames; the least recently used ones are released beyond a budget
of triangles, so memory stays flat over long runs.
"""

from __future__ import annotations

import functools
import logging
from collections import OrderedDict
from typing import Sequence

import numpy as np

from pipeline.gl import pyrender_module

log = logging.getLogger(__name__)

# OpenCV camera axes (x right, y down, z forward) -> OpenGL camera axes (x right, y up, z backward).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def gl_camera_pose(T_c2w: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world pose of an OpenCV camera-to-world pose.

    Parameters
    ----------
    T_c2w : (4, 4) float64
        Camera-to-world, metres, OpenCV camera axes.

    Returns
    -------
    (4, 4) float64
        Camera-to-world with OpenGL camera axes (y up, looking down -z), as pyrender expects.
    """
    return np.asarray(T_c2w, dtype=np.float64) @ _CV_TO_GL


def gl_intrinsics(K: np.ndarray, x0: int = 0, y0: int = 0) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` for pyrender's IntrinsicsCamera rendering the window at ``(x0, y0)``.

    Parameters
    ----------
    K : (3, 3) float64
        OpenCV intrinsics, pixels; pixel centres at integer coordinates.
    x0, y0 : int
        Top-left pixel of the rendered window in the image's pixel grid (may be negative).

    Returns
    -------
    tuple of float
        The principal point is moved to the window and shifted by half a pixel, because OpenGL samples
        pixel ``c`` at ``c + 0.5`` while OpenCV's pixel centre is ``c``.
    """
    return (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) - x0 + 0.5, float(K[1, 2]) - y0 + 0.5)


class MeshRasterizer:
    """Metric depth of posed meshes through one pyrender OffscreenRenderer.

    Parameters
    ----------
    znear, zfar : float
        Clip planes, metres. Geometry nearer than ``znear`` is clipped (not drawn).
    max_triangles : int
        Triangle budget of the meshes kept uploaded; least recently used meshes beyond it are released.

    Examples
    --------
    >>> r = MeshRasterizer()                                          # doctest: +SKIP
    >>> r.add_mesh("cube", vertices, faces)                           # doctest: +SKIP
    >>> depth = r.render_depth(K, T_c2w, 640, 480, [("cube", T_m2w)])  # doctest: +SKIP
    """

    def __init__(self, *, znear: float = 0.01, zfar: float = 100.0, max_triangles: int = 8_000_000):
        pr = pyrender_module()
        self._pr = pr
        self.znear, self.zfar = float(znear), float(zfar)
        self.max_triangles = int(max_triangles)
        self._renderer = pr.OffscreenRenderer(64, 64)
        self._scene = pr.Scene(bg_color=(0.0, 0.0, 0.0, 0.0), ambient_light=(0.0, 0.0, 0.0))
        self._camera = pr.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=self.znear, zfar=self.zfar)
        self._cam_node = self._scene.add(self._camera, pose=np.eye(4))
        # key -> (pyrender.Mesh, anchor node keeping it uploaded, vertices (V,3) float64, n_triangles)
        self._meshes: OrderedDict[str, tuple] = OrderedDict()

    # -- meshes ------------------------------------------------------------------------------------
    def has_mesh(self, key: str) -> bool:
        """Whether a mesh named ``key`` is uploaded."""
        return key in self._meshes

    def add_mesh(self, key: str, vertices: np.ndarray, faces: np.ndarray) -> None:
        """Upload a triangle mesh under ``key`` (replacing one of the same name).

        Parameters
        ----------
        vertices : (V, 3) float
            Metres, model frame.
        faces : (T, 3) int
            Vertex indices. Both sides are drawn (scan meshes are open and inconsistently wound).
        """
        pr = self._pr
        v = np.ascontiguousarray(vertices, dtype=np.float32)
        f = np.ascontiguousarray(faces, dtype=np.uint32)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise ValueError(f"mesh {key!r}: expected (V,3) vertices and (T,3) faces, "
                             f"got {v.shape} and {f.shape}")
        self.remove_mesh(key)
        mat = pr.MetallicRoughnessMaterial(doubleSided=True)
        prim = pr.Primitive(positions=v, indices=f, mode=pr.constants.GLTF.TRIANGLES, material=mat)
        mesh = pr.Mesh([prim])
        anchor = self._scene.add(mesh, pose=np.eye(4))
        self._meshes[key] = (mesh, anchor, np.asarray(vertices, dtype=np.float64), int(f.shape[0]))
        self._evict(keep=key)

    def remove_mesh(self, key: str) -> None:
        """Release the mesh ``key`` (its GL buffers are freed at the next render)."""
        entry = self._meshes.pop(key, None)
        if entry is not None:
            self._scene.remove_node(entry[1])

    def mesh_vertices(self, key: str) -> np.ndarray:
        """(V, 3) float64 vertices of the uploaded mesh ``key`` (model frame, metres)."""
        return self._meshes[key][2]

    def _evict(self, keep: str) -> None:
        total = sum(e[3] for e in self._meshes.values())
        for key in list(self._meshes):
            if total <= self.max_triangles:
                break
            if key == keep:
                continue
            total -= self._meshes[key][3]
            log.debug("releasing mesh %s (triangle budget %d)", key, self.max_triangles)
            self.remove_mesh(key)

    # -- rendering ---------------------------------------------------------------------------------
    def _draw(self, K: np.ndarray, T_c2w: np.ndarray, width: int, height: int,
              instances: Sequence[tuple[str, np.ndarray]], x0: int, y0: int, with_ids: bool):
        pr = self._pr
        fx, fy, cx, cy = gl_intrinsics(K, x0, y0)
        cam = self._camera
        cam.fx, cam.fy, cam.cx, cam.cy = fx, fy, cx, cy
        self._scene.set_pose(self._cam_node, gl_camera_pose(T_c2w))
        nodes = {}
        for i, (key, T_m2w) in enumerate(instances):
            mesh = self._meshes[key][0]
            self._meshes.move_to_end(key)
            node = self._scene.add(mesh, pose=np.asarray(T_m2w, dtype=np.float64))
            n = i + 1  # instance index + 1 as a 24-bit flat colour, so 0 (black) is "nothing"
            nodes[node] = (n & 0xFF, (n >> 8) & 0xFF, (n >> 16) & 0xFF)
        r = self._renderer
        # A size change re-creates the framebuffers (~0.1 s on OSMesa): callers keep one size per frame.
        if r.viewport_width != width or r.viewport_height != height:
            r.viewport_width, r.viewport_height = int(width), int(height)
        flags = pr.RenderFlags.SEG if with_ids else pr.RenderFlags.DEPTH_ONLY | pr.RenderFlags.SEG
        try:
            # SEG restricts drawing to the listed nodes, draws flat colours and disables multisampling,
            # so depth and ids are sampled exactly at pixel centres.
            return r.render(self._scene, flags=flags, seg_node_map=nodes)
        finally:
            for node in nodes:
                self._scene.remove_node(node)

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
            Window size, pixels. Keep it the same from call to call (see :meth:`_draw`).
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
        """Free the GL context (the object is unusable afterwards)."""
        for key in list(self._meshes):
            self.remove_mesh(key)
        self._renderer.delete()


@functools.lru_cache(maxsize=1)
def shared_rasterizer() -> MeshRasterizer:
    """The process's one :class:`MeshRasterizer` (created on first use, kept for reuse; see module doc)."""
    return MeshRasterizer()
