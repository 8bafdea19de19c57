"""Shadow-ratio pass: how much light a room point loses (or gains) because the objects are there.

For a room pixel, the room point is where the pixel's centre ray meets the room. Cosine-weighted
hemisphere rays cast from it against the room alone give the light arriving without objects, ``E0``
(the room's emission, or the environment for escaping rays, plus the direct light of point lights in
the published mode). What the objects change is sampled separately, where it can be non-zero: inside
the cone of each nearby object's bounding sphere, rays are tested against the objects, and a ray
that meets an object before the room swaps the room's light behind it for the object's (its albedo
times ``E0``, a one-bounce estimate of the light the object sends on). Sampling the small cone instead
of the whole hemisphere makes this part far less noisy for the same number of rays. The ratio

    shadow_ratio = E_with_objects / E_without_objects

is 1 where the objects change nothing. It is traced only where it can differ from 1 by more than
``min_effect``: points whose distance ``d`` to an object's bounding sphere centre satisfies
``(r / d)^2 >= min_effect`` (``(r / d)^2`` bounds the cosine-weighted share of the hemisphere a sphere
of radius ``r`` can cover).

Resolution: away from the objects the ratio is traced on a ``stride`` grid and smoothed; within
:data:`CONTACT_BAND_PX` pixels of them, where an object meets the surface it rests on, every pixel is
traced (twice the rays) and smoothed over :data:`CONTACT_SMOOTH_PX`, so the dark contact line keeps its
strength (a wider kernel washes one-pixel contact lines out toward 1 where the truth is dark).
Smoothing is a normalised convolution over room samples only (object pixels are not samples: counted as
1 they would dilute the contact shadow), and ``E0``, which changes slowly,
is averaged over :data:`E0_SMOOTH_PX` before the ratio is formed, so its sampling noise does not scale
the objects' effect.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from pipeline.color import LUMINANCE_F64
from pipeline.trace.intersect import EmbreeIntersector, Intersector, offset_origins
from pipeline.trace.pbr import emission_at
from pipeline.camera import Camera
from pipeline.trace.sampling import cosine_hemisphere, to_world
from pipeline.trace.scene import TraceScene, instance_spheres, sphere_cover

log = logging.getLogger(__name__)

CONTACT_BAND_PX = 3       # pixels around the objects traced at full resolution (see :func:`shadow_ratio`)
CONTACT_SMOOTH_PX = 0.75  # Gaussian sigma (pixels) of the ratio in that band
E0_SMOOTH_PX = 4.0        # Gaussian sigma (pixels) of the light arriving without objects


def _room_radiance(scene: TraceScene, room_isect: Intersector, org: np.ndarray,
                   dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Radiance (R, 3) float64 that rays receive from the room (or the environment) and the hit distance.

    The area lights are left out (0): :func:`_direct_light` samples them explicitly."""
    hr = room_isect.intersect(org, dirs)
    L = np.array(scene.escape_radiance(dirs), np.float64)
    hit = hr.hit
    if hit.any():
        L[hit] = emission_at(scene, hr.prim[hit], hr.u[hit], hr.v[hit], dirs[hit])
        if scene.area_lights.count:
            hi = np.flatnonzero(hit)
            L[hi[scene.area_lights.prob_of_tri[hr.prim[hi]] > 0]] = 0.0
    return L, hr.t


def _direct_light(scene: TraceScene, room_isect: Intersector, obj_isect: Intersector, p: np.ndarray,
                  ng: np.ndarray, per: np.ndarray, rng: np.random.Generator, eps: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Light (luminance, as radiance from a white surface) that the area lights send to room points
    ``p`` without objects, and the part of it the objects block: ``(E0_direct, blocked)``, each (n,).

    ``per[i]`` points on the lights per room point (the caller gives them a quarter of its ray budget:
    stratified and smoothed like the rest, few suffice), stratified over the light selection; a shadow ray
    first against the room (does the light reach the point at all?), then against the objects. This
    gives the objects' shadow its direction and its edge (hard under a small light, soft under a large
    one) with the noise of a few explicit samples, not of hemisphere rays that rarely meet a small lamp.
    """
    from pipeline.trace.pbr import light_rays

    n = p.shape[0]
    pr = np.repeat(np.arange(n), per)
    m = per[pr]
    rank = np.arange(pr.size) - np.repeat(np.cumsum(per) - per, per)
    u0 = (rank + rng.random(pr.size)) / m                     # stratified light choice
    ok, org, wl32, tmax, c = light_rays(scene, p, ng, pr, m, u0, rng.random(pr.size), rng.random(pr.size), eps)
    e0 = np.zeros(n)
    blocked = np.zeros(n)
    if ok.size == 0:
        return e0, blocked
    free = ~room_isect.occluded(org, wl32, tmax)
    ok, org, wl32, tmax = ok[free], org[free], wl32[free], tmax[free]
    # as radiance from a white surface: E / pi, in luminance
    c = c[free] @ LUMINANCE_F64 / np.pi
    e0 = np.bincount(pr[ok], weights=c, minlength=n)
    if ok.size:
        hit_obj = obj_isect.occluded(org, wl32, tmax)
        blocked = np.bincount(pr[ok[hit_obj]], weights=c[hit_obj], minlength=n)
    return e0, blocked


def split_intersectors(scene: TraceScene, room: Intersector | None = None) -> tuple[Intersector, Intersector]:
    """Intersectors of the room alone and of the objects alone (triangle ids offset by the room's). ``room``:
    the room's, built for another scene of the same room (its triangles are the first ``num_room_tris``
    of every such scene, whatever objects follow)."""
    nr = scene.num_room_tris
    return (room if room is not None else EmbreeIntersector(scene.vertices, scene.faces[:nr]),
            EmbreeIntersector(scene.vertices, scene.faces[nr:]))


def shadow_ratio(scene: TraceScene, camera: Camera, labels: np.ndarray, rng: np.random.Generator, *,
                 samples: int = 32, min_effect: float = 0.02, stride: int = 1, smooth: float = 0.0,
                 eps: float = 1e-4, room_isect: Intersector | None = None,
                 obj_isect: Intersector | None = None, contact_px: int = CONTACT_BAND_PX) -> np.ndarray:
    """Shadow ratio per pixel, (H, W) float32; 1 on object pixels and wherever nothing changes.

    The steps: :func:`room_points` (the room points the objects can change), :func:`light_without_objects`
    (``E0``, and ``E1`` with the area lights' shadows), :func:`_object_cones` (what the objects swap in the
    cones of their bounding spheres), :func:`_point_lights`, then the smoothing
    (:func:`_smooth_unshadowed`, :func:`_smooth_ratio`) when ``stride > 1`` or ``smooth > 0``.

    Parameters
    ----------
    scene : the frame's scene (room + objects)
    camera : the frame's camera
    labels : (H, W) uint16 object labels (0 = room); labelled pixels are not room pixels
    samples : hemisphere rays per traced room point (and ``max(2, samples // 4)`` per nearby object)
    min_effect : smallest possible change worth tracing (see the module docstring)
    stride : away from the objects, trace one pixel in ``stride x stride`` (shadows are smooth there)
    smooth : Gaussian smoothing (sigma, in traced-grid pixels) of the ratio away from the objects; 0 = none
    contact_px : room pixels within this many pixels of an object are all traced, at full resolution and
        with ``2 * samples`` rays, and smoothed over :data:`CONTACT_SMOOTH_PX` only: the dark line where an
        object meets the surface it rests on is about a pixel wide
    room_isect, obj_isect : prebuilt intersectors of :func:`split_intersectors` (built when None)
    """
    H, W = camera.height, camera.width
    out = np.ones(H * W, np.float32)
    if scene.num_instances == 0 or scene.num_room_tris == 0:
        return out.reshape(H, W)
    if room_isect is None or obj_isect is None:
        room_isect, obj_isect = split_intersectors(scene)
    obj = np.asarray(labels) > 0
    grid = np.zeros((H, W), bool)
    grid[::stride, ::stride] = True
    contact = _dilate(obj, contact_px) & ~obj if stride > 1 or smooth > 0 else np.zeros((H, W), bool)
    pts = room_points(scene, camera, ~obj.ravel() & (grid | contact).ravel(), min_effect)
    pix = pts.pix
    n = pix.size
    if n == 0:
        return out.reshape(H, W)
    per = np.where(contact.ravel()[pix], 2 * samples, samples)              # rays per point
    E0, E1, rays = light_without_objects(scene, room_isect, obj_isect, pts, per, rng, eps)
    E1 = _object_cones(scene, room_isect, obj_isect, pts, per, E0, E1, rng, eps, min_effect)
    E0, E1 = _point_lights(scene, room_isect, obj_isect, pts, E0, E1, eps)
    if stride > 1 or smooth > 0:
        E0, E1 = _smooth_unshadowed(E0, E1, pix, H, W)
    ratio = np.where(E0 > 0, E1 / np.where(E0 > 0, E0, 1.0), 1.0)
    out[pix] = np.clip(ratio, 0.0, 2.0)
    log.debug("shadow ratio: %d room points traced, %d rays", n, rays)
    out = out.reshape(H, W)
    if stride == 1 and smooth <= 0:
        return out
    return _smooth_ratio(out, grid, obj, contact, stride, smooth)


@dataclass(frozen=True)
class RoomPoints:
    """The room points the shadow pass traces: where pixels' centre rays meet the room near an object."""

    pix: np.ndarray       # (n,) int64, flat pixel index
    p: np.ndarray         # (n, 3) float32, m, world point
    ng: np.ndarray        # (n, 3) float32, unit geometric normal facing the camera
    sin2: np.ndarray      # (n, N) float64, (r / d)^2 of each object's bounding sphere (:func:`sphere_cover`)
    centres: np.ndarray   # (N, 3) float64, m, the bounding spheres' centres


def room_points(scene: TraceScene, camera: Camera, candidates: np.ndarray, min_effect: float) -> RoomPoints:
    """The room points seen by the pixels ``candidates`` (H*W,) bool that some object's bounding sphere
    covers by at least ``min_effect`` (elsewhere the objects cannot change the light by as much).

    Only pixels whose ray passes within a sphere's reach (:func:`reach_mask`) are cast: a room point
    elsewhere on the frame is too far from every object whatever depth the ray meets it at."""
    pix = np.flatnonzero(candidates)
    o, d = camera.rays(pix, np.full((pix.size, 2), 0.5))
    c, r = instance_spheres(scene)
    if min_effect > 0:
        keep = reach_mask(o, d, c, r / np.sqrt(min_effect))
        pix, o, d = pix[keep], o[keep], d[keep]
    h = scene.intersector.intersect(o, d)
    room_hit = h.hit & (scene.tri_inst[np.maximum(h.prim, 0)] == 0)
    pix, d = pix[room_hit], d[room_hit]
    prim, u, v = h.prim[room_hit], h.u[room_hit], h.v[room_hit]
    f = scene.faces[prim]
    V = scene.vertices
    p0, p1, p2 = V[f[:, 0]], V[f[:, 1]], V[f[:, 2]]
    p = ((1 - u - v)[:, None] * p0 + u[:, None] * p1 + v[:, None] * p2).astype(np.float32)
    ng = np.cross(p1 - p0, p2 - p0)
    ng /= np.maximum(np.linalg.norm(ng, axis=1, keepdims=True), 1e-20)
    ng = np.where((np.einsum("ij,ij->i", ng, d) > 0)[:, None], -ng, ng).astype(np.float32)
    sin2 = sphere_cover(p, (c, r))                                          # (n, N)
    near = (sin2 >= min_effect).any(axis=1)
    pix, p, ng = pix[near], p[near], ng[near]
    sin2 = sin2[near]
    return RoomPoints(pix=pix, p=p, ng=ng, sin2=sin2, centres=c)


def reach_mask(o: np.ndarray, d: np.ndarray, centres: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(R,) bool: rays ``o + t d`` (``o``, unit ``d`` (R, 3), t >= 0) that pass within ``reach`` (N,) of some
    of ``centres`` (N, 3). Widened by 1 % + 1 mm, so that float32 rays and float64 distances never drop a
    ray whose room point :func:`sphere_cover` would keep."""
    keep = np.zeros(o.shape[0], bool)
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    for ck, rk in zip(np.asarray(centres, np.float64), np.asarray(reach, np.float64)):
        v = ck[None] - o64
        tc = np.maximum(np.einsum("ij,ij->i", v, d64), 0.0)
        dist2 = np.einsum("ij,ij->i", v, v) - tc * tc
        keep |= dist2 <= (1.01 * rk + 1e-3) ** 2
    return keep


def light_without_objects(scene: TraceScene, room_isect: Intersector, obj_isect: Intersector, pts: RoomPoints,
                          per: np.ndarray, rng: np.random.Generator, eps: float
                          ) -> tuple[np.ndarray, np.ndarray, int]:
    """``E0``, the light arriving at the room points without objects, and ``E1``, the same less the area
    lights' light the objects block: each (n,) float64 luminance, as radiance from a white surface.

    Cosine-weighted hemisphere rays against the room alone; the area lights, sampled explicitly
    (:func:`_direct_light`), take a quarter of the ``per`` (n,) rays per point. Returns
    ``(E0, E1, hemisphere rays)``.
    """
    p, ng = pts.p, pts.ng
    n = pts.pix.size
    # the area lights, sampled explicitly, take a quarter of the budget from the hemisphere rays, which
    # then see only the room's indirect light (smooth: fewer rays suffice)
    lper = np.maximum(2, per // 4) if scene.area_lights.count else np.zeros_like(per)
    hper = np.maximum(1, per - lper)
    pr = np.repeat(np.arange(n), hper)
    uu = rng.random((2, pr.size))
    dl, _ = cosine_hemisphere(uu[0], uu[1])
    dw = to_world(dl, ng[pr].astype(np.float64)).astype(np.float32)
    L0 = _room_radiance(scene, room_isect, offset_origins(p[pr], ng[pr], dw, eps), dw)[0] @ LUMINANCE_F64
    E0 = np.bincount(pr, weights=L0, minlength=n) / hper
    if scene.area_lights.count:   # the lights sampled explicitly (left out of the rays above)
        Ed, blocked = _direct_light(scene, room_isect, obj_isect, p.astype(np.float64), ng.astype(np.float64),
                                    lper, rng, eps)
        E0 = E0 + Ed
        E1 = E0 - blocked
    else:
        E1 = E0.copy()
    return E0, E1, pr.size


def _object_cones(scene: TraceScene, room_isect: Intersector, obj_isect: Intersector, pts: RoomPoints,
                  per: np.ndarray, E0: np.ndarray, E1: np.ndarray, rng: np.random.Generator, eps: float,
                  min_effect: float) -> np.ndarray:
    """``E1`` (n,) with what the objects change: rays sampled uniformly inside the cone of each nearby
    bounding sphere (low noise for a small solid angle); a ray that hits an object before the room swaps
    the room's light behind it for the object's (albedo x ``E0`` here); directions inside several cones
    are shared between them (weight 1 / number of cones). ``max(2, per // 4)`` rays per cone."""
    p, ng, sin2, c = pts.p, pts.ng, pts.sin2, pts.centres
    n = pts.pix.size
    E1 = E1.copy()
    cos_max = np.where(sin2 < 1, np.sqrt(np.maximum(0.0, 1 - sin2)), -1.0)  # inside a sphere: all directions
    axes = c[None] - p[:, None, :].astype(np.float64)
    axes /= np.maximum(np.linalg.norm(axes, axis=2, keepdims=True), 1e-12)
    cone = sin2 >= min_effect
    mper = np.maximum(2, per // 4)  # rays per cone: a small solid angle needs few
    for k in range(c.shape[0]):
        sel = np.flatnonzero(cone[:, k])
        if sel.size == 0:
            continue
        prk = np.repeat(sel, mper[sel])
        m = mper[prk]
        uu = rng.random((2, prk.size))
        cm = cos_max[prk, k]
        ct = 1 - uu[0] * (1 - cm)
        st = np.sqrt(np.maximum(0.0, 1 - ct * ct))
        ph = 2 * np.pi * uu[1]
        dl = np.stack([st * np.cos(ph), st * np.sin(ph), ct], axis=1)
        dw = to_world(dl, axes[prk, k])
        cosn = np.einsum("ij,ij->i", dw, ng[prk])
        ok = np.flatnonzero(cosn > 0)
        if ok.size == 0:
            continue
        prk, dw, cosn, cm, m = prk[ok], dw[ok].astype(np.float32), cosn[ok], cm[ok], m[ok]
        org = offset_origins(p[prk], ng[prk], dw, eps)
        ho = obj_isect.intersect(org, dw)
        b = np.flatnonzero(ho.hit)
        if b.size == 0:
            continue
        Lb, t_room = _room_radiance(scene, room_isect, org[b], dw[b])
        b_ok = t_room > ho.t[b]
        b, Lb = b[b_ok], Lb[b_ok] @ LUMINANCE_F64
        fo = scene.faces[ho.prim[b] + scene.num_room_tris]
        ua, va = ho.u[b][:, None], ho.v[b][:, None]
        alb = ((1 - ua - va) * scene.albedo[fo[:, 0]] + ua * scene.albedo[fo[:, 1]]
               + va * scene.albedo[fo[:, 2]]) @ LUMINANCE_F64
        inside = (np.einsum("ij,ikj->ik", dw[b].astype(np.float64), axes[prk[b]]) >= cos_max[prk[b]]) & cone[prk[b]]
        shared = np.maximum(inside.sum(axis=1), 1)
        pdf = 1.0 / (2 * np.pi * (1 - cm[b]))
        dE = (Lb - alb * E0[prk[b]]) * cosn[b] / np.pi / pdf / m[b] / shared
        E1 -= np.bincount(prk[b], weights=dE, minlength=n)
    return E1


def _point_lights(scene: TraceScene, room_isect: Intersector, obj_isect: Intersector, pts: RoomPoints,
                  E0: np.ndarray, E1: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """``(E0, E1)`` (n,) with the point lights' direct light added: to ``E0`` where the room does not
    block it, to ``E1`` where the objects do not block it either."""
    p, ng = pts.p, pts.ng
    E0, E1 = E0.copy(), E1.copy()
    pl = scene.point_lights
    for k in range(pl.count):
        dv = pl.position[k] - p
        dd = np.linalg.norm(dv, axis=1)
        wl = (dv / np.maximum(dd, 1e-12)[:, None]).astype(np.float32)
        cos = np.einsum("ij,ij->i", wl, ng)
        ok = np.flatnonzero(cos > 0)
        if ok.size == 0:
            continue
        org_l = offset_origins(p[ok], ng[ok], wl[ok], eps)
        tmax = (dd[ok] - 2 * eps).astype(np.float32)
        free = ~room_isect.occluded(org_l, wl[ok], tmax)
        ok = ok[free]
        org_l, tmax = org_l[free], tmax[free]
        e = (pl.intensity[k] @ LUMINANCE_F64) * cos[ok] / dd[ok] ** 2 / np.pi  # as radiance from a white surface
        E0[ok] += e
        E1[ok] += np.where(obj_isect.occluded(org_l, wl[ok], tmax), 0.0, e)
    return E0, E1


def _smooth_unshadowed(E0: np.ndarray, E1: np.ndarray, pix: np.ndarray, H: int, W: int
                       ) -> tuple[np.ndarray, np.ndarray]:
    """``(E0, E1)`` with ``E0`` averaged over neighbouring traced points (over :data:`E0_SMOOTH_PX`).

    The light arriving without objects changes slowly over the room: its sampling noise would otherwise
    scale the objects' effect; what the objects take away (``E0 - E1``) keeps its full resolution.
    """
    traced = np.zeros(H * W, bool)
    traced[pix] = True
    e0 = np.zeros(H * W)
    e0[pix] = E0
    E0s = _normalized_blur(e0.reshape(H, W), traced.reshape(H, W), E0_SMOOTH_PX).ravel()[pix]
    return E0s, E0s - (E0 - E1)


def _smooth_ratio(out: np.ndarray, grid: np.ndarray, obj: np.ndarray, contact: np.ndarray, stride: int,
                  smooth: float) -> np.ndarray:
    """The ratio (H, W) smoothed: wide away from the objects, under a pixel in the contact band; (H, W)
    float32, 1 on object pixels.

    A normalised convolution over room samples only (object pixels carry no sample, so the ratio beside an
    object is not pulled towards 1 by it).
    """
    far = _normalized_blur(out, grid & ~obj, max(smooth, 0.5) * stride)
    near = _normalized_blur(out, (grid | contact) & ~obj, CONTACT_SMOOTH_PX)
    res = np.where(contact, near, far)
    res[obj] = 1.0
    return res.astype(np.float32)


def _dilate(mask: np.ndarray, px: int) -> np.ndarray:
    """``mask`` grown by ``px`` pixels (square neighbourhood)."""
    import cv2

    if px <= 0:
        return mask.copy()
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * px + 1, 2 * px + 1), np.uint8)) > 0


def _normalized_blur(values: np.ndarray, samples: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian-weighted mean of ``values`` over the pixels in ``samples`` (H, W) bool, at every pixel
    (1 where no sample is within reach)."""
    from scipy import ndimage

    w = samples.astype(np.float64)
    num = ndimage.gaussian_filter(np.where(samples, values, 0.0).astype(np.float64), sigma, mode="nearest",
                                  truncate=3.0)
    den = ndimage.gaussian_filter(w, sigma, mode="nearest", truncate=3.0)
    return np.where(den > 1e-6, num / np.maximum(den, 1e-12), 1.0)
