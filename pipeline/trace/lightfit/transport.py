"""Step 4, light transport: the irradiance at the fit's points, known and per unit radiance of each unknown.

A diffuse point of albedo ``rho`` shows ``L = rho / pi * (E_known + A e)``. ``E_known`` is gathered by
cosine-weighted hemisphere rays against the closed room (the known radiance where they meet it; the unseen
side of a sheet sends nothing here, the solve adds what it reflects). The columns ``A`` sample each unknown's
area explicitly, with visibility through the room's own geometry, so the shadows in the photos say where the
light comes from. The unseen cells also reflect: ``G`` is the irradiance one receives per unit radiance of
another, ``Eu`` what each receives from the known room. Random numbers are drawn in order on this thread; the
shadow rays may run on a pool's threads with the same result.
"""

from __future__ import annotations

import collections
import functools
from dataclasses import dataclass, field

import numpy as np

from pipeline.trace.lightfit.closure import Room, quad_area, unseen_side

COLUMN_CHUNK = 8              # columns whose shadow rays are traced together (on the fit's threads)
REGION_SAMPLES = 16           # area samples per (unseen cell, clipped region) pair
KNOWN_SAMPLES = 16            # area samples per (unseen cell, known light) pair
MIN_CELL_RAYS = 16            # hemisphere rays per unseen cell at least (half the points' otherwise)


@dataclass(frozen=True)
class Transport:
    """How light reaches the fit's points and the unseen cells (K unknowns, n points)."""

    Ek: np.ndarray             # (n, 3) float64 irradiance at the points from the known radiance and known lights
    A: np.ndarray              # (n, K) float64 irradiance at the points per unit radiance of each unknown
    srows: np.ndarray          # (n1,) int64 the points that find where the light is (every other one)
    A1: np.ndarray             # (n1, K) float64 ``A`` on those points
    active: np.ndarray         # (k,) int64 unknowns that send light to some point
    G: np.ndarray              # (K, K) float64 irradiance at each unseen cell per unit radiance of each unknown
    Eu: np.ndarray             # (K, 3) float64 irradiance at each unseen cell from the known room
    back_owner: np.ndarray     # (R,) int64 point whose gather ray met an unseen side of a sheet
    back_pos: np.ndarray       # (R, 3) float64 metres, where it met it
    back_normal: np.ndarray    # (R, 3) float64 normal of the side the cameras saw there
    summary: dict = field(default_factory=dict)   # what was measured (JSON-able)


def light_transport(room: Room, unk, pts, seen_side: int, gather_rays: int, samples: int, min_points: int,
                    rng: np.random.Generator, pool=None) -> Transport:
    """The :class:`Transport` of the unknowns ``unk`` to the points ``pts`` in ``room`` (``seen_side``: the
    mesh's side the cameras see): ``gather_rays`` hemisphere rays and ``samples`` area samples per pair, the
    points that find the light every other one where there are ``2 x min_points`` or more."""
    P, N, n = pts.P, pts.N, pts.n
    K = unk.K
    Ek, owner, pos, normal, share = _known_irradiance(room, unk, P, N, seen_side, gather_rays, rng, pool)
    A = _unknown_columns(room, unk, P, N, samples, rng, pool)
    if room.known_quads:   # the known lights' irradiance joins the known part
        Ek = Ek + A[:, K:] @ room.known_radiance
    A = np.ascontiguousarray(A[:, :K])
    active = np.flatnonzero(A.max(axis=0) > 0)
    srows = np.arange(0, n, 2) if n >= 2 * min_points else np.arange(n)
    G, Eu = _cell_transport(room, unk, seen_side, gather_rays, rng, pool)
    return Transport(Ek=Ek, A=A, srows=srows, A1=np.ascontiguousarray(A[srows]), active=active, G=G, Eu=Eu,
                     back_owner=owner, back_pos=pos, back_normal=normal, summary={"gather_unseen_side": share})


def _known_irradiance(room: Room, unk, P: np.ndarray, N: np.ndarray, seen_side: int, M: int,
                      rng: np.random.Generator, pool) -> tuple:
    """Irradiance (n, 3) at points ``P`` from the room's known radiance (``M`` cosine-weighted rays each; the
    unknowns and the known lights are sampled by area instead), and the rays that met the unseen side of a
    sheet: their point, where they met it, the seen side's normal; and their share of the rays that hit."""
    nt, nbt, tn = room.nt, room.nbt, room.tri_normal
    pr, hh, dg = gather(room.isect, P, N, M, rng, room.eps, pool)
    Lg = np.zeros((pr.size, 3))
    hit = np.flatnonzero(hh.hit)
    Lg[hit] = at(unk.vrad, room.all_f, hh.prim[hit], hh.u[hit], hh.v[hit])
    # a mesh triangle's unseen side does not send the seen side's colour (what it sends depends on the albedo)
    back = hit[unseen_side(hh.prim[hit], dg[hit], tn, nt, seen_side)]
    Lg[back] = 0.0
    # (a clipped region's back is not a sheet: the region is an unknown, sampled two-sided)
    sheet = back[unk.unknown_tri[hh.prim[back]] < 0]
    back_owner = pr[sheet]
    back_pos = P[back_owner] + hh.t[sheet, None].astype(np.float64) * dg[sheet].astype(np.float64)
    back_normal = tn[hh.prim[sheet]] * float(seen_side)    # the side the cameras saw (seen_side is +-1 here)
    share = round(float(back.size / max(hit.size, 1)), 4)
    Lg[hit[(unk.unknown_tri[hh.prim[hit]] >= 0) | (hh.prim[hit] >= nbt)]] = 0.0   # sampled explicitly
    Ek = np.pi * Lg.reshape(len(P), M, 3).mean(axis=1)
    return Ek, back_owner, back_pos, back_normal, share


def _unknown_columns(room: Room, unk, P: np.ndarray, N: np.ndarray, S: int, rng: np.random.Generator,
                     pool) -> np.ndarray:
    """(n, K + k) irradiance at points ``P`` per unit radiance of each unknown, then of each known light: ``S``
    area samples per pair, with visibility. A clipped mesh region (or a known light) lights both ways."""
    n, K, nbu, nbt = len(P), unk.K, unk.nbu, room.nbt
    nk = len(room.known_quads)
    known_tris = [np.array([nbt + i, nbt + nk + i]) for i in range(nk)]
    A = np.zeros((n, K + nk))
    Pi = np.repeat(P, S, axis=0)
    Ni = np.repeat(N, S, axis=0)

    def jobs():
        for k, tris in enumerate(unk.el_tris + known_tris):
            drawn = area_points(tris, n * S, room.corners, room.tri_normal, room.tri_area, rng)
            if drawn is not None:
                yield k, functools.partial(sampled_irradiance, room.isect, Pi, Ni, drawn[0], drawn[1], drawn[2],
                                           room.eps, two_sided=nbu <= k < K)

    return fill_columns(A, S, jobs(), pool)


def _cell_transport(room: Room, unk, seen_side: int, M: int, rng: np.random.Generator, pool) -> tuple:
    """``G (K, K)``, the irradiance at each unseen cell per unit radiance of each unknown, and ``Eu (K, 3)``,
    what each receives from the known room: hemisphere rays from the cells' centres for the known room and the
    other cells, the clipped regions and the known lights sampled by area (the rays seldom meet a small one)."""
    K, nbu = unk.K, unk.nbu
    G = np.zeros((K, K))
    Eu = np.zeros((K, 3))
    if not nbu:
        return G, Eu
    bu = unk.box_unknown
    cen, nrm = room.box_centre[bu], room.box_normal[bu]
    Mu = max(MIN_CELL_RAYS, M // 2)
    ku, hu, du = gather(room.isect, cen, nrm, Mu, rng, room.eps, pool)
    hit = np.flatnonzero(hu.hit)
    hit = hit[~unseen_side(hu.prim[hit], du[hit], room.tri_normal, room.nt, seen_side)]
    tri = hu.prim[hit]
    j = unk.unknown_tri[tri]
    un = (j >= 0) & (j < nbu)             # unseen cells (clipped regions: sampled below)
    np.add.at(G, (ku[hit[un]], j[un]), np.pi / Mu)
    kn = hit[(j < 0) & (tri < room.nbt)]
    np.add.at(Eu, ku[kn], np.pi / Mu * at(unk.vrad, room.all_f, hu.prim[kn], hu.u[kn], hu.v[kn]))
    if unk.groups:   # from the side the cameras saw, as the gather takes it
        G[:nbu, nbu:] = region_columns(room.isect, cen, nrm, unk.groups, room.corners, room.tri_normal,
                                       room.tri_area, REGION_SAMPLES, seen_side, rng, room.eps, pool)
    if room.known_quads:   # sampled by area, as the trace stage's lights are
        Eu[:nbu] += quad_columns(room.isect, cen, nrm, np.asarray(room.known_quads), np.asarray(room.known_normals),
                                 KNOWN_SAMPLES, rng, room.eps, pool) @ room.known_radiance
    return G, Eu


def at(values: np.ndarray, faces: np.ndarray, prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Per-vertex ``values`` interpolated at barycentric points ``(u, v)`` of triangles ``prim``."""
    f = faces[prim]
    u, v = u[:, None], v[:, None]
    return (1 - u - v) * values[f[:, 0]] + u * values[f[:, 1]] + v * values[f[:, 2]]


def gather(isect, points: np.ndarray, normals: np.ndarray, rays: int, rng: np.random.Generator, eps: float,
           pool=None):
    """``rays`` cosine-weighted hemisphere rays from each point: (owner (R,) point index, hits, directions);
    cast in parts on ``pool``'s threads if given (the same hits)."""
    from pipeline.trace.intersect import Hits, offset_origins
    from pipeline.trace.sampling import cosine_hemisphere, to_world

    owner = np.repeat(np.arange(len(points)), rays)
    u = rng.random((2, owner.size))
    dl, _ = cosine_hemisphere(u[0], u[1])
    n = normals[owner]
    d = to_world(dl, n).astype(np.float32)
    o = offset_origins(points[owner].astype(np.float32), n.astype(np.float32), d, eps)
    if pool is None:
        return owner, isect.intersect(o, d), d
    cuts = np.linspace(0, len(o), 5).astype(int)   # four parts: two threads each cast two
    parts = in_order([functools.partial(isect.intersect, o[a:b], d[a:b]) for a, b in zip(cuts[:-1], cuts[1:])], pool)
    return owner, Hits(*(np.concatenate([getattr(h, f) for h in parts]) for f in ("t", "prim", "u", "v"))), d


def sampled_irradiance(isect, Pi: np.ndarray, Ni: np.ndarray, lp: np.ndarray, nl: np.ndarray, area: float,
                       eps: float, two_sided: bool = False) -> np.ndarray:
    """(R,) one-sample estimates of the irradiance at receivers ``Pi`` (normals ``Ni``) per unit radiance
    of a light of total ``area``, from points ``lp`` drawn uniformly on it (normals ``nl``), with visibility
    through ``isect``; a one-sided light emits along ``nl``."""
    from pipeline.trace.intersect import offset_origins

    dv = lp - Pi
    dist = np.linalg.norm(dv, axis=1)
    wl = dv / np.maximum(dist, 1e-12)[:, None]
    cos_i = np.einsum("ij,ij->i", wl, Ni)
    cos_l = -np.einsum("ij,ij->i", wl, nl)
    if two_sided:
        cos_l = np.abs(cos_l)
    g = np.zeros(len(Pi))
    ok = np.flatnonzero((cos_i > 0) & (cos_l > 0) & (dist > 4 * eps))
    if ok.size == 0:
        return g
    o2 = offset_origins(Pi[ok].astype(np.float32), Ni[ok].astype(np.float32), wl[ok].astype(np.float32), eps)
    occ = isect.occluded(o2, wl[ok].astype(np.float32), (dist[ok] - 3 * eps).astype(np.float32))
    vis = ok[~occ]
    g[vis] = cos_i[vis] * cos_l[vis] / dist[vis] ** 2 * area
    return g


def in_order(jobs: list, pool) -> list:
    """``[job() for job in jobs]``, on ``pool``'s threads when there is one (Embree traces without holding
    the GIL). Callers draw their random numbers before, in order: the result does not depend on the pool."""
    if pool is None:
        return [job() for job in jobs]
    return list(pool.map(lambda job: job(), jobs))


def fill_columns(out: np.ndarray, samples: int, jobs, pool) -> np.ndarray:
    """``out[:, c]``: the mean over ``samples`` of each ``(c, job)`` that ``jobs`` yields (a generator that
    draws its random numbers as it goes, so in order). On ``pool``'s threads, at most ``COLUMN_CHUNK`` jobs
    ahead of the oldest unfinished one: this thread draws the next jobs' samples while the pool traces."""
    def put(c: int, g: np.ndarray) -> None:
        out[:, c] = g.reshape(out.shape[0], samples).mean(axis=1)

    if pool is None:
        for c, job in jobs:
            put(c, job())
        return out
    ahead: collections.deque = collections.deque()
    for c, job in jobs:
        ahead.append((c, pool.submit(job)))
        if len(ahead) > COLUMN_CHUNK:
            c0, fut = ahead.popleft()
            put(c0, fut.result())
    for c0, fut in ahead:
        put(c0, fut.result())
    return out


def quad_columns(isect, P: np.ndarray, N: np.ndarray, quads: np.ndarray, normals: np.ndarray, samples: int,
                 rng: np.random.Generator, eps: float, pool=None) -> np.ndarray:
    """(n, C) irradiance at points ``P`` (normals ``N``) per unit radiance of each one-sided rectangle
    ``quads (C, 4, 3)`` emitting along ``normals (C, 3)``: ``samples`` area samples per pair, with visibility
    through ``isect``; the shadow rays on ``pool``'s threads if given."""
    n = len(P)
    Pi = np.repeat(P, samples, axis=0)
    Ni = np.repeat(N, samples, axis=0)

    def jobs():
        for c, q in enumerate(quads):
            a, b = q[1] - q[0], q[3] - q[0]
            r = rng.random((2, n * samples))
            lp = q[0] + r[0][:, None] * a + r[1][:, None] * b
            yield c, functools.partial(sampled_irradiance, isect, Pi, Ni, lp,
                                       np.broadcast_to(normals[c], lp.shape), float(quad_area(q)[0]), eps)

    return fill_columns(np.zeros((n, len(quads))), samples, jobs(), pool)


def area_points(tris: np.ndarray, count: int, corners: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float] | None:
    """``count`` points drawn uniformly over the area of triangles ``tris`` (indices into ``corners (T, 3, 3)``,
    ``normals (T, 3)``, ``areas (T,)``): the points (count, 3), their triangles' normals (count, 3) and the
    triangles' total area; None where that is 0."""
    ar = areas[tris]
    tot = float(ar.sum())
    if tot <= 0:
        return None
    pick = tris[np.minimum(np.searchsorted(np.cumsum(ar) / tot, rng.random(count)), len(tris) - 1)]
    r1, r2 = rng.random(count), rng.random(count)
    s1 = np.sqrt(r1)
    q = corners[pick]
    lp = (1 - s1)[:, None] * q[:, 0] + (s1 * (1 - r2))[:, None] * q[:, 1] + (s1 * r2)[:, None] * q[:, 2]
    return lp, normals[pick], tot


def region_columns(isect, P: np.ndarray, N: np.ndarray, regions: list, corners: np.ndarray, normals: np.ndarray,
                   areas: np.ndarray, samples: int, side: int, rng: np.random.Generator, eps: float,
                   pool=None) -> np.ndarray:
    """(n, R) irradiance at points ``P`` (normals ``N``) per unit radiance of each region of ``regions`` (arrays
    of triangle indices, as :func:`area_points` takes them): ``samples`` area samples per pair, with visibility
    through ``isect``. A region emits from its triangles' normal side (``side`` +1), the other side (-1) or
    both (0)."""
    Pi, Ni = np.repeat(P, samples, axis=0), np.repeat(N, samples, axis=0)

    def jobs():
        for r, tris in enumerate(regions):
            drawn = area_points(tris, len(Pi), corners, normals, areas, rng)
            if drawn is not None:
                yield r, functools.partial(sampled_irradiance, isect, Pi, Ni, drawn[0], drawn[1] * (side or 1),
                                           drawn[2], eps, two_sided=side == 0)

    return fill_columns(np.zeros((len(P), len(regions))), samples, jobs(), pool)
