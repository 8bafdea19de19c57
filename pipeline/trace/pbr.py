"""The wavefront path integrator (:func:`trace_paths`, used by this module's object tracer and by
:mod:`pipeline.trace.fullframe`), and the object tracer: primary rays, AO, PBR with NEE + MIS, adaptive spp.

Every step works on a batch of rays (structure of arrays) that carry the index of the pixel sample
they belong to (pbrt-v4's wavefront design, ``pixelIndex``); there is no Python loop over rays.

Per pass, each active pixel gets ``spp_batch`` jittered primary rays; the first bounce's random numbers
(jitter, light sample, BSDF sample) are stratified over a pixel's samples (:class:`StratifiedDraws`). A
primary ray that hits an object starts a path (and ``ao_samples`` AO rays); one that hits the room first,
or nothing, contributes 0 and lowers the pixel's coverage. Paths bounce between objects (and, in the
published mode, off the room) up to ``max_depth`` scattering events with Russian roulette from
``rr_depth`` on. After ``spp_min`` samples a pixel stops once the standard error of its mean luminance
is below ``noise_target`` times its mean (with a floor for dark pixels), or at ``spp``.

The room's radiance comes from photos taken without the objects. In the fit lighting, where the fit also
gives the room's albedo, an object path that meets the room near the objects sees it less the direct
light the objects block there (:func:`shadowed_room_radiance`, ``trace.object_shadows``), so an object's
underside is not lit by the bright table its own shadow darkens.

Output radiance is linear and premultiplied by coverage (a half-covered edge pixel holds half the
object's radiance), ready for ``out = pbr + (1 - coverage) * background``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from pipeline.camera import Camera
from pipeline.color import LUMINANCE
from pipeline.tolerances import TRACE_RAY_EPS_M
from pipeline.trace import bsdf
from pipeline.trace.intersect import Hits, offset_origins
from pipeline.trace.lights import sample_area_lights
from pipeline.trace.sampling import (cosine_hemisphere, frame_to_local, frame_to_world, local_frame,
                                     power_heuristic, to_world)
from pipeline.trace.scene import TraceScene, instance_spheres, sphere_cover

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RenderSettings:
    """Quality knobs of :func:`render` (the stage fills them from TraceConfig)."""

    spp: int = 16                 # samples per pixel, upper bound
    spp_min: int = 4              # samples before the adaptive stop may end a pixel
    spp_batch: int = 4            # samples per pixel per pass
    noise_target: float = 0.02    # stop when std error of the mean < this x mean luminance
    max_depth: int = 4            # scattering events per path
    rr_depth: int = 2             # Russian roulette from this scattering event on
    ao_samples: int = 1           # AO rays per primary object hit (0 = no AO pass)
    ao_distance: float = 0.3      # metres, AO occluders farther than this do not count
    ray_eps: float = TRACE_RAY_EPS_M  # metres, origin offset off surfaces
    stratified: bool = True       # first bounce from StratifiedDraws (False: independent draws, PathDraws)


@dataclass(frozen=True)
class FrameBuffers:
    """What :func:`render` returns; (H, W) image arrays, zero (ao: one) outside traced pixels."""

    pbr: np.ndarray        # (H, W, 3) float32 linear radiance, premultiplied by coverage
    ao: np.ndarray         # (H, W) float32 in [0, 1], mean over object-hit samples; 1 elsewhere
    coverage: np.ndarray   # (H, W) float32 in [0, 1], share of samples that hit an object first
    albedo: np.ndarray     # (H, W, 3) float32 linear base colour, premultiplied by coverage
    normal: np.ndarray     # (H, W, 3) float32 shading normal, camera frame, premultiplied by coverage
    spp: np.ndarray        # (H, W) int32 samples taken per pixel
    rays: int              # rays cast in total (all queries)


@dataclass(frozen=True)
class Surface:
    """Hit points of a batch of rays (structure of arrays)."""

    p: np.ndarray          # (R, 3) float32 position
    ng: np.ndarray         # (R, 3) float32 geometric normal, facing the incoming ray
    ns: np.ndarray         # (R, 3) float32 shading normal, same side as ng and the viewer
    inst: np.ndarray       # (R,) int32, 0 room, k + 1 object instance k
    prim: np.ndarray       # (R,) int32 triangle
    albedo: np.ndarray     # (R, 3) float32 linear base colour


def _unit(x: np.ndarray) -> np.ndarray:
    n = np.sqrt(np.einsum("ij,ij->i", x, x))
    return x / np.maximum(n, 1e-20)[:, None]


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def interact(scene: TraceScene, hits: Hits, dirs: np.ndarray) -> Surface:
    """Surface data at the hits of rays ``dirs (R, 3)``; every ray must have hit (emission aside)."""
    prim = hits.prim
    f = scene.faces[prim]
    u = hits.u[:, None]
    v = hits.v[:, None]
    w = 1.0 - u - v
    V = scene.vertices
    p0, p1, p2 = V[f[:, 0]], V[f[:, 1]], V[f[:, 2]]
    p = w * p0 + u * p1 + v * p2
    ng = scene.tri_normal[prim]
    ng = np.where((_dot(ng, dirs) > 0)[:, None], -ng, ng)
    N = scene.normals
    ns = _unit(w * N[f[:, 0]] + u * N[f[:, 1]] + v * N[f[:, 2]])
    ns = np.where((_dot(ns, ng) < 0)[:, None], -ns, ns)
    # a shading normal that faces away from the viewer would make the BSDF zero: use the true one
    ns = np.where((_dot(ns, dirs) >= -1e-4)[:, None], ng, ns)
    A = scene.albedo
    alb = w * A[f[:, 0]] + u * A[f[:, 1]] + v * A[f[:, 2]]
    inst = scene.tri_inst[prim]
    for k, img in zip(scene.textures.inst, scene.textures.images):
        sel = np.flatnonzero(inst == k)
        if sel.size == 0:
            continue
        T = scene.uv
        fs = f[sel]
        uv = w[sel] * T[fs[:, 0]] + u[sel] * T[fs[:, 1]] + v[sel] * T[fs[:, 2]]
        h, wd = img.shape[:2]
        col = np.clip(((uv[:, 0] % 1.0) * wd).astype(np.int64), 0, wd - 1)
        row = np.clip(((1.0 - uv[:, 1] % 1.0) * h).astype(np.int64), 0, h - 1)
        alb[sel] = alb[sel] * img[row, col]
    return Surface(p=p, ng=ng, ns=ns, inst=inst, prim=prim, albedo=alb)


def emission_at(scene: TraceScene, prim: np.ndarray, u: np.ndarray, v: np.ndarray,
                dirs: np.ndarray | None = None) -> np.ndarray:
    """(R, 3) float32 emitted radiance at barycentric points of triangles ``prim``; with the rays' directions
    ``dirs``, 0 where a ray meets a room triangle on the side it sends nothing to (``scene.tri_side``)."""
    f = scene.faces[prim]
    E = scene.emission
    u = u[:, None]
    v = v[:, None]
    Le = (1 - u - v) * E[f[:, 0]] + u * E[f[:, 1]] + v * E[f[:, 2]]
    if dirs is not None and scene.tri_side is not None:
        away = scene.tri_side[prim] * _dot(scene.tri_normal[prim], dirs) > 0   # side 0: never away
        if away.any():
            Le[away] = 0
    return Le


def material(scene: TraceScene, s: Surface) -> bsdf.Material:
    """The BSDF parameters at surface points (room points: Lambert with their albedo)."""
    return bsdf.Material(base_color=s.albedo, metallic=scene.metallic[s.inst],
                         roughness=scene.roughness[s.inst], specular=scene.specular[s.inst])


def take(s: Surface, idx: np.ndarray) -> Surface:
    return Surface(*(getattr(s, k)[idx] for k in ("p", "ng", "ns", "inst", "prim", "albedo")))


class RayCounter:
    """Counts rays cast (for reports and the benchmark); a local object, not module state.

    Every ray that is traced counts once: camera rays, continuation rays, shadow rays towards area and
    point lights, AO rays (both renderers count the same way)."""

    def __init__(self) -> None:
        self.rays = 0


class PathDraws:
    """Random numbers drawn per live path, when and as many as needed (the object tracer)."""

    correlated = False

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng

    def start(self, active: np.ndarray, done: int, count: int) -> None:
        """A pass of the object tracer begins (see :meth:`StratifiedDraws.start`); nothing is drawn ahead."""

    def camera(self, n: int) -> np.ndarray:
        """(n, 2) float32 jitter of the camera rays in their pixels."""
        return self.rng.random((n, 2), dtype=np.float32)

    def begin(self, n: int) -> None:
        """Start of a bounce of ``n`` samples (nothing is drawn ahead)."""

    def nee(self, idx: np.ndarray) -> np.ndarray:
        return self.rng.random((3, idx.size))

    def bsdf(self, idx: np.ndarray) -> np.ndarray:
        return self.rng.random((3, idx.size), dtype=np.float32)

    def rr(self, idx: np.ndarray) -> np.ndarray:
        return self.rng.random(idx.size, dtype=np.float32)


def _sobol_2d(m: int) -> np.ndarray:
    """The first ``2**m`` points of the two-dimensional Sobol' sequence, (2**m, 2) float64: the van der Corput
    sequence in base 2 and its companion. Every aligned block of ``2**k`` consecutive points has one point in
    each of any ``2**k`` elementary boxes of equal area (a (0, 2)-sequence), so a pixel's first 4 or 8
    samples are stratified whatever the adaptive stop leaves it."""
    n = 1 << m
    k = np.arange(n, dtype=np.uint64)
    x = np.zeros(n, np.uint64)
    y = np.zeros(n, np.uint64)
    v = np.uint64(1) << np.uint64(31)     # direction numbers of the second dimension: v_j = v_{j-1} ^ (v_{j-1} >> 1)
    for j in range(m):
        bit = (k >> np.uint64(j)) & np.uint64(1)
        x ^= bit * (np.uint64(1) << np.uint64(31 - j))
        y ^= bit * v
        v ^= v >> np.uint64(1)
    return np.stack([x, y], axis=1).astype(np.float64) / float(1 << 32)


class StratifiedDraws(PathDraws):
    """The object tracer's draws: the first bounce's uniforms (the camera jitter, the light sample of
    next-event estimation and the BSDF sample) stratified over each pixel's samples, later bounces plain
    random numbers as in :class:`PathDraws`.

    Each group of dimensions (jitter 2D; light choice 1D, light point 2D; lobe choice 1D, direction 2D)
    takes a point of a (0, 2)-sequence (:func:`_sobol_2d`), shifted modulo 1 by a random offset per pixel
    and group (Cranley-Patterson rotation: every sample stays uniform, so the estimate stays unbiased). A
    pixel's samples come in passes of ``batch``; each pass takes the next block of ``batch`` points of the
    sequence (from a random first block per pixel and group), in a fresh random order per pixel and group.
    A block of 2**k consecutive points of the sequence is stratified (one point in each of any 2**k
    elementary boxes), so the samples of every pass cover the pixel, the lights and the hemisphere evenly
    instead of clumping, and the random orders pair the groups' points at random (pbrt-v4's padded Sobol'
    sampler, permuted within passes so that the adaptive stop after any pass keeps whole strata).
    """

    #: dimensions of each group, in draw order: camera jitter, light choice, light point, lobe, direction
    GROUPS = (2, 1, 2, 1, 2)

    def __init__(self, rng: np.random.Generator, pixels: int, max_samples: int, batch: int) -> None:
        super().__init__(rng)
        self.batch = max(1, int(batch))
        self.nblocks = max(1, -(-int(max_samples) // self.batch))
        self.table = _sobol_2d(max(1, int(np.ceil(np.log2(max(self.nblocks * self.batch, 2))))))
        # per pixel and group: the block the first pass takes (each later pass the next one, cyclically)
        self.offset = rng.integers(0, self.nblocks, size=(pixels, len(self.GROUPS)))
        self.shift = rng.random((pixels, sum(self.GROUPS)))
        self.first = np.zeros((sum(self.GROUPS), 0), np.float32)
        self.depth = 0

    def start(self, active: np.ndarray, done: int, count: int) -> None:
        """The next pass: samples ``done .. done + count - 1`` (``done`` a multiple of ``batch``, ``count <=
        batch``) of the pixels ``active (m,)`` (indices into the pixels traced), in the rows' order of
        ``np.repeat(active, count)``; computes the rows' first-bounce uniforms. Each pass draws a fresh
        order of the block's points per pixel and group (its first ``count`` when the pass is short)."""
        m, g = active.size, len(self.GROUPS)
        perm = np.argsort(self.rng.random((m, g, self.batch), dtype=np.float32), axis=2)[:, :, :count]
        cols, d = [], 0
        for gi, dim in enumerate(self.GROUPS):
            blk = (done // self.batch + self.offset[active, gi]) % self.nblocks
            k = (blk[:, None] * self.batch + perm[:, gi, :]).reshape(-1)
            shift = np.repeat(self.shift[active, d:d + dim], count, axis=0)
            cols.append((self.table[k, :dim] + shift) % 1.0)
            d += dim
        self.first = np.ascontiguousarray(np.concatenate(cols, axis=1).T.astype(np.float32))
        # float32 rounding may reach 1.0: keep every uniform in [0, 1)
        np.minimum(self.first, np.float32(1.0 - 2 ** -24), out=self.first)
        self.depth = -1

    def camera(self, n: int) -> np.ndarray:
        return np.ascontiguousarray(self.first[0:2].T)

    def begin(self, n: int) -> None:
        self.depth += 1

    def nee(self, idx: np.ndarray) -> np.ndarray:
        if self.depth == 0:
            return self.first[2:5, idx].astype(np.float64)
        return self.rng.random((3, idx.size))

    def bsdf(self, idx: np.ndarray) -> np.ndarray:
        if self.depth == 0:
            return self.first[5:8, idx]
        return self.rng.random((3, idx.size), dtype=np.float32)


class ChunkDraws(PathDraws):
    """Every uniform of a bounce drawn for the whole chunk and indexed by sample, whatever happens to the
    other samples: a path that meets none of a scene's changes keeps its exact value when objects are
    inserted (correlated sampling, the full-frame renderer)."""

    correlated = True

    def begin(self, n: int) -> None:
        self.U = self.rng.random((7, n), dtype=np.float32)

    def nee(self, idx: np.ndarray) -> np.ndarray:
        return self.U[0:3, idx]

    def bsdf(self, idx: np.ndarray) -> np.ndarray:
        return self.U[3:6, idx]

    def rr(self, idx: np.ndarray) -> np.ndarray:
        return self.U[6, idx]


@dataclass(frozen=True)
class PathOptions:
    """What differs between the object tracer and the full-frame renderer (see :func:`trace_paths`)."""

    max_depth: int
    rr_depth: int
    ray_eps: float = TRACE_RAY_EPS_M
    objects_only: bool = True     # paths start only where an object (tri_inst >= 1) is hit first
    one_sided: bool = False       # emitters light their front side only (else both sides)
    trace_last: bool = True       # the last scattering event's continuation is traced (emitters it hits count)
    ao_samples: int = 0           # AO rays per first hit
    ao_distance: float = 0.3      # metres
    cover_from: int = 1           # ``covered``: the first hit's tri_inst is at least this
    object_shadows: "ObjectShadows | None" = None   # the objects' shadows taken out of the room they see


def _emission(scene: TraceScene, prim: np.ndarray, u: np.ndarray, v: np.ndarray, dirs: np.ndarray,
              one_sided: bool) -> np.ndarray:
    """(R, 3) float32 emitted radiance towards rays ``dirs`` that hit ``prim``; 0 from an emitter's back
    side when ``one_sided``."""
    Le = emission_at(scene, prim, u, v, dirs)
    if not one_sided:
        return Le
    front = _dot(scene.tri_normal[prim], dirs) < 0
    return np.where(front[:, None], Le, np.float32(0)).astype(np.float32)


def _scatter(scene: TraceScene, s: Surface, wo: np.ndarray, beta: np.ndarray, draws: PathDraws, idx: np.ndarray,
             opts: PathOptions, counter: RayCounter) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Next-event estimation at surfaces ``s`` (the samples ``idx``) and a BSDF-sampled continuation.

    Returns
    -------
    L_direct : (R, 3) radiance reaching the path start through the explicit lights, already x beta
    wi : (R, 3) float32 sampled world directions
    weight : (R, 3) ``f cos / pdf`` (0 where the sample is invalid)
    pdf : (R,) solid-angle pdf of ``wi`` (for MIS on emitters hit next)
    """
    n = s.p.shape[0]
    eps = opts.ray_eps
    frame = local_frame(s.ns)
    wo_l = frame_to_local(wo, frame)
    lobes = bsdf.prepare(material(scene, s), wo_l[:, 2])
    L = np.zeros((n, 3), np.float32)
    if scene.area_lights.count and n:
        u = draws.nee(idx)
        Ld, rays = area_light_nee(scene, s, lobes, wo_l, frame, beta, u[0].astype(np.float64),
                                  u[1].astype(np.float64), u[2].astype(np.float64), eps, one_sided=opts.one_sided)
        L += Ld
        counter.rays += rays
    pl = scene.point_lights
    for k in range(pl.count):
        dvec = pl.position[k].astype(np.float32) - s.p
        dist = np.linalg.norm(dvec, axis=1)
        wl = dvec / np.maximum(dist, 1e-12)[:, None]
        fc, _ = bsdf.eval_pdf(lobes, wo_l, frame_to_local(wl, frame))
        vi = np.flatnonzero((_dot(wl, s.ng) > 0) & (fc.max(axis=1) > 0))
        if vi.size:
            org = offset_origins(s.p[vi], s.ng[vi], wl[vi], eps)
            occ = scene.intersector.occluded(org, wl[vi], dist[vi] - 2 * eps)
            counter.rays += vi.size
            vis = vi[~occ]
            L[vis] += beta[vis] * fc[vis] * (pl.intensity[k].astype(np.float32) / (dist[vis] ** 2)[:, None])
    u = draws.bsdf(idx)
    wi, weight, pdf = sample_continuation(lobes, wo_l, frame, s.ng, u[0], u[1], u[2])
    return L, wi, weight, pdf


def light_sample(scene: TraceScene, p: np.ndarray, u0: np.ndarray, u1: np.ndarray, u2: np.ndarray, *,
                 one_sided: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One point on the area lights per point ``p (R, 3)`` (chosen by power, then by area), seen from ``p``.

    Shared by next-event estimation (:func:`area_light_nee`) and the shadow pass's direct light. Works in
    ``p``'s precision.

    Returns
    -------
    wl : (R, 3) unit directions from ``p`` to the light points
    dist : (R,) distances
    Le : (R, 3) emitted radiance there
    cos_l : (R,) cosine at the light (``one_sided``: > 0 only on the emitting side; else absolute)
    pA : (R,) float64 pdf per unit light area
    """
    tri, b1, b2, pA = sample_area_lights(scene.area_lights, scene.vertices, scene.faces, u0, u1, u2)
    f = scene.faces[tri]
    V = scene.vertices
    q0, q1, q2 = V[f[:, 0]], V[f[:, 1]], V[f[:, 2]]
    b1 = b1.astype(p.dtype)[:, None]
    b2 = b2.astype(p.dtype)[:, None]
    b0 = 1 - b1 - b2
    lp = b0 * q0 + b1 * q1 + b2 * q2
    E = scene.emission
    Le = b0 * E[f[:, 0]] + b1 * E[f[:, 1]] + b2 * E[f[:, 2]]
    dvec = lp - p
    dist = np.linalg.norm(dvec, axis=1)
    wl = dvec / np.maximum(dist, 1e-12)[:, None]
    if one_sided:
        cos_l = -_dot(wl, scene.tri_normal[tri])          # > 0: the point sees the emitting side
    else:
        cos_l = np.abs(_dot(wl, _unit(np.cross(q1 - q0, q2 - q0))))
    return wl, dist, Le, cos_l, pA


def light_rays(scene: TraceScene, p: np.ndarray, ng: np.ndarray, pr: np.ndarray, m, u0: np.ndarray,
               u1: np.ndarray, u2: np.ndarray, eps: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Shadow rays from room points ``p[pr]`` (normals ``ng[pr]``, on the side the light comes from) to one
    point each on the area lights (:func:`light_sample`, both sides emitting, draws ``u0, u1, u2``), and
    what each would add to its point's irradiance if nothing blocked it, ``Le cos_p cos_l / (pA d^2 m)``
    (``m``: samples per point, scalar or per ray). Shared by the shadow pass's direct light and the object
    shadows; the callers choose which occluders to ask, in which order.

    Returns ``ok`` (indices into ``pr`` of the rays that can carry light), their origins, directions
    (float32), ``tmax`` and contributions (k, 3) float64."""
    wl, dist, Le, cos_l, pA = light_sample(scene, p[pr], u0, u1, u2, one_sided=False)
    cos_p = _dot(wl, ng[pr])
    ok = np.flatnonzero((cos_p > 0) & (cos_l > 1e-6) & (dist > 4 * eps))
    wl32 = wl[ok].astype(np.float32)
    org = offset_origins(p[pr[ok]].astype(np.float32), ng[pr[ok]].astype(np.float32), wl32, eps)
    tmax = (dist[ok] - 2 * eps).astype(np.float32)
    mk = np.broadcast_to(np.asarray(m, np.float64), pr.shape)[ok]
    c = Le[ok] * (cos_p[ok] * cos_l[ok] / (pA[ok] * dist[ok] ** 2 * mk))[:, None]
    return ok, org, wl32, tmax, c


def area_light_nee(scene: TraceScene, s: Surface, lobes, wo_l: np.ndarray, frame, beta: np.ndarray,
                   u0: np.ndarray, u1: np.ndarray, u2: np.ndarray, eps: float, *,
                   one_sided: bool) -> tuple[np.ndarray, int]:
    """Next-event estimation: one point on the area lights per surface point, MIS-weighted (power heuristic).

    Shared by the object tracer (``one_sided=False``: the scan's emitting triangles light both ways) and
    the full-frame integrator (``one_sided=True``: lamps emit from their front side only).

    Parameters
    ----------
    s : the R surface points; ``lobes``, ``wo_l``, ``frame``: their BSDF, outgoing direction and frame
    beta : (R, 3) path throughput
    u0, u1, u2 : (R,) float64 uniforms for the light sample
    eps : ray offset, metres

    Returns
    -------
    (R, 3) float32 direct radiance x beta, and the number of shadow rays cast.
    """
    n = s.p.shape[0]
    L = np.zeros((n, 3), np.float32)
    wl, dist, Le, cos_l, pA = light_sample(scene, s.p, u0, u1, u2, one_sided=one_sided)
    pdf_sa = pA * dist.astype(np.float64) ** 2 / np.maximum(cos_l, 1e-12)
    fc, pdf_b = bsdf.eval_pdf(lobes, wo_l, frame_to_local(wl, frame))
    ok = (_dot(wl, s.ng) > 0) & (cos_l > 1e-6) & (fc.max(axis=1) > 0)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return L, 0
    org = offset_origins(s.p[idx], s.ng[idx], wl[idx], eps)
    occ = scene.intersector.occluded(org, wl[idx], dist[idx] - 2 * eps)
    vis = idx[~occ]
    w = power_heuristic(pdf_sa[vis], pdf_b[vis])
    L[vis] += beta[vis] * fc[vis] * Le[vis] * (w / pdf_sa[vis]).astype(np.float32)[:, None]
    return L, int(idx.size)


def emission_mis_weight(scene: TraceScene, prim: np.ndarray, t: np.ndarray, wi: np.ndarray,
                        pdf_bsdf: np.ndarray) -> np.ndarray:
    """(R,) float32 MIS weight of emitters ``prim`` hit at distance ``t`` by BSDF-sampled rays ``wi``.

    Power heuristic against :func:`area_light_nee`'s pdf of sampling the same point (1 where the
    triangle cannot be sampled as a light).
    """
    al = scene.area_lights
    if not al.count:
        return np.ones(prim.size, np.float32)
    pt = al.prob_of_tri[prim]
    cos_l = np.abs(_dot(scene.tri_normal[prim], wi))
    pdf_l = pt * t.astype(np.float64) ** 2 / np.maximum(cos_l, 1e-12)
    return np.where(pt > 0, power_heuristic(pdf_bsdf, pdf_l), 1.0).astype(np.float32)


def sample_continuation(lobes, wo_l: np.ndarray, frame, ng: np.ndarray, u0: np.ndarray, u1: np.ndarray,
                        u2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample the next path direction from the BSDF.

    Returns ``wi`` (R, 3) float32 world directions, ``weight`` (R, 3) float32 = f cos / pdf (0 where the
    sample is invalid) and ``pdf`` (R,) solid-angle densities. ``u0..u2`` are (R,) uniforms in [0, 1).
    """
    wi_l, fc, pdf = bsdf.sample_prepared(lobes, wo_l, u0, u1, u2)
    wi = frame_to_world(wi_l, frame)
    # a direction above the shading normal but under the facet (interpolated normals on a coarse mesh)
    # is mirrored into the upper side rather than lost, so flat-shaded facets do not darken
    dn = _dot(wi, ng)
    wi = np.where((dn <= 0)[:, None], wi - (2 * dn)[:, None] * ng, wi)
    ok = (pdf > 0) & (wi_l[:, 2] > 0)
    weight = np.where(ok[:, None], fc / np.where(ok, pdf, 1)[:, None], 0).astype(np.float32)
    return wi.astype(np.float32), weight, pdf


def trace_paths(scene: TraceScene, camera: Camera, pixels: np.ndarray, draws: PathDraws, opts: PathOptions,
                counter: RayCounter) -> dict[str, np.ndarray]:
    """Trace one camera sample per entry of ``pixels (R,)`` (flat pixel indices; repeats allowed): the one
    bounce loop of both renderers (pbrt-v4's wavefront stages: camera rays, intersect, escaped rays,
    emitters hit, NEE shadow rays and BSDF continuation, Russian roulette).

    Returns a dict of per-sample arrays: ``L (R, 3)`` float64 radiance, ``covered (R,)`` bool (first hit
    has ``tri_inst >= opts.cover_from``), ``ao (R,)`` (1 where no AO was traced), ``albedo (R, 3)`` and
    ``normal (R, 3)`` (world frame) of the first scattering hit (0 elsewhere).
    """
    n = pixels.shape[0]
    eps = opts.ray_eps
    o, d = camera.rays(pixels, draws.camera(n))
    h = scene.intersector.intersect(o, d)
    counter.rays += n
    covered = np.zeros(n, bool)
    covered[h.hit] = scene.tri_inst[h.prim[h.hit]] >= opts.cover_from
    out = {"L": np.zeros((n, 3)), "covered": covered, "ao": np.ones(n),
           "albedo": np.zeros((n, 3), np.float32), "normal": np.zeros((n, 3), np.float32)}
    L = out["L"]
    if opts.objects_only:
        idx = np.flatnonzero(covered)
    else:
        miss = np.flatnonzero(~h.hit)
        if miss.size:
            add_rows(L, miss, scene.escape_radiance(d[miss]))
        idx = np.flatnonzero(h.hit)
        if idx.size:
            em = idx[scene.tri_emits[h.prim[idx]]]
            if em.size:
                add_rows(L, em, _emission(scene, h.prim[em], h.u[em], h.v[em], d[em], opts.one_sided))
            idx = idx[scene.tri_scatters[h.prim[idx]]]
    if idx.size == 0:
        return out
    s = interact(scene, Hits(t=h.t[idx], prim=h.prim[idx], u=h.u[idx], v=h.v[idx]), d[idx])
    out["albedo"][idx] = s.albedo
    out["normal"][idx] = s.ns
    if opts.ao_samples > 0:
        out["ao"][idx] = ambient_occlusion(scene.intersector, s.p, s.ng, s.ns, draws.rng, samples=opts.ao_samples,
                                           max_distance=opts.ao_distance, eps=eps, counter=counter)
    beta = np.ones((idx.size, 3), np.float32)
    wo = -d[idx]
    for depth in range(opts.max_depth):
        draws.begin(n)
        if idx.size == 0:
            if draws.correlated:
                continue   # keep drawing: the stream position must not depend on the scene
            break
        Ld, wi, weight, pdf = _scatter(scene, s, wo, beta, draws, idx, opts, counter)
        add_rows(L, idx, Ld)
        if not opts.trace_last and depth + 1 >= opts.max_depth:
            continue
        beta = beta * weight
        alive = beta.max(axis=1) > 0
        if depth + 1 >= opts.rr_depth:
            q = np.clip(beta.max(axis=1), np.float32(0.05), np.float32(1.0))
            alive &= draws.rr(idx) < q
            beta = beta / q[:, None]
        k = np.flatnonzero(alive)
        idx, beta, pdf, wi = idx[k], beta[k], pdf[k], wi[k]
        org = offset_origins(s.p[k], s.ng[k], wi, eps)
        h = scene.intersector.intersect(org, wi)
        counter.rays += k.size
        m = np.flatnonzero(~h.hit)
        if m.size:
            add_rows(L, idx[m], beta[m] * scene.escape_radiance(wi[m]))
        hk = np.flatnonzero(h.hit)
        prim = h.prim[hk]
        em = hk[scene.tri_emits[prim]]
        if em.size:
            pe = h.prim[em]
            Le = _emission(scene, pe, h.u[em], h.v[em], wi[em], opts.one_sided)
            if opts.object_shadows is not None:
                Le = shadowed_room_radiance(scene, opts.object_shadows, org[em], wi[em], h.t[em], pe, h.u[em],
                                            h.v[em], Le, draws.rng, eps)
            w = emission_mis_weight(scene, pe, h.t[em], wi[em], pdf[em])
            add_rows(L, idx[em], beta[em] * Le * w[:, None])
        sc = hk[scene.tri_scatters[prim]]
        idx, beta, wi = idx[sc], beta[sc], wi[sc]
        s = interact(scene, Hits(t=h.t[sc], prim=h.prim[sc], u=h.u[sc], v=h.v[sc]), wi)
        wo = -wi
    return out


@dataclass(frozen=True)
class ObjectShadows:
    """What :func:`shadowed_room_radiance` needs: the room and the objects as separate occluders, the room's
    albedo, the objects' bounding spheres and the light samples per room point (see :func:`object_shadows`)."""

    room: object             # Intersector of the room alone
    objects: object          # Intersector of the objects alone
    room_albedo: np.ndarray  # (room vertices, 3) float32 linear albedo (the light fit's)
    centres: np.ndarray      # (N, 3) float64 bounding-sphere centres of the instances
    radii: np.ndarray        # (N,) float64
    samples: int             # light samples per room point
    min_effect: float        # room points where (r / d)^2 >= this for some object are corrected


def object_shadows(scene: TraceScene, room_isect, obj_isect, room_albedo: np.ndarray | None, *, samples: int,
                   min_effect: float) -> ObjectShadows | None:
    """:class:`ObjectShadows` of a scene whose room vertices (the first of ``scene.vertices``) have the albedo
    ``room_albedo``, or None where there is nothing to correct (no samples, no objects, no area lights, or
    no albedo: the room reflects nothing the tracer knows of). Once per scene: it holds for every frame."""
    if (samples <= 0 or scene.num_instances == 0 or not scene.area_lights.count or room_albedo is None
            or not np.any(room_albedo > 0)):
        return None
    c, r = instance_spheres(scene)
    return ObjectShadows(room=room_isect, objects=obj_isect, room_albedo=np.asarray(room_albedo, np.float32),
                         centres=c, radii=r, samples=int(samples), min_effect=float(min_effect))


def shadowed_room_radiance(scene: TraceScene, sh: ObjectShadows, org: np.ndarray, wi: np.ndarray,
                           t: np.ndarray, prim: np.ndarray, u: np.ndarray, v: np.ndarray, Le: np.ndarray,
                           rng: np.random.Generator, eps: float) -> np.ndarray:
    """The room's radiance ``Le (R, 3)`` at the hits of object paths, less the light the objects keep off it.

    The room's radiance comes from photos taken without the objects: a table point beside an object is
    as bright as the photo shows it, though the object now shades it, and the object's underside, which
    sees mostly that point, came out too bright (against Mitsuba, its lowest two pixel rows by 7-9 gray
    levels, 2.5x in the light suite's spot room). Where an object can matter (``(r / d)^2 >= min_effect``
    for one of the bounding spheres) and the room point is no light, ``sh.samples`` points on the area
    lights estimate the direct light the objects block there (a shadow ray that the objects stop and the
    room alone does not), and the point's diffuse reflection of it, ``albedo / pi x blocked``, is taken
    away (at least 0). The albedo is the light fit's (:class:`pipeline.trace.lightfit.RoomLights`); the
    light the objects themselves send to the point is left out.
    """
    room = (scene.tri_inst[prim] == 0) & (scene.area_lights.prob_of_tri[prim] == 0)
    sel = np.flatnonzero(room)
    if sel.size == 0:
        return Le
    x = org[sel].astype(np.float64) + t[sel, None].astype(np.float64) * wi[sel]
    near = (sphere_cover(x, (sh.centres, sh.radii)) >= sh.min_effect).any(axis=1)
    sel, x = sel[near], x[near]
    if sel.size == 0:
        return Le
    f = scene.faces[prim[sel]]
    uu, vv = u[sel, None], v[sel, None]
    A = sh.room_albedo                   # room triangles index the room's vertices only
    rho = (1 - uu - vv) * A[f[:, 0]] + uu * A[f[:, 1]] + vv * A[f[:, 2]]
    ng = scene.tri_normal[prim[sel]].astype(np.float64)
    ng = np.where((_dot(ng, wi[sel]) > 0)[:, None], -ng, ng)
    m = sh.samples
    pr = np.repeat(np.arange(sel.size), m)
    draws = rng.random((3, pr.size))
    ok, o2, wl32, tmax, e = light_rays(scene, x, ng, pr, m, draws[0], draws[1], draws[2], eps)
    if ok.size:
        blocked = sh.objects.occluded(o2, wl32, tmax)
        ok, e, o2, wl32, tmax = ok[blocked], e[blocked], o2[blocked], wl32[blocked], tmax[blocked]
        if ok.size:
            free = ~sh.room.occluded(o2, wl32, tmax)
            ok, e = ok[free], e[free]
    if ok.size == 0:
        return Le
    lost = np.zeros((sel.size, 3))
    add_rows(lost, pr[ok], e)
    out = np.array(Le, np.float32)
    out[sel] = np.maximum(out[sel] - (rho / np.pi * lost).astype(np.float32), 0.0)
    return out


def add_rows(acc: np.ndarray, rows: np.ndarray, vals: np.ndarray) -> None:
    """``acc[rows] += vals`` with repeated rows summed (bincount per channel, faster than add.at)."""
    if rows.size == 0:
        return
    for c in range(acc.shape[1]):
        acc[:, c] += np.bincount(rows, weights=vals[:, c], minlength=acc.shape[0])


def ambient_occlusion(intersector, p: np.ndarray, ng: np.ndarray, ns: np.ndarray, rng: np.random.Generator, *,
                      samples: int, max_distance: float, eps: float, counter: RayCounter | None = None) -> np.ndarray:
    """Cosine-weighted ambient occlusion at surface points.

    Parameters
    ----------
    intersector : occluders (the room and all objects)
    p, ng, ns : (R, 3) points, geometric and shading normals (facing the viewer)
    samples : rays per point
    max_distance : metres; hits farther away do not occlude

    Returns
    -------
    (R,) float64 in [0, 1]: the cosine-weighted share of the hemisphere about ``ns`` that is open
    within ``max_distance`` (1 = open, 0 = enclosed).
    """
    n = p.shape[0]
    if n == 0:
        return np.ones(0)
    pr = np.repeat(np.arange(n), samples)
    u = rng.random((2, pr.size), dtype=np.float32)
    dl, _ = cosine_hemisphere(u[0], u[1])
    dw = to_world(dl, ns[pr])
    dn = np.einsum("ij,ij->i", dw, ng[pr])
    dw = np.where((dn < 0)[:, None], dw - (2 * dn)[:, None] * ng[pr], dw)  # see _scatter: no self-hits
    org = offset_origins(p[pr], ng[pr], dw, eps)
    occ = intersector.occluded(org, dw, np.float32(max_distance))
    if counter is not None:
        counter.rays += pr.size
    return 1.0 - np.bincount(pr, weights=occ.astype(np.float64), minlength=n) / samples


def render(scene: TraceScene, camera: Camera, mask: np.ndarray, settings: RenderSettings,
           rng: np.random.Generator, object_shadows: ObjectShadows | None = None) -> FrameBuffers:
    """Render the pixels in ``mask (H, W) bool`` with adaptive sampling; see the module docstring.

    ``object_shadows``: take the objects' shadows out of the room's light the objects see
    (:func:`shadowed_room_radiance`); None = the room as photographed."""
    H, W = camera.height, camera.width
    if mask.shape != (H, W):
        raise ValueError(f"mask shape {mask.shape} does not match the camera's {(H, W)}")
    pix = np.flatnonzero(mask)
    n = pix.size
    counter = RayCounter()
    Ls = np.zeros((n, 3))
    lum2 = np.zeros(n)
    cnt = np.zeros(n, np.int64)
    cov = np.zeros(n)
    ao_s = np.zeros(n)
    ao_n = np.zeros(n)
    alb = np.zeros((n, 3))
    nrm = np.zeros((n, 3))
    active = np.arange(n)
    done = 0
    draws = StratifiedDraws(rng, n, settings.spp, settings.spp_batch) if settings.stratified else PathDraws(rng)
    opts = PathOptions(max_depth=settings.max_depth, rr_depth=settings.rr_depth, ray_eps=settings.ray_eps,
                       ao_samples=settings.ao_samples, ao_distance=settings.ao_distance,
                       object_shadows=object_shadows)
    while active.size and done < settings.spp:
        b = min(settings.spp_batch, settings.spp - done)
        loc = np.repeat(active, b)
        draws.start(active, done, b)
        r = trace_paths(scene, camera, pix[loc], draws, opts, counter)
        add_rows(Ls, loc, r["L"])
        lum = r["L"] @ LUMINANCE.astype(np.float64)
        lum2 += np.bincount(loc, weights=lum * lum, minlength=n)
        cnt += np.bincount(loc, minlength=n)
        c = r["covered"].astype(np.float64)
        cov += np.bincount(loc, weights=c, minlength=n)
        ao_s += np.bincount(loc, weights=r["ao"] * c, minlength=n)
        ao_n += np.bincount(loc, weights=c, minlength=n)
        add_rows(alb, loc, r["albedo"].astype(np.float64))
        add_rows(nrm, loc, r["normal"].astype(np.float64))
        done += b
        if done >= settings.spp_min and done < settings.spp:
            m = (Ls[active] @ LUMINANCE) / cnt[active]
            var = np.maximum(lum2[active] / cnt[active] - m * m, 0.0)
            se = np.sqrt(var / cnt[active])
            covered_m = (Ls @ LUMINANCE)[cov > 0] / cnt[cov > 0]
            floor = 0.1 * float(covered_m.mean()) if covered_m.size else 0.0
            active = active[se > settings.noise_target * np.maximum(m, floor)]
    cnt_safe = np.maximum(cnt, 1)
    R_w2c = camera.T_c2w[:3, :3].T
    out_pbr = np.zeros((H * W, 3), np.float32)
    out_ao = np.ones(H * W, np.float32)
    out_cov = np.zeros(H * W, np.float32)
    out_alb = np.zeros((H * W, 3), np.float32)
    out_nrm = np.zeros((H * W, 3), np.float32)
    out_spp = np.zeros(H * W, np.int32)
    out_pbr[pix] = Ls / cnt_safe[:, None]
    out_cov[pix] = cov / cnt_safe
    out_ao[pix] = np.where(ao_n > 0, ao_s / np.maximum(ao_n, 1), 1.0)
    out_alb[pix] = alb / cnt_safe[:, None]
    out_nrm[pix] = (nrm / cnt_safe[:, None]) @ R_w2c.T
    out_spp[pix] = cnt
    log.debug("rendered %d pixels, %d rays, mean spp %.1f", n, counter.rays, cnt.mean() if n else 0.0)
    return FrameBuffers(pbr=out_pbr.reshape(H, W, 3), ao=out_ao.reshape(H, W), coverage=out_cov.reshape(H, W),
                        albedo=out_alb.reshape(H, W, 3), normal=out_nrm.reshape(H, W, 3),
                        spp=out_spp.reshape(H, W), rays=counter.rays)


def trace_mask(labels: np.ndarray, edge_band: int) -> np.ndarray:
    """Pixels to trace: where ``labels (H, W)`` is non-zero, dilated by ``edge_band`` pixels (square)."""
    m = np.asarray(labels) > 0
    if edge_band <= 0 or not m.any():
        return m
    from scipy.ndimage import binary_dilation

    return binary_dilation(m, structure=np.ones((3, 3), bool), iterations=edge_band)
