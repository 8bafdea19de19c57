"""The scene the tracer sees: room + placed objects as one triangle soup with per-vertex attributes.

Triangles ``[0, num_room_tris)`` are the room, the rest the object instances in placement order.
``tri_inst`` is 0 for the room and ``k + 1`` for instance ``k`` (the raster label convention).
Surfaces have a linear base colour (albedo) and a linear emitted radiance per vertex; in the "scan"
lighting mode the room emits its own colours and reflects nothing, in the "published" mode it emits
nothing and reflects its colours diffusely; in the "fit" mode it emits the fitted radiance. Objects never emit.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from pipeline.color import srgb_to_linear
from pipeline.trace.intersect import EmbreeIntersector, Intersector
from pipeline.trace.lights import (AreaLights, PointLights, build_area_lights, detect_bright_triangles,
                                   env_lookup, mean_radiance, published_lights)
from pipeline.types import ObjectModel

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Textures:
    """Base-colour textures of textured instances."""

    inst: tuple[int, ...]                 # instance numbers (tri_inst values) that use a texture
    images: tuple[np.ndarray, ...]        # (H, W, 3) float32 linear RGB, one per entry of ``inst``


@dataclass(frozen=True)
class TraceScene:
    """Geometry, materials and lights of one frame's scene, in the world frame (metres)."""

    vertices: np.ndarray      # (V, 3) float32, world
    faces: np.ndarray         # (T, 3) int32
    normals: np.ndarray       # (V, 3) float32 unit vertex normals, world
    tri_inst: np.ndarray      # (T,) int32, 0 = room, k + 1 = object instance k
    albedo: np.ndarray        # (V, 3) float32 linear base colour
    emission: np.ndarray      # (V, 3) float32 linear radiance
    uv: np.ndarray            # (V, 2) float32 texture coordinates (OpenGL, v up); 0 where untextured
    metallic: np.ndarray      # (N + 1,) float32 per instance (index 0 = room)
    roughness: np.ndarray     # (N + 1,) float32 perceptual roughness per instance
    specular: np.ndarray      # (N + 1,) float32 per instance: 1 = the principled dielectric, 0 = Lambert (bsdf.py)
    textures: Textures
    area_lights: AreaLights   # emitters sampled explicitly (NEE + MIS)
    point_lights: PointLights  # delta lights (published mode); may be empty
    env_radiance: np.ndarray  # (3,) float32, radiance of rays that escape the scene
    num_room_tris: int
    scale: float              # metres, a size of the scene (for ray offsets)
    intersector: Intersector
    tri_normal: np.ndarray    # (T, 3) float32 unit geometric normals (winding order)
    tri_emits: np.ndarray     # (T,) bool, some vertex of the triangle has non-zero emission
    tri_scatters: np.ndarray  # (T,) bool, paths continue from this triangle (objects; a reflecting room)
    env_map: np.ndarray | None = None  # (h, w, 3) float32 equirectangular radiance of escaping rays, or None
    up: np.ndarray | None = None       # (3,) world up vector, the env_map's axis
    spheres: tuple[np.ndarray, np.ndarray] | None = None  # instances' bounding spheres: centres (N, 3), radii (N,)
    # (T,) int8 or None: the side a room triangle sends its radiance to (+1 its front, the winding normal's
    # side; -1 its back; 0 both). A scan is a shell of sheets seen from one side: a ray meeting a table
    # top from below must not take the lit top's colour (fit lighting: the cameras' side vote)
    tri_side: np.ndarray | None = None

    def escape_radiance(self, dirs: np.ndarray) -> np.ndarray:
        """Radiance (N, 3) float32 seen by rays ``dirs (N, 3)`` that leave the scene."""
        if self.env_map is None:
            return np.broadcast_to(self.env_radiance, (len(dirs), 3))

        return env_lookup(self.env_map, np.array([0.0, 0.0, 1.0]) if self.up is None else self.up, dirs)

    @property
    def num_instances(self) -> int:
        return int(self.metallic.shape[0]) - 1


def _bounding_spheres(vertex_sets: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, 3) and radii (N,) of the spheres around each set's bounding box (0 for an empty set)."""
    c = np.zeros((len(vertex_sets), 3))
    r = np.zeros(len(vertex_sets))
    for k, v in enumerate(vertex_sets):
        if len(v):
            lo, hi = v.min(axis=0), v.max(axis=0)
            c[k] = 0.5 * (lo + hi)
            r[k] = 0.5 * np.linalg.norm(hi - lo)
    return c, r


def sphere_cover(points: np.ndarray, spheres: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(n, N) ``(r / d)^2`` of each bounding sphere ``spheres`` (centres (N, 3), radii (N,)) seen from
    ``points (n, 3)``: a bound on the cosine-weighted share of the hemisphere the sphere can cover (>= 1
    inside it). The shadow pass and the object shadows trace only where it reaches their ``min_effect``."""
    c, r = spheres
    d = np.linalg.norm(points[:, None, :] - c[None], axis=2)
    return (r[None] / np.maximum(d, 1e-9)) ** 2


def instance_spheres(scene: TraceScene) -> tuple[np.ndarray, np.ndarray]:
    """Bounding spheres of the object instances: centres (N, 3) and radii (N,) (bounding-box based)."""
    if scene.spheres is not None:   # kept by build_scene
        return scene.spheres
    return _bounding_spheres([scene.vertices[np.unique(scene.faces[scene.tri_inst == k + 1])]
                              for k in range(scene.num_instances)])


@dataclass(frozen=True)
class ObjectInstance:
    """One placed object: its mesh in world coordinates and its material."""

    vertices: np.ndarray          # (V, 3) float, world, metres
    faces: np.ndarray             # (T, 3) int
    normals: np.ndarray           # (V, 3) float unit normals, world
    albedo: np.ndarray            # (V, 3) float32 linear base colour
    uv: np.ndarray | None = None  # (V, 2) float32 or None
    texture: np.ndarray | None = None  # (H, W, 3) float32 linear, or None
    metallic: float = 0.0
    roughness: float = 0.5
    specular: float = 1.0


def instance_from_model(model: ObjectModel, R_m2w: np.ndarray, t_m2w: np.ndarray) -> ObjectInstance:
    """An :class:`ObjectInstance` from a library model and its pose.

    Parameters
    ----------
    model : the object model (vertex colours, UV texture or a plain base colour; metallic, roughness)
    R_m2w : (3, 3) float model-to-world rotation
    t_m2w : (3,) float model-to-world translation, metres
    """
    R = np.asarray(R_m2w, np.float64)
    v = np.asarray(model.vertices, np.float64) @ R.T + np.asarray(t_m2w, np.float64)
    n = np.asarray(model.normals, np.float64) @ R.T
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    nv = v.shape[0]
    tex = None
    uv = None
    if model.vertex_colors is not None:
        alb = srgb_to_linear(model.vertex_colors)
    else:
        alb = np.tile(np.asarray(model.base_color, np.float32), (nv, 1))
        if model.texture is not None and model.uv is not None:
            tex = srgb_to_linear(model.texture)
            uv = np.asarray(model.uv, np.float32)
            alb = np.ones((nv, 3), np.float32)
    return ObjectInstance(vertices=v, faces=np.asarray(model.faces), normals=n, albedo=alb, uv=uv,
                          texture=tex, metallic=float(model.metallic), roughness=float(model.roughness))


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (V, 3) float32 (zero-area neighbourhoods get +z)."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(ln > 0, n / np.maximum(ln, 1e-300), np.array([0.0, 0.0, 1.0]))
    return n.astype(np.float32)


def boost_lights(room_radiance: np.ndarray, room_faces: np.ndarray, bright: np.ndarray,
                 light_vertices: np.ndarray | None, *, light_gain: float, radiance_scale: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The room's emission with its lights boosted (scan lighting), and which vertices are lights.

    Vertices of ``bright`` triangles (clipped mesh colours) and ``light_vertices`` (seen clipped in the
    photos; their radiance is sensor white x ``radiance_scale`` whatever the mesh colour) get
    ``light_gain`` times their radiance.

    Parameters
    ----------
    room_radiance : (V, 3) float32 linear radiance of the room's vertices
    room_faces : (T, 3) int
    bright : (T,) bool clipped triangles (:func:`~pipeline.trace.lights.detect_bright_triangles`)
    light_vertices : (V,) bool or None; ignored when ``light_gain <= 0``

    Returns
    -------
    emission : (V, 3) float32
    boosted : (V,) bool
    """
    E = np.array(room_radiance, np.float32).reshape(-1, 3)
    nrv = E.shape[0]
    boosted = np.zeros(nrv, bool)
    boosted[np.unique(np.asarray(room_faces)[np.asarray(bright, bool)])] = True
    if light_vertices is not None and light_gain > 0:
        lv = np.asarray(light_vertices, bool).reshape(-1)
        if lv.shape[0] != nrv:
            raise ValueError(f"light_vertices has {lv.shape[0]} entries, the room has {nrv} vertices")
        E[lv & ~boosted] = np.float32(radiance_scale)   # seen clipped: sensor white
        boosted |= lv
    E[boosted] *= np.float32(light_gain)
    return E, boosted


def build_scene(room_vertices: np.ndarray, room_faces: np.ndarray, room_colors: np.ndarray | None,
                objects: list[ObjectInstance], *, lighting: str = "scan", radiance_scale: float = 1.0,
                light_threshold: int = 250, light_gain: float = 4.0, env_radiance: np.ndarray | None = None,
                published_power: float = 1.0, up: np.ndarray | None = None,
                room_linear_radiance: np.ndarray | None = None, light_vertices: np.ndarray | None = None,
                env_map: np.ndarray | None = None, room_lights=None) -> TraceScene:
    """Assemble a :class:`TraceScene` and its Embree intersector.

    Parameters
    ----------
    room_vertices, room_faces : (V, 3) float metres, (T, 3) int; may be empty
    room_colors : (V, 3) uint8 sRGB vertex colours of the room, or None (grey 0.5)
    objects : placed objects, instance ``k`` gets ``tri_inst = k + 1``
    lighting : "scan" (room emits its colours), "fit" (room emits the radiance of ``room_lights``, the
        recovered emitters sampled as lights) or "published" (four point lights, room diffuse)
    radiance_scale : multiplies the room's linear colours to give radiance
    light_threshold, light_gain : clipped-colour detection (0..255) and the radiance gain of the lights
        it finds; ``light_gain <= 0`` disables detection
    env_radiance : (3,) radiance of escaping rays; None = the room's mean radiance (scan mode) or 0
    up : (3,) unit up vector of the world (published lights); None = +z
    room_linear_radiance : (V, 3) float linear radiance given directly (tests, reference scenes);
        replaces the colour conversion and disables clipped-light detection
    light_vertices : (V,) bool room vertices found clipped in the photos
        (:func:`pipeline.trace.photolights.photo_lights`): lights like clipped vertex colours (linear
        white x ``radiance_scale`` x ``light_gain``), scan lighting only, ignored when ``light_gain <= 0``
    env_map : (h, w, 3) float32 equirectangular radiance of escaping rays about ``up``
        (:func:`pipeline.trace.lights.env_lookup`); replaces ``env_radiance`` for the object tracer
        and the shadow pass (scan lighting only)
    room_lights : :class:`~pipeline.trace.lightfit.RoomLights` (fit lighting: replaces the room mesh,
        its colours and the light detection by the closed, fitted room)
    """
    if lighting == "fit":
        if room_lights is None:
            raise ValueError("lighting 'fit' needs room_lights (pipeline.trace.lightfit.fit_room_lights)")
        room_vertices, room_faces = room_lights.vertices, room_lights.faces
        room_linear_radiance = room_lights.radiance
    rv = np.asarray(room_vertices, np.float64).reshape(-1, 3)
    rf = np.asarray(room_faces, np.int64).reshape(-1, 3)
    nrv, nrt = rv.shape[0], rf.shape[0]
    emits = lighting in ("scan", "fit")
    room_lin, bright = _room_linear(rv, rf, room_colors, room_linear_radiance, radiance_scale, light_threshold,
                                    light_gain)
    soup = _stack(rv, rf, room_lin, emits, objects)
    V, F = soup.vertices, soup.faces
    E = soup.emission.copy()
    boosted = np.zeros(nrv, bool)
    if lighting == "scan":
        E[:nrv], boosted = boost_lights(E[:nrv], rf, bright, None if room_linear_radiance is not None else light_vertices,
                                        light_gain=light_gain, radiance_scale=radiance_scale)
    light_mask = np.zeros(len(F), bool)
    if lighting == "fit":
        light_mask[:nrt] = np.asarray(room_lights.light_tri, bool)
    if boosted.any():
        # every triangle touching a boosted vertex carries boosted emission: sample them all explicitly
        light_mask[:nrt] = boosted[rf].any(axis=1)
    area = build_area_lights(V, F, E, light_mask)
    if lighting == "published" and nrv:
        pts = published_lights(rv, np.array([0.0, 0.0, 1.0]) if up is None else up, power=published_power)
    else:
        pts = PointLights(position=np.zeros((0, 3)), intensity=np.zeros((0, 3)))
    if env_radiance is None:
        env = mean_radiance(rv, rf, room_lin) if emits else np.zeros(3, np.float32)
    else:
        env = np.asarray(env_radiance, np.float32).reshape(3)
    ext = V.max(axis=0) - V.min(axis=0) if len(V) else np.ones(3)
    tri_inst_all = soup.tri_inst
    alb_all = soup.albedo
    p = V[F]
    tn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    tn /= np.maximum(np.linalg.norm(tn, axis=1, keepdims=True), 1e-30)
    tri_emits = (E[F].max(axis=(1, 2)) > 0) if len(F) else np.zeros(0, bool)
    tri_scatters = (tri_inst_all >= 1) | ((alb_all[F].max(axis=(1, 2)) > 0) if len(F) else np.zeros(0, bool))
    tri_side = _seen_side(room_lights, len(F)) if lighting == "fit" else None
    log.debug("trace scene: %d triangles (%d room), %d area lights, %d point lights",
              len(F), nrt, area.count, pts.count)
    return TraceScene(vertices=V, faces=F, normals=soup.normals,
                      tri_inst=tri_inst_all, albedo=alb_all.astype(np.float32),
                      emission=E, uv=soup.uv, metallic=soup.metallic,
                      roughness=soup.roughness, specular=soup.specular,
                      textures=soup.textures, area_lights=area, point_lights=pts,
                      env_radiance=env, num_room_tris=nrt, scale=float(np.max(ext)),
                      intersector=EmbreeIntersector(V, F), tri_normal=tn.astype(np.float32),
                      tri_emits=tri_emits, tri_scatters=tri_scatters,
                      env_map=(None if env_map is None or lighting != "scan" else np.asarray(env_map, np.float32)),
                      up=None if up is None else np.asarray(up, np.float64), spheres=soup.spheres, tri_side=tri_side)


def _room_linear(rv: np.ndarray, rf: np.ndarray, room_colors: np.ndarray | None,
                 room_linear_radiance: np.ndarray | None, radiance_scale: float, light_threshold: int,
                 light_gain: float) -> tuple[np.ndarray, np.ndarray]:
    """The room's linear colours (V, 3) float32 (radiance or albedo, by the lighting mode) and its
    triangles (T,) bool found clipped in the colours (lights to boost; none for given radiance)."""
    nrv, nrt = rv.shape[0], rf.shape[0]
    if room_linear_radiance is not None:
        room_lin = np.asarray(room_linear_radiance, np.float32).reshape(-1, 3)
        bright = np.zeros(nrt, bool)
    else:
        cols = (np.asarray(room_colors) if room_colors is not None
                else np.full((nrv, 3), 188, np.uint8))  # sRGB 188 = linear 0.5
        room_lin = srgb_to_linear(cols) * np.float32(radiance_scale)
        bright = (detect_bright_triangles(cols, rf, threshold=light_threshold) if light_gain > 0
                  else np.zeros(nrt, bool))
    return room_lin, bright


@dataclass(frozen=True)
class _Soup:
    """Room and object instances as one triangle soup (:func:`_stack`); fields as in :class:`TraceScene`."""

    vertices: np.ndarray      # (V, 3) float32
    faces: np.ndarray         # (T, 3) int32
    normals: np.ndarray       # (V, 3) float32
    tri_inst: np.ndarray      # (T,) int32
    albedo: np.ndarray        # (V, 3) linear base colour (float32 once cast)
    emission: np.ndarray      # (V, 3) float32, before the lights are boosted
    uv: np.ndarray            # (V, 2) float32
    metallic: np.ndarray      # (N + 1,) float32
    roughness: np.ndarray     # (N + 1,) float32
    specular: np.ndarray      # (N + 1,) float32
    textures: Textures
    spheres: tuple[np.ndarray, np.ndarray]  # instances' bounding spheres: centres (N, 3), radii (N,)


def _stack(rv: np.ndarray, rf: np.ndarray, room_lin: np.ndarray, emits: bool, objects: list[ObjectInstance]
           ) -> _Soup:
    """The room (emitting ``room_lin`` when ``emits``, else reflecting it) and the objects, in placement order,
    as one soup; instance ``k`` gets ``tri_inst = k + 1``."""
    nrv, nrt = rv.shape[0], rf.shape[0]
    verts = [rv]
    faces = [rf]
    norms = [vertex_normals(rv, rf) if nrt else np.zeros((nrv, 3), np.float32)]
    tri_inst = [np.zeros(nrt, np.int32)]
    emis = [room_lin.copy() if emits else np.zeros((nrv, 3), np.float32)]
    albedo = [np.zeros((nrv, 3), np.float32) if emits else np.clip(room_lin, 0, 1)]
    uvs = [np.zeros((nrv, 2), np.float32)]
    metallic, roughness, specular = [0.0], [1.0], [0.0]
    tex_inst, tex_img = [], []
    off = nrv
    for k, ob in enumerate(objects):
        ov = np.asarray(ob.vertices, np.float64)
        verts.append(ov)
        faces.append(np.asarray(ob.faces, np.int64) + off)
        norms.append(np.asarray(ob.normals, np.float32))
        tri_inst.append(np.full(len(ob.faces), k + 1, np.int32))
        emis.append(np.zeros((len(ov), 3), np.float32))
        albedo.append(np.asarray(ob.albedo, np.float32))
        uvs.append(np.asarray(ob.uv, np.float32) if ob.uv is not None else np.zeros((len(ov), 2), np.float32))
        metallic.append(ob.metallic)
        roughness.append(ob.roughness)
        specular.append(ob.specular)
        if ob.texture is not None and ob.uv is not None:
            tex_inst.append(k + 1)
            tex_img.append(np.asarray(ob.texture, np.float32))
        off += len(ov)
    V = np.concatenate(verts).astype(np.float32)
    F = np.concatenate(faces).astype(np.int32)
    # the instances' bounding spheres, once per scene: the shadow pass and the object tracer ask every frame
    ends = np.cumsum([len(v) for v in verts])
    spheres = _bounding_spheres([V[a:b] for a, b in zip(ends[:-1], ends[1:])])
    return _Soup(vertices=V, faces=F, normals=np.concatenate(norms).astype(np.float32),
                 tri_inst=np.concatenate(tri_inst), albedo=np.concatenate(albedo),
                 emission=np.concatenate(emis).astype(np.float32), uv=np.concatenate(uvs),
                 metallic=np.asarray(metallic, np.float32), roughness=np.asarray(roughness, np.float32),
                 specular=np.asarray(specular, np.float32), textures=Textures(tuple(tex_inst), tuple(tex_img)),
                 spheres=spheres)


def _seen_side(room_lights, n_tris: int) -> np.ndarray | None:
    """(T,) int8 side each triangle sends light to in fit lighting (see ``TraceScene.tri_side``), or None
    when the fit gives no side.

    The scan mesh's triangles send light to the side the cameras saw (as in the fit's gathers); the
    sampled lights (clipped regions, lamps) and the closing box stay two-sided, as the lights are
    sampled both ways (next-event estimation and a hit must agree on what a light sends).
    """
    if int(room_lights.summary.get("seen_side", 0)) == 0:
        return None
    tri_side = np.zeros(n_tris, np.int8)
    nm = int(room_lights.num_mesh_tris)
    tri_side[:nm] = int(room_lights.summary["seen_side"])
    tri_side[:nm][np.asarray(room_lights.light_tri, bool)[:nm]] = 0
    return tri_side
