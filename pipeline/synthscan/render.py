"""Photo and depth renderers for synthetic scans.

A photo renderer turns a camera (pose, intrinsics, size) into a linear-RGB image in exposure units
(1.0 = sensor white). Modes sit behind :class:`PhotoRenderer`, made by :func:`make_photo_renderer`:

- ``"raster"`` (:class:`RasterPhotoRenderer`): pyrender on OSMesa. Diffuse albedo from the procedural
  textures times a per-vertex light map (exact area-light irradiance with ray-traced soft shadows,
  plus a uniform ambient term, baked once per room); emitters are clipped white.
- ``"traced"``: reserved for the path tracer of issue 9 (global illumination, sharp soft shadows). It
  plugs in by implementing the same two methods; until then asking for it is a :class:`UserError`.

Depth is rendered by the raster backend in every mode (it is exact geometry, not lighting).
"""

from __future__ import annotations

import logging
from typing import Protocol

import numpy as np

from pipeline.errors import UserError
from pipeline.gl import offscreen_renderer, pyrender_module
from pipeline.synthscan.room import MeshData, Room

log = logging.getLogger(__name__)

PHOTO_MODES = ("raster", "traced")

# OpenCV camera axes (x right, y down, z forward) -> OpenGL camera axes (x right, y up, z backward).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


class PhotoRenderer(Protocol):
    """What every photo mode provides."""

    def render_color(self, T_c2w: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
        """Linear RGB (height, width, 3) float32 in exposure units (may exceed 1 at emitters)."""

    def render_depth(self, T_c2w: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
        """Z-depth (height, width) float32 metres along the optical axis; 0 where nothing was hit."""

    def close(self) -> None:
        """Release the backend."""


class RasterPhotoRenderer:
    """pyrender/OSMesa renderer of a room with baked vertex lighting.

    Parameters
    ----------
    room : Room
    mesh : MeshData, the tessellated room (its vertices carry the light map)
    vertex_radiance : (V, 3) float32, exposure-scaled outgoing radiance per unit albedo at each vertex
        (for emitters: the emitted radiance times exposure)
    """

    def __init__(self, room: Room, mesh: MeshData, vertex_radiance: np.ndarray) -> None:


        self._pr = pyrender_module()
        self._room, self._mesh, self._radiance = room, mesh, vertex_radiance
        # OSMesa cannot resize a context and a pyrender mesh binds to one context, so each image size
        # gets its own renderer and scene: (renderer, scene, colour meshes or None, depth mesh, camera node)
        self._views: dict[tuple[int, int], list] = {}

    def _colour_meshes(self) -> list:
        pr, room, mesh = self._pr, self._room, self._mesh
        out = []
        face_mat = room.quad_material[mesh.face_quad]
        for mat in room.materials:
            sel = np.flatnonzero(face_mat == mat.id)
            if len(sel) == 0:
                continue
            f = mesh.faces[sel]
            used, inv = np.unique(f.reshape(-1), return_inverse=True)
            tex = pr.Texture(source=room.textures[mat.id], source_channels="RGB",
                             sampler=pr.Sampler(wrapS=10497, wrapT=10497))  # GL_REPEAT
            material = pr.MetallicRoughnessMaterial(
                baseColorFactor=np.ones(4), baseColorTexture=tex, metallicFactor=0.0, roughnessFactor=1.0)
            light = np.power(np.maximum(self._radiance[used], 0.0), 1 / 2.2)
            colors = np.concatenate([light, np.ones((len(used), 1), np.float32)], 1).astype(np.float32)
            prim = pr.Primitive(
                positions=mesh.vertices[used].astype(np.float32), normals=mesh.normals[used],
                texcoord_0=mesh.uv[used], color_0=colors,
                indices=inv.reshape(-1, 3).astype(np.uint32), material=material, mode=4)
            out.append(pr.Mesh([prim]))
        return out

    def _view(self, T_c2w: np.ndarray, K: np.ndarray, width: int, height: int, colour: bool):
        pr = self._pr
        key = (int(width), int(height))
        if key not in self._views:
            scene = pr.Scene(ambient_light=np.ones(3), bg_color=np.zeros(4))
            prim = pr.Primitive(positions=self._mesh.vertices.astype(np.float32),
                                indices=self._mesh.faces.astype(np.uint32), mode=4)
            depth_mesh = pr.Mesh([prim])
            scene.add(depth_mesh)
            renderer = offscreen_renderer(width, height)
            self._views[key] = [renderer, scene, None, depth_mesh, None]
        view = self._views[key]
        renderer, scene, meshes, depth_mesh, cam_node = view
        if colour and meshes is None:
            meshes = view[2] = self._colour_meshes()
            for m in meshes:
                scene.add(m)
        for m in meshes or ():
            m.is_visible = colour
        depth_mesh.is_visible = not colour
        # pyrender puts pixel centres at half-integers; OpenCV K puts them at integers.
        cam = pr.IntrinsicsCamera(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]) + 0.5,
                                  cy=float(K[1, 2]) + 0.5, znear=0.02, zfar=50.0)
        if cam_node is not None:
            scene.remove_node(cam_node)
        view[4] = scene.add(cam, pose=T_c2w @ CV_TO_GL)
        return renderer, scene

    def render_color(self, T_c2w: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
        r, scene = self._view(T_c2w, K, width, height, colour=True)
        color, _ = r.render(scene, flags=self._pr.RenderFlags.FLAT)
        # The flat shader writes clamp(texture_sRGB * vertex_colour), and the vertex colours hold the
        # light map raised to 1/2.2: the product is the gamma-2.2 encoded photo. Undo it: linear units.
        return np.power(color.astype(np.float32) / 255.0, 2.2)

    def render_depth(self, T_c2w: np.ndarray, K: np.ndarray, width: int, height: int) -> np.ndarray:
        r, scene = self._view(T_c2w, K, width, height, colour=False)
        depth = r.render(scene, flags=self._pr.RenderFlags.DEPTH_ONLY)
        return np.asarray(depth, np.float32)

    def close(self) -> None:
        for view in self._views.values():
            view[0].delete()
        self._views.clear()


def make_photo_renderer(mode: str, room: Room, mesh: MeshData, vertex_radiance: np.ndarray) -> PhotoRenderer:
    """The photo renderer for ``mode`` (one of :data:`PHOTO_MODES`)."""
    if mode == "raster":
        return RasterPhotoRenderer(room, mesh, vertex_radiance)
    if mode == "traced":
        raise UserError("photo mode 'traced' needs the path tracer (issue 9), which is not built yet; "
                        "use --photo-mode raster")
    raise UserError(f"unknown photo mode {mode!r}; choose one of {', '.join(PHOTO_MODES)}")
