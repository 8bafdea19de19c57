"""Light sources found in the scan's photos rather than in the room mesh's colours.

The room mesh's vertex colours are fused from many photos (and, for a simplified mesh, averaged over
large triangles), so a lamp or a window that every photo shows clipped at sensor white often ends up
in the mesh as an ordinary, unclipped colour, or not at all: glass gives the depth sensor nothing, so
a real scan has a hole where the window is, or the wall behind it. The photos themselves are the
measurement. :func:`photo_lights` casts the rays of a strided pixel grid of some of the scan's frames
against the room mesh and

- votes, per mesh vertex, how often the photos see it clipped (every channel ``>= threshold``): a
  vertex seen clipped in at least ``min_share`` of its observations is a light (the trace stage then
  treats it like a clipped vertex colour: linear 1 times ``trace.light_gain``, sampled explicitly);
- collects the photo's linear colour of rays that leave the mesh (holes, open doors, windows without
  geometry) into an equirectangular environment map of the world directions they were seen in; the
  tracer uses it for its own rays escaping through those holes instead of one constant radiance.
  Clipped pixels there count ``light_gain`` times, as clipped mesh colours do.

Only the photos' colours and the poses are used: it works the same on a real scan and on a synthetic
one. Cost: one Embree ray per grid pixel per frame used (``frames`` frames, every ``stride``-th pixel).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from pipeline.color import LUMINANCE, exposure_ratio, srgb_to_linear
from pipeline.trace.lights import ENV_H, ENV_W, env_bin

log = logging.getLogger(__name__)

GRID_W = 80             # photo pixels cast per row by :func:`scan_lighting` (stride = width / GRID_W)


@dataclass(frozen=True)
class PhotoLights:
    """What :func:`photo_lights` found."""

    light_vertices: np.ndarray   # (V,) bool, room vertices the photos see clipped
    seen: np.ndarray             # (V,) int32, photo observations per vertex
    clipped: np.ndarray          # (V,) int32, clipped observations per vertex
    env: np.ndarray              # (ENV_H, ENV_W, 3) float32 linear radiance of escaping directions (x gain for clipped)
    env_count: np.ndarray        # (ENV_H, ENV_W) int32, photo rays per bin (0 = no observation)
    frames_used: int
    points: np.ndarray           # (S, 3) float32 room points the photos saw unclipped (energy balance)
    normals: np.ndarray          # (S, 3) float32 their normals, facing the camera that saw them
    radiance: np.ndarray         # (S,) float32 their linear luminance in the photo


def photo_lights(vertices: np.ndarray, faces: np.ndarray, intersector, frames, *, up: np.ndarray,
                 threshold: int = 250, light_gain: float = 4.0, stride: int = 8, min_share: float = 0.5,
                 min_seen: int = 2, fallback: np.ndarray | None = None) -> PhotoLights:
    """Vote clipped vertices and build the escaping-ray environment map from photos.

    Parameters
    ----------
    vertices, faces : (V, 3) float metres and (T, 3) int, the room mesh the intersector was built from
        (room triangles first; hits on later triangles are ignored)
    intersector : :class:`~pipeline.trace.intersect.Intersector` of the room (or room + objects)
    frames : iterable of ``(photo (H, W, 3) uint8 sRGB, K (3, 3), T_c2w (4, 4))``
    up : (3,) world up vector (environment map axis)
    threshold : a photo pixel is clipped when every channel is ``>= threshold``
    light_gain : radiance of a clipped environment pixel, times its linear colour
    stride : every ``stride``-th pixel in x and y is cast
    min_share, min_seen : a vertex is a light when it was seen at least ``min_seen`` times and clipped in
        at least ``min_share`` of them
    fallback : (3,) radiance of environment bins no photo saw; None = mean of the observed bins (0 if none)

    Returns
    -------
    PhotoLights
    """
    from pipeline.camera import Camera

    nv, nt = len(vertices), len(faces)
    f = np.asarray(faces, np.int64)
    seen = np.zeros(nv, np.int64)
    clipped = np.zeros(nv, np.int64)
    env_sum = np.zeros((ENV_H, ENV_W, 3), np.float64)
    env_n = np.zeros((ENV_H, ENV_W), np.int64)
    used = 0
    pts, nrm, lum = [], [], []
    V = np.asarray(vertices, np.float64)
    for photo, K, T in frames:
        photo = np.asarray(photo, np.uint8)
        h, w = photo.shape[:2]
        ys, xs = np.mgrid[stride // 2:h:stride, stride // 2:w:stride]
        pix = (ys * w + xs).ravel()
        cam = Camera(K=np.asarray(K, np.float64), T_c2w=np.asarray(T, np.float64), width=w, height=h)
        o, d = cam.rays(pix, np.full((pix.size, 2), 0.5, np.float32))
        hits = intersector.intersect(o, d)
        col = photo.reshape(-1, 3)[pix]
        clip = col.min(axis=1) >= threshold
        on_room = hits.hit & (hits.prim < nt)
        if on_room.any():
            tri = f[hits.prim[on_room]]
            np.add.at(seen, tri.ravel(), 1)
            np.add.at(clipped, tri[clip[on_room]].ravel(), 1)
            ok = np.flatnonzero(on_room & ~clip & (col.max(axis=1) < threshold))[::4]
            if ok.size:
                ft = f[hits.prim[ok]]
                n = np.cross(V[ft[:, 1]] - V[ft[:, 0]], V[ft[:, 2]] - V[ft[:, 0]])
                n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
                n *= -np.sign(np.sum(n * d[ok], axis=1, keepdims=True) + 1e-30)
                pts.append(o[ok] + hits.t[ok, None] * d[ok])
                nrm.append(n)
                lum.append(srgb_to_linear(col[ok]) @ LUMINANCE)
        esc = ~hits.hit
        if esc.any():
            lin = srgb_to_linear(col[esc]).astype(np.float64)
            lin[clip[esc]] *= light_gain
            r, c = env_bin(d[esc], up)
            np.add.at(env_sum, (r, c), lin)
            np.add.at(env_n, (r, c), 1)
        used += 1
    lightv = (seen >= min_seen) & (clipped >= min_share * np.maximum(seen, 1))
    have = env_n > 0
    env = np.zeros((ENV_H, ENV_W, 3), np.float32)
    env[have] = (env_sum[have] / env_n[have, None]).astype(np.float32)
    if fallback is None:
        fb = env[have].mean(axis=0) if have.any() else np.zeros(3, np.float32)
    else:
        fb = np.asarray(fallback, np.float32).reshape(3)
    env[~have] = fb
    log.debug("photo lights: %d frames, %d light vertices, %d environment bins observed", used,
              int(lightv.sum()), int(have.sum()))
    return PhotoLights(light_vertices=lightv, seen=seen.astype(np.int32), clipped=clipped.astype(np.int32),
                       env=env, env_count=env_n.astype(np.int32), frames_used=used,
                       points=(np.concatenate(pts) if pts else np.zeros((0, 3))).astype(np.float32),
                       normals=(np.concatenate(nrm) if nrm else np.zeros((0, 3))).astype(np.float32),
                       radiance=(np.concatenate(lum) if lum else np.zeros(0)).astype(np.float32))


def balance_unseen(scene, pl: PhotoLights, rng: np.random.Generator, *, albedo: float = 0.5, rays: int = 32,
                   max_points: int = 2000, min_unseen: float = 0.1) -> float | None:
    """Radiance of the directions no photo saw, from the energy balance of the room points the photos saw.

    A diffuse room point of albedo ``rho`` that the photo shows with radiance ``L`` receives the
    irradiance ``pi L / rho``. Part of it comes from the room mesh's emission and the observed
    environment bins (traced with cosine-weighted rays); the rest must come from where the scan saw
    nothing (ceiling lamps outside every photo, the unscanned top of the room). With ``rho`` the
    room's typical albedo (a grey-world prior), each point with at least ``min_unseen`` of its
    cosine-weighted hemisphere unseen gives ``x = (L / rho - L_known) / share_unseen``; the median over
    points is returned (>= 0; None when no point qualifies: nothing to balance).

    Parameters
    ----------
    scene : :class:`~pipeline.trace.scene.TraceScene` of the room (emission = the trace stage's lighting)
    pl : :class:`PhotoLights` (its ``points``, ``normals``, ``radiance``, ``env_count``, ``env``)
    rng : seeded generator
    albedo : typical diffuse albedo of the room's surfaces (linear)
    rays : hemisphere rays per point
    max_points : room points used at most
    min_unseen : least cosine-weighted share of unseen directions for a point to vote

    Returns
    -------
    float or None, linear radiance of unseen directions (the trace stage's units)
    """
    from pipeline.trace.intersect import offset_origins
    from pipeline.trace.sampling import cosine_hemisphere, to_world

    n_pts = len(pl.points)
    if n_pts == 0:
        return None
    sel = np.sort(rng.choice(n_pts, size=min(n_pts, max_points), replace=False))
    p, n, L = pl.points[sel], pl.normals[sel], pl.radiance[sel].astype(np.float64)
    m = len(sel)
    P = np.repeat(p, rays, axis=0)
    N = np.repeat(n, rays, axis=0)
    loc, _ = cosine_hemisphere(rng.random(m * rays, dtype=np.float32), rng.random(m * rays, dtype=np.float32))
    d = to_world(loc, N).astype(np.float32)
    org = offset_origins(P, N, d, 1e-3 * max(scene.scale, 1e-3))
    h = scene.intersector.intersect(org, d)
    known = np.zeros(m * rays)
    hit = h.hit
    if hit.any():
        fr = scene.faces[h.prim[hit]]
        a, b = h.u[hit][:, None], h.v[hit][:, None]
        E = scene.emission
        known[hit] = ((1 - a - b) * E[fr[:, 0]] + a * E[fr[:, 1]] + b * E[fr[:, 2]]) @ LUMINANCE
    unseen = np.zeros(m * rays, bool)
    miss = np.flatnonzero(~hit)
    if miss.size:
        up = np.array([0.0, 0.0, 1.0]) if scene.up is None else scene.up
        r, c = env_bin(d[miss], up)
        obs = pl.env_count[r, c] > 0
        known[miss[obs]] = pl.env[r[obs], c[obs]] @ LUMINANCE
        unseen[miss[~obs]] = True
    share = unseen.reshape(m, rays).mean(axis=1)
    lk = known.reshape(m, rays).mean(axis=1)
    ok = share >= min_unseen
    if not ok.any():
        return None
    x = (L[ok] / albedo - lk[ok]) / share[ok]
    return float(max(np.median(x), 0.0))


def scan_lighting(scan, room_vertices: np.ndarray, room_faces: np.ndarray, room_colors: np.ndarray | None,
                  cfg, seed: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The trace stage's photo-based lighting of a scan: ``(light_vertices (V,) bool, env_map)``.

    ``(None, None)`` when the scan has no colour frames or no room mesh (then the mesh colours and
    ``env_radiance`` light the objects, as before).

    Reads ``cfg.photo_frames`` frames spread evenly over the scan, runs :func:`photo_lights` on the room
    mesh with the stage's light settings on a grid of about :data:`GRID_W` x ``GRID_W * 3 / 4`` pixels
    per frame, then fills the environment bins no photo saw with
    :func:`balance_unseen` (``cfg.room_albedo > 0``) or with ``cfg.env_radiance`` / the room's mean
    radiance. Deterministic for a scan, a mesh, a config and a seed (not per item).

    Parameters
    ----------
    scan : :class:`~pipeline.types.Scan`
    room_vertices, room_faces, room_colors : the room mesh the stage traces
    cfg : :class:`~pipeline.config.TraceConfig`
    seed : the run seed
    """
    from pipeline.scanformats.common import read_color
    from pipeline.seeding import item_rng
    from pipeline.trace.lights import detect_bright_triangles
    from pipeline.trace.scene import boost_lights, build_scene

    room = build_scene(room_vertices, room_faces, room_colors, [], radiance_scale=cfg.radiance_scale,
                       light_threshold=cfg.light_threshold, light_gain=cfg.light_gain, up=scan.up_w)
    have = np.flatnonzero([bool(p) for p in scan.color_paths])
    if have.size == 0 or len(room_faces) == 0:
        log.info("photo lights of %s: no colour frames or no room mesh; mesh colours only", scan.name)
        return None, None
    idx = have[np.unique(np.linspace(0, have.size - 1, max(1, cfg.photo_frames)).round().astype(int))]
    frames = ((read_color(scan, int(i)), scan.K[i], scan.T_c2w[i]) for i in idx)
    scale = np.float32(cfg.radiance_scale)
    pl = photo_lights(room.vertices, room.faces, room.intersector, frames, up=scan.up_w,
                      threshold=cfg.light_threshold, light_gain=cfg.light_gain,
                      stride=max(1, round(scan.width / GRID_W)))
    env = pl.env * scale
    unseen = pl.env_count == 0
    if cfg.room_albedo > 0:
        # the room lit as the trace stage will light it (same boost as build_scene), without a second BVH
        cols = (np.asarray(room_colors) if room_colors is not None
                else np.full((len(room_vertices), 3), 188, np.uint8))
        bright = (detect_bright_triangles(cols, room_faces, threshold=cfg.light_threshold) if cfg.light_gain > 0
                  else np.zeros(len(room_faces), bool))
        E, _ = boost_lights(srgb_to_linear(cols) * scale, room_faces, bright, pl.light_vertices,
                            light_gain=cfg.light_gain, radiance_scale=cfg.radiance_scale)
        lit = dataclasses.replace(room, emission=E, env_map=env)
        pl_scaled = PhotoLights(light_vertices=pl.light_vertices, seen=pl.seen, clipped=pl.clipped, env=env,
                                env_count=pl.env_count, frames_used=pl.frames_used, points=pl.points,
                                normals=pl.normals, radiance=pl.radiance * scale)
        x = balance_unseen(lit, pl_scaled, item_rng(seed, "trace", "photo-lights", scan.name), albedo=cfg.room_albedo)
    else:
        x = None
    if x is not None:
        env[unseen] = np.float32(x)
    else:   # no energy balance (off, or no room point sees an unseen direction): the constant fallback
        env[unseen] = (room.env_radiance if cfg.env_radiance < 0 else np.float32(cfg.env_radiance))
    log.info("photo lights of %s: %d frames, %d light vertices (%d from the mesh colours), %d/%d environment bins "
             "seen, unseen radiance %.3f", scan.name, pl.frames_used, int(pl.light_vertices.sum()),
             int((np.asarray(room_colors).min(axis=1) >= cfg.light_threshold).sum()) if room_colors is not None else 0,
             int((~unseen).sum()), unseen.size, float(env[unseen].mean()) if unseen.any() else 0.0)
    return pl.light_vertices, env.astype(np.float32)


MIN_EXPOSURE_SAMPLES = 64        # room pixels needed to measure a frame's exposure
EXPOSURE_RANGE = (0.25, 4.0)     # a frame's measured exposure is clamped to this range


def frame_exposure(scene, cam, photo: np.ndarray, *, radiance_scale: float = 1.0, threshold: int = 250,
                   grid: int = GRID_W) -> float:
    """The photo's exposure relative to the room mesh's colours: 1 = the mesh's own exposure.

    A camera with automatic exposure takes each frame brighter or darker than the average the mesh
    colours were fused from; objects lit by the mesh must be scaled by the same factor to match the
    photo around them. Primary rays on a grid of about ``grid`` pixels per row hit the room; the factor
    is the median ratio of the photo's linear luminance to the mesh's (its emission / ``radiance_scale``)
    over room hits that are neither lights nor clipped nor near black in the photo.

    Parameters
    ----------
    scene : :class:`~pipeline.trace.scene.TraceScene` (room triangles have ``tri_inst == 0``)
    cam : :class:`~pipeline.camera.Camera` of the photo (its resolution)
    photo : (H, W, 3) uint8 sRGB
    radiance_scale : the trace stage's ``radiance_scale``
    threshold : clipped photo pixels (every channel >= this) are left out

    Returns
    -------
    float in :data:`EXPOSURE_RANGE`; 1.0 when fewer than :data:`MIN_EXPOSURE_SAMPLES` pixels qualify
    """

    photo = np.asarray(photo, np.uint8)
    h, w = photo.shape[:2]
    if (h, w) != (cam.height, cam.width) or scene.num_room_tris == 0:
        return 1.0
    stride = max(1, round(w / grid))
    ys, xs = np.mgrid[stride // 2:h:stride, stride // 2:w:stride]
    pix = (ys * w + xs).ravel()
    o, d = cam.rays(pix, np.full((pix.size, 2), 0.5, np.float32))
    hits = scene.intersector.intersect(o, d)
    prim = np.maximum(hits.prim, 0)
    room = hits.hit & (scene.tri_inst[prim] == 0) & (scene.area_lights.prob_of_tri[prim] == 0)
    col = photo.reshape(-1, 3)[pix]
    ok = room & (col.max(axis=1) < threshold)
    if ok.sum() < MIN_EXPOSURE_SAMPLES:
        return 1.0
    fr = scene.faces[prim[ok]]
    a, b = hits.u[ok][:, None], hits.v[ok][:, None]
    E = scene.emission
    mesh = ((1 - a - b) * E[fr[:, 0]] + a * E[fr[:, 1]] + b * E[fr[:, 2]]) @ LUMINANCE / np.float32(radiance_scale)
    ratio = exposure_ratio(srgb_to_linear(col[ok]) @ LUMINANCE, mesh, floor=0.02, min_samples=MIN_EXPOSURE_SAMPLES)
    return 1.0 if ratio is None else float(np.clip(ratio, *EXPOSURE_RANGE))
