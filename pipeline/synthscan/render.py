"""Photo and depth renderers for synthetic scans.

A photo renderer turns a camera (pose, intrinsics, size) into a linear-RGB image in exposure units
(1.0 = sensor white). Modes sit behind :class:`PhotoRenderer`, made by :func:`make_photo_renderer`:

- ``"raster"`` (:class:`RasterPhotoRenderer`): pyrender on OSMesa. Diffuse albedo from the procedural
  textures times a per-vertex light map (exact area-light irradiance with ray-traced soft shadows,
  plus a uniform ambient term, baked once per room); emitters are clipped white.
- ``"traced"`` (:class:`TracedPhotoRenderer`): the path tracer (:mod:`pipeline.trace.fullframe`, Embree,
  metallic-roughness BSDF, NEE + MIS) on the TRUE room: every quad with its material's texture and
  roughness, the ceiling panels and the window as one-sided emitters of their known radiance. Global
  illumination and soft shadows come out of the light transport itself (no ambient term). Radiance is
  multiplied by the scan's exposure, the same number the raster mode uses, so both modes go through
  the same camera response (``degrade.encode_photo``) and look alike.

Depth is rendered by the raster backend in every mode (it is exact geometry, not lighting), so depth
files do not change with the photo mode.

:func:`render_traced_view` renders the same room with extra objects inserted (same renderer, same
lights): the ground truth of the compositor's accuracy benchmark (issue 10).
"""

from __future__ import annotations

import logging
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from pipeline.camera import Camera
from pipeline.errors import UserError
from pipeline.gl import offscreen_renderer, pyrender_module
from pipeline.synthscan.room import MeshData, Room

if TYPE_CHECKING:
    from pipeline.trace.scene import ObjectInstance, TraceScene

log = logging.getLogger(__name__)

PHOTO_MODES = ("raster", "traced")
ZNEAR, ZFAR = 0.02, 50.0   # metres: clip planes of the scan's photos and depth maps



class PhotoRenderer(Protocol):
    """What every photo mode provides."""

    def render_color(self, cam: Camera) -> np.ndarray:
        """Linear RGB (height, width, 3) float32 in exposure units (may exceed 1 at emitters)."""

    def render_depth(self, cam: Camera) -> np.ndarray:
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


        from pipeline.render_gl import MeshRasterizer

        self._pr = pyrender_module()
        self._room, self._mesh, self._radiance = room, mesh, vertex_radiance
        # OSMesa cannot resize a context and a pyrender mesh binds to one context, so each image size
        # gets its own renderer and scene: (renderer, scene, camera node or None)
        self._views: dict[tuple[int, int], list] = {}
        self._depth = MeshRasterizer(znear=ZNEAR, zfar=ZFAR)   # the pipeline's rasterizer draws the depth
        self._depth.add_mesh("room", mesh.vertices, mesh.faces)

    def _colour_mesh(self):
        """The room as ONE pyrender mesh with a primitive per material: primitives are drawn in list order,
        while separate meshes are drawn in the order of a set of nodes (it varies from process to process),
        which decided z-ties between coincident surfaces differently in different runs."""
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
            out.append(prim)
        return pr.Mesh(out)

    def render_color(self, cam: Camera) -> np.ndarray:
        pr = self._pr
        view = self._views.get(cam.shape)
        if view is None:
            scene = pr.Scene(ambient_light=np.ones(3), bg_color=np.zeros(4))
            scene.add(self._colour_mesh())
            view = self._views[cam.shape] = [offscreen_renderer(cam.width, cam.height), scene, None]
        renderer, scene, cam_node = view
        fx, fy, cx, cy = cam.gl_intrinsics()
        if cam_node is not None:
            scene.remove_node(cam_node)
        view[2] = scene.add(pr.IntrinsicsCamera(fx=fx, fy=fy, cx=cx, cy=cy, znear=ZNEAR, zfar=ZFAR),
                            pose=cam.gl_pose())
        color, _ = renderer.render(scene, flags=pr.RenderFlags.FLAT)
        # The flat shader writes clamp(texture_sRGB * vertex_colour), and the vertex colours hold the
        # light map raised to 1/2.2: the product is the gamma-2.2 encoded photo. Undo it: linear units.
        return np.power(color.astype(np.float32) / 255.0, 2.2)

    def render_depth(self, cam: Camera) -> np.ndarray:
        return self._depth.render_depth(cam.K, cam.T_c2w, cam.width, cam.height, [("room", np.eye(4))])

    def close(self) -> None:
        for view in self._views.values():
            view[0].delete()
        self._views.clear()
        self._depth.release()


TRACED_SPP = 16           # samples per pixel of traced photos (make_scan); sensor noise is added after
TRACED_MAX_DEPTH = 5      # scattering events per path
TRACED_DENOISE = "auto"   # traced photos: OIDN (pyoidn) when installed, else none; see _denoise
DENOISE_CHOICES = ("none", "auto", "oidn", "bilateral")
TRACED_CELL = 100.0       # metres: tessellation of the traced room (one cell per quad: the quads are flat)


def exposure_from_radiance(room: Room, mesh: MeshData, vertex_radiance: np.ndarray) -> float:
    """The exposure baked into ``vertex_radiance`` (emitter vertices hold ``light.radiance * exposure``).

    Raises ``ValueError`` when the room has no light or its light vertices are not in ``mesh``.
    """
    names = {p.name: q for q, p in enumerate(room.parts)}
    vpart = room.quad_part[mesh.vertex_quad]
    for light in room.lights:
        sel = np.flatnonzero(vpart == names.get(light.name, -1))
        if sel.size:
            c = int(np.argmax(light.radiance))
            return float(vertex_radiance[sel[0], c]) / float(light.radiance[c])
    raise ValueError("the room mesh has no emitter vertices to read the exposure from")


def room_trace_scene(room: Room, exposure: float, extra: list[ObjectInstance] | tuple = (), *,
                     T_world_from_canonical: np.ndarray | None = None) -> TraceScene:
    """The room (canonical frame) as a :class:`~pipeline.trace.scene.TraceScene`, plus extra objects.

    Triangles of room quads get ``tri_inst = material id``; extra object ``k`` gets
    ``tri_inst = len(room.materials) + k``. Room surfaces are dielectric metallic-roughness materials
    (textured base colour, the material's roughness, specular 1); emitters reflect nothing and emit
    ``light.radiance * exposure`` to the side of their normal.

    Parameters
    ----------
    room : Room
    exposure : float, > 0, radiance-to-sensor scale (``scan.json["exposure"]``)
    extra : objects to insert, vertices/normals in the world frame of ``T_world_from_canonical``
    T_world_from_canonical : (4, 4) float, the scan's world frame (``scan.json``); None = canonical
    """
    from pipeline.synthscan.room import tessellate
    from pipeline.color import srgb_to_linear
    from pipeline.trace.intersect import EmbreeIntersector
    from pipeline.trace.lights import PointLights, build_area_lights
    from pipeline.trace.scene import TraceScene, Textures

    mesh = tessellate(room, TRACED_CELL)
    nm = len(room.materials)
    emitter = np.array([m.emitter for m in room.materials])
    vmat = room.quad_material[mesh.vertex_quad]
    alb = np.repeat(np.where(emitter[vmat], 0.0, 1.0)[:, None], 3, axis=1).astype(np.float32)  # texture = colour
    emis = np.zeros((len(mesh.vertices), 3), np.float32)
    part_of = {p.name: q for q, p in enumerate(room.parts)}
    vpart = room.quad_part[mesh.vertex_quad]
    for light in room.lights:
        emis[vpart == part_of[light.name]] = (light.radiance * exposure).astype(np.float32)
    verts = [mesh.vertices]
    faces = [mesh.faces.astype(np.int64)]
    norms = [mesh.normals.astype(np.float32)]
    albs, emss, uvs = [alb], [emis], [mesh.uv.astype(np.float32)]
    tri_inst = [room.quad_material[mesh.face_quad].astype(np.int32)]
    metallic = [0.0] * nm
    roughness = [m.roughness for m in room.materials]
    specular = [0.0 if m.emitter else 1.0 for m in room.materials]
    tex_inst = [m.id for m in room.materials if not m.emitter]
    tex_img = [srgb_to_linear(room.textures[i]) for i in tex_inst]
    T_cw = np.eye(4) if T_world_from_canonical is None else np.linalg.inv(np.asarray(T_world_from_canonical, float))
    off = len(mesh.vertices)
    for k, ob in enumerate(extra):
        ov = np.asarray(ob.vertices, np.float64) @ T_cw[:3, :3].T + T_cw[:3, 3]
        on = np.asarray(ob.normals, np.float64) @ T_cw[:3, :3].T
        verts.append(ov)
        faces.append(np.asarray(ob.faces, np.int64) + off)
        norms.append(on.astype(np.float32))
        albs.append(np.asarray(ob.albedo, np.float32).reshape(-1, 3))
        emss.append(np.zeros((len(ov), 3), np.float32))
        uvs.append(np.asarray(ob.uv, np.float32) if ob.uv is not None else np.zeros((len(ov), 2), np.float32))
        tri_inst.append(np.full(len(ob.faces), nm + k, np.int32))
        metallic.append(float(ob.metallic))
        roughness.append(float(ob.roughness))
        specular.append(float(ob.specular))
        if ob.texture is not None and ob.uv is not None:
            tex_inst.append(nm + k)
            tex_img.append(np.asarray(ob.texture, np.float32))
        off += len(ov)
    V = np.concatenate(verts).astype(np.float32)
    F = np.concatenate(faces).astype(np.int32)
    E = np.concatenate(emss)
    A = np.concatenate(albs)
    ti = np.concatenate(tri_inst)
    p = V[F].astype(np.float64)
    tn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    tn /= np.maximum(np.linalg.norm(tn, axis=1, keepdims=True), 1e-30)
    tri_emits = E[F].max(axis=(1, 2)) > 0
    tri_scatters = ~tri_emits & (A[F].max(axis=(1, 2)) > 0)
    area = build_area_lights(V, F, E, tri_emits)
    return TraceScene(
        vertices=V, faces=F, normals=np.concatenate(norms).astype(np.float32), tri_inst=ti, albedo=A, emission=E,
        uv=np.concatenate(uvs), metallic=np.asarray(metallic, np.float32),
        roughness=np.asarray(roughness, np.float32), specular=np.asarray(specular, np.float32),
        textures=Textures(tuple(tex_inst), tuple(tex_img)), area_lights=area,
        point_lights=PointLights(position=np.zeros((0, 3)), intensity=np.zeros((0, 3))),
        env_radiance=np.zeros(3, np.float32), num_room_tris=len(mesh.faces),
        scale=float(np.max(V.max(0) - V.min(0))), intersector=EmbreeIntersector(V, F),
        tri_normal=tn.astype(np.float32), tri_emits=tri_emits, tri_scatters=tri_scatters)


def _view_rng(seed: int, T_c2w: np.ndarray, K: np.ndarray, width: int, height: int) -> np.random.Generator:
    """Generator of one view: named by the seed and the camera's exact numbers."""
    from pipeline.seeding import item_rng

    h = hashlib.sha256()
    for a in (np.asarray(T_c2w, np.float64), np.asarray(K, np.float64), np.array([width, height], np.int64)):
        h.update(np.ascontiguousarray(a).tobytes())
    return item_rng(int(seed), "synthscan", "traced", h.hexdigest()[:32])


def _denoise(ff, method: str) -> np.ndarray:
    """Radiance of a :class:`~pipeline.trace.fullframe.FullFrame`, denoised by ``method``.

    "none": as traced; "oidn": Intel Open Image Denoise (pyoidn) guided by the first-hit albedo and
    normal; "bilateral": the tracer's joint bilateral filter; "auto": OIDN when pyoidn is installed,
    else none (so a machine without pyoidn still gives unbiased, if grainy, photos).
    """
    from pipeline.trace.denoise import denoise, oidn_available

    if method not in DENOISE_CHOICES:
        raise UserError(f"traced denoise {method!r}: choose one of {', '.join(DENOISE_CHOICES)}")
    if method == "auto":
        method = "oidn" if oidn_available() else "none"
    if method == "none":
        return ff.radiance
    n = ff.normal
    n = n / np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-6)
    mask = np.ones(ff.radiance.shape[:2], bool)
    return np.maximum(denoise(ff.radiance, ff.albedo, n, mask, method=method), 0.0).astype(np.float32)


class TracedPhotoRenderer:
    """Path-traced photos of the true room (global illumination, soft shadows); depth by the raster.

    Parameters
    ----------
    room : Room
    mesh : MeshData, the tessellated room (used for depth, by the raster backend)
    vertex_radiance : (V, 3) float32, the raster light map (depth renderer; the exposure is read from it
        when ``exposure`` is None)
    exposure : float or None, radiance-to-sensor scale (the scan's ``exposure``)
    seed : int or None; None derives a seed from the room (itself a function of the scan seed)
    spp : samples per pixel
    max_depth : scattering events per path
    denoise : one of :data:`DENOISE_CHOICES` (see :func:`_denoise`)
    """

    def __init__(self, room: Room, mesh: MeshData, vertex_radiance: np.ndarray, *, exposure: float | None = None,
                 seed: int | None = None, spp: int = TRACED_SPP, max_depth: int = TRACED_MAX_DEPTH,
                 denoise: str = TRACED_DENOISE) -> None:
        from pipeline.trace.fullframe import FullFrameSettings

        if int(spp) < 1:
            raise UserError(f"traced photos: spp {spp!r} must be >= 1")
        self._exposure = float(exposure_from_radiance(room, mesh, vertex_radiance) if exposure is None else exposure)
        if seed is None:
            d = hashlib.sha256(np.asarray(room.size, np.float64).tobytes()
                               + np.asarray(room.quad_origin, np.float64).tobytes()).digest()
            seed = int.from_bytes(d[:4], "little")
        self._seed = int(seed)
        self._scene = room_trace_scene(room, self._exposure)
        self._settings = FullFrameSettings(spp=int(spp), max_depth=int(max_depth))
        if denoise not in DENOISE_CHOICES:
            raise UserError(f"traced photos: denoise {denoise!r}; choose one of {', '.join(DENOISE_CHOICES)}")
        self._denoise = denoise
        from pipeline.render_gl import MeshRasterizer

        self._depth = MeshRasterizer(znear=ZNEAR, zfar=ZFAR)
        self._depth.add_mesh("room", mesh.vertices, mesh.faces)

    @property
    def exposure(self) -> float:
        return self._exposure

    def render_color(self, cam: Camera) -> np.ndarray:
        from pipeline.trace.fullframe import render_full_frame

        rng = _view_rng(self._seed, cam.T_c2w, cam.K, cam.width, cam.height)
        return _denoise(render_full_frame(self._scene, cam, self._settings, rng), self._denoise)

    def render_depth(self, cam: Camera) -> np.ndarray:
        return self._depth.render_depth(cam.K, cam.T_c2w, cam.width, cam.height, [("room", np.eye(4))])

    def close(self) -> None:
        self._depth.release()


@dataclass(frozen=True)
class TracedView:
    """One path-traced view of a room (see :func:`render_traced_view`)."""

    radiance: np.ndarray         # (H, W, 3) float32 linear, exposure units (1.0 = sensor white)
    object_coverage: np.ndarray  # (H, W) float32 in [0, 1], share of samples whose first hit is an extra object
    albedo: np.ndarray           # (H, W, 3) float32 mean first-hit base colour (0 on emitters and misses)
    rays: int


@dataclass(frozen=True)
class TracedRoom:
    """What a generated scan needs to render more traced views of its room (:func:`traced_room_from_scan`)."""

    room: Room
    exposure: float
    T_world_from_canonical: np.ndarray   # (4, 4) float64: poses in the scan's files are in this world frame
    seed: int


def traced_room_from_scan(scan_dir: str | Path) -> TracedRoom:
    """Rebuild the true room of a scan written by ``make_scan`` (from its seed) with its exposure and frame.

    Raises :class:`~pipeline.errors.InputError` naming the file when ``ground_truth/scan.json`` is
    missing or was not written by the generator.
    """
    from pipeline.errors import InputError
    from pipeline.io import read_json
    from pipeline.seeding import item_rng
    from pipeline.synthscan.room import make_room

    path = Path(scan_dir) / "ground_truth" / "scan.json"
    try:
        doc = read_json(path)
        seed, exposure, T = int(doc["seed"]), float(doc["exposure"]), np.asarray(doc["T_world_from_canonical"], float)
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"{path}: cannot read the scan's ground truth ({e}); give a folder written by "
                         f"`scansynth make-scan`") from e
    return TracedRoom(room=make_room(item_rng(seed, "synthscan", "room")), exposure=exposure,
                      T_world_from_canonical=T, seed=seed)


def render_traced_view(room: Room, T_c2w: np.ndarray, K: np.ndarray, width: int, height: int, *, exposure: float,
                       extra_meshes: list[ObjectInstance] | tuple = (), spp: int = 32, seed: int = 0,
                       max_depth: int = TRACED_MAX_DEPTH, T_world_from_canonical: np.ndarray | None = None,
                       denoise: str = "none", scene: TraceScene | None = None) -> TracedView:
    """Path-trace the room, optionally with objects inserted, with the traced photo mode's renderer and lights.

    With ``extra_meshes`` empty this is the traced photo (before sensor noise) of the same view and
    seed at the same spp; with objects it is the "objects really in the room" ground truth of the
    compositor benchmark. Same ``seed`` and inputs, same bytes.

    Parameters
    ----------
    room : Room (e.g. ``traced_room_from_scan(dir).room``)
    T_c2w : (4, 4) float camera-to-world, metres, OpenCV axes, in the frame of ``T_world_from_canonical``
    K : (3, 3) float intrinsics (pixel centres at integers)
    width, height : image size, pixels
    exposure : radiance-to-sensor scale (``scan.json["exposure"]``)
    extra_meshes : :class:`pipeline.trace.scene.ObjectInstance` list in the same world frame (make them
        from library models and poses with :func:`pipeline.trace.scene.instance_from_model`)
    spp : samples per pixel
    seed : noise seed; the same seed with and without objects gives correlated noise (paths that never
        meet an object keep their exact values), so differences are the objects' effect, not noise
    denoise : one of :data:`DENOISE_CHOICES`; "none" (default) keeps the estimate unbiased
    T_world_from_canonical : (4, 4) the scan's world frame (``scan.json``); None = the room's canonical frame
    scene : a scene from :func:`room_trace_scene` to reuse across views (then ``extra_meshes``,
        ``exposure`` and ``T_world_from_canonical`` are ignored, and poses are in the canonical frame)

    Returns
    -------
    TracedView
    """
    from pipeline.trace.fullframe import FullFrameSettings, render_full_frame

    if int(spp) < 1:
        raise UserError(f"render_traced_view: spp {spp!r} must be >= 1")
    T = np.asarray(T_c2w, np.float64)
    if scene is None:
        scene = room_trace_scene(room, exposure, list(extra_meshes), T_world_from_canonical=T_world_from_canonical)
        if T_world_from_canonical is not None:
            T = np.linalg.inv(np.asarray(T_world_from_canonical, np.float64)) @ T
    settings = FullFrameSettings(spp=int(spp), max_depth=int(max_depth))
    ff = render_full_frame(scene, Camera(K, T, width, height), settings, _view_rng(seed, T, K, width, height),
                           cover_from=len(room.materials))
    return TracedView(radiance=_denoise(ff, denoise), object_coverage=ff.coverage, albedo=ff.albedo,
                      rays=ff.rays)


def make_photo_renderer(mode: str, room: Room, mesh: MeshData, vertex_radiance: np.ndarray, *,
                        exposure: float | None = None, seed: int | None = None,
                        spp: int = TRACED_SPP, denoise: str = TRACED_DENOISE) -> PhotoRenderer:
    """The photo renderer for ``mode`` (one of :data:`PHOTO_MODES`).

    ``exposure``, ``seed``, ``spp`` and ``denoise`` concern the traced mode only (see :class:`TracedPhotoRenderer`).
    """
    if mode == "raster":
        return RasterPhotoRenderer(room, mesh, vertex_radiance)
    if mode == "traced":
        return TracedPhotoRenderer(room, mesh, vertex_radiance, exposure=exposure, seed=seed, spp=spp,
                                   denoise=denoise)
    raise UserError(f"unknown photo mode {mode!r}; choose one of {', '.join(PHOTO_MODES)}")
