"""Stage 3, lamp refinement: the emitting box cells stand for lamps smaller than a cell.

A 0.4 m cell on the ceiling smears a 10 cm spot above a table into a broad glow from higher up. Each emitting
cell is cut into squares of ``refine`` metres, at the box and, under a ceiling cell, hanging below it in free
space no photo saw (:func:`lamp_candidates`); the sparsity prior picks among them, the box cells then only
reflect, and the chosen lamps are refitted without the prior. Where a light is and how big is what the objects
see most, and the same objective tells it: each cluster of touching lamps hung below the ceiling becomes one
rectangle whose height, place and size a coordinate search sets (``polish``). The albedo levels are searched
again with the lamps pinned.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.color import LUMINANCE_F64
from pipeline.trace.lightfit.albedo import (ALBEDO_LEVELS, brightest_colour, curve_minimum, finite, grey_levels,
                                            level_search_with_power, white_levels)
from pipeline.trace.lightfit.closure import quad_area
from pipeline.trace.lightfit.colour import colour_clipped
from pipeline.trace.lightfit.observe import MIN_FIT_POINTS
from pipeline.trace.lightfit.solve import (Problem, alternate, design, prior_scale, rho_unknown, sliver_rule,
                                           unseen_albedo)
from pipeline.trace.lightfit.transport import quad_columns

REFINE_DEPTHS = (0.0, 0.25, 0.5, 0.75)  # metres below an emitting ceiling cell a lamp may hang
LAMP_MIN_M = 1.5              # a hanging lamp is at least this far above the scan's lowest point
CELL_SAMPLES = 4              # area samples per (unseen cell, lamp) pair
# the polish: each cluster of touching lamps holding at least POLISH_SHARE of their power becomes one rectangle,
# moved along its normal and in its plane and resized by a coordinate search from POLISH_STEPS (metres along
# the normal, along its two edges; log of its two half sizes), halving POLISH_HALVINGS times
POLISH_SHARE = 0.1
POLISH_STEPS = (0.05, 0.04, 0.04, 0.3, 0.3)
POLISH_DEPTH_STEP_M = 0.05    # the search starts at the best of the depths this far apart
POLISH_HALVINGS = 3
POLISH_MIN_HALF_M = 0.01      # the smallest lamp the polish makes: 2 cm across


@dataclass(frozen=True)
class Lamps:
    """Stage 3's answer: the unknowns' emission with the box cells only reflecting, and the lamps."""

    e: np.ndarray              # (K, 3) float64 emission of the unknowns (the clipped regions'; cells at their bound)
    Lu: np.ndarray             # (K, 3) float64 radiance of the unknowns: emitted and reflected
    E: np.ndarray              # (n, 3) float64 irradiance at the points
    rho: np.ndarray            # (npatch, 3) float64 patch albedo
    quads: np.ndarray          # (J, 4, 3) float64 metres, the lamps' corners
    normals: np.ndarray        # (J, 3) float64 the side each lamp emits on
    emission: np.ndarray       # (J, 3) float64 their radiance
    level: np.ndarray          # (3,) float64 albedo level per channel
    res_curve: np.ndarray      # (len(ALBEDO_LEVELS), 3) float64 objective per level (inf: not evaluated)
    obj: np.ndarray            # (3,) float64 objective per channel at ``level``
    raised: float | None       # the most the edges' colour raised a clipped light (None: not coloured)
    summary: dict = field(default_factory=dict)   # what was found (JSON-able)


@dataclass(frozen=True)
class LampProblem:
    """Stage 3's unknowns: the clipped regions among the emitters, then lamps; every box cell only reflects."""

    pb: Problem
    regions: np.ndarray        # (nr,) int64 unknowns that are clipped mesh regions (they stay as they are)
    rest: np.ndarray           # (K - nr,) int64 the other unknowns (at their lower bound)

    @property
    def nr(self) -> int:
        return self.regions.size


def lamp_problem(lp: LampProblem, lv: np.ndarray, Gcand: np.ndarray, Acand: np.ndarray, rows=None) -> tuple:
    """Transport, known light and columns (the regions', then the lamps', whose light at the unseen cells is
    ``Gcand (K, J)`` and at the points ``rows`` ``Acand``) at levels ``lv``."""
    Mc, Ae, Ekc = design(lp.pb, lv, lp.regions, lp.rest, Gcand, rows=rows)
    nr = lp.nr
    cols = [np.concatenate([Ae[c][:, :nr], Acand + Ae[c][:, nr:]], axis=1) for c in range(3)]
    return Mc, Ekc, cols


def lamp_bounds(lp: LampProblem, J: int) -> tuple[np.ndarray, np.ndarray]:
    """Lower bounds and prior weights of the regions and ``J`` lamps, for the fits without the prior (the lamps'
    lower bound 0)."""
    return np.concatenate([lp.pb.unk.lb[lp.regions], np.zeros((J, 3))]), np.zeros(lp.nr + J)


def refine(pb: Problem, level: np.ndarray, sup: np.ndarray, rng: np.random.Generator, pool) -> Lamps | None:
    """Stage 3 from stage 2's emitters ``sup`` at its levels ``level (3,)``: lamps chosen among the emitting
    cells' squares by the sparsity prior, polished, then the levels searched again. None when there is nothing
    to refine."""
    K = pb.unk.K
    regions = sup[sup >= pb.unk.nbu]
    lp = LampProblem(pb=pb, regions=regions, rest=np.setdiff1d(np.arange(K), regions))
    cand = _candidates(pb, sup, rng, pool)
    if cand is None:
        return None
    quads, qn, parent, Ac, lam_c, Gc, crows = cand
    keep, pw = _choose(lp, level, quads, Ac, lam_c, Gc, crows, pool)
    if keep is None:
        return None
    summary: dict = {}
    lq, ln, Gk = quads[keep], qn[keep], Gc[:, keep]
    if pb.st.polish > 0:
        lq, ln, Gk, summary["polished_lamps"] = polish(lp, level, lq, ln, parent[keep], pw[keep], Gk, rng)
    # the chosen lamps' light at all the points (fresh samples)
    Akeep = quad_columns(pb.room.isect, pb.pts.P, pb.pts.N, lq, ln, pb.st.emitter_samples, rng, pb.room.eps, pool)
    summary["stage2_level"] = [float(x) for x in level]
    lamps = _final_levels(lp, lq, ln, Gk, Akeep, pool, summary)
    summary["refined_candidates"] = int(len(quads))
    return lamps


def _candidates(pb: Problem, sup: np.ndarray, rng: np.random.Generator, pool) -> tuple | None:
    """The lamps the emitting box cells of ``sup`` may stand for, with their light at the points (on every
    other point of stage 1's: the largest single cost of the fit) and at the unseen cells, and their prior
    weights: a lamp the points see far less of than its size says (a square behind a wall, seen through a gap)
    is priced as one of its size seen like the median cell, and dropped under the sliver rule's share."""
    room, unk, tr, st = pb.room, pb.unk, pb.tr, pb.st
    cells = sup[sup < unk.nbu]
    quads, qn, parent = lamp_candidates(room.isect, unk.box_unknown[cells], room.box_v, room.box_normal, room.up,
                                        st.refine, room.h_low + LAMP_MIN_M, room.cameras, room.eps)
    if len(quads) == 0:
        return None
    srows = tr.srows
    crows = srows[::2] if len(srows) >= 2 * MIN_FIT_POINTS else srows
    Ac = quad_columns(room.isect, pb.pts.P[crows], pb.pts.N[crows], quads, qn, st.emitter_samples, rng, room.eps,
                      pool)
    cnc = np.linalg.norm(Ac, axis=0) * np.sqrt(len(srows) / len(crows))     # as if on stage 1's points
    seen_ok, lam_c = sliver_rule(cnc, quad_area(quads) * pb.dens, pb.med)
    use = np.flatnonzero((cnc > 0) & seen_ok)
    quads, qn, parent, Ac, lam_c = quads[use], qn[use], parent[use], Ac[:, use], lam_c[use]
    if len(quads) == 0:
        return None
    return quads, qn, parent, Ac, lam_c, cell_columns(pb, quads, qn, rng, pool), crows


def cell_columns(pb: Problem, quads: np.ndarray, normals: np.ndarray, rng: np.random.Generator,
                 pool=None) -> np.ndarray:
    """(K, J) float64: each lamp's (corners ``quads (J, 4, 3)``, ``normals (J, 3)``) light per unit radiance at
    the unseen box cells (the first ``nbu`` unknowns; the clipped regions' rows stay 0)."""
    room, unk = pb.room, pb.unk
    bu = unk.box_unknown
    g = np.zeros((unk.K, len(quads)))
    g[:unk.nbu] = quad_columns(room.isect, room.box_centre[bu], room.box_normal[bu], quads, normals, CELL_SAMPLES,
                               rng, room.eps, pool)
    return g


def _choose(lp: LampProblem, level: np.ndarray, quads: np.ndarray, Ac: np.ndarray, lam_c: np.ndarray,
            Gc: np.ndarray, crows: np.ndarray, pool) -> tuple:
    """The lamps the sparsity prior picks (as much as a whole cell per unit of light sent to the points, its
    scale from stage 1's columns): those carrying ``support_share`` of their power, at most ``max_emitters``;
    and every candidate's power. (None, None) where none emits."""
    pb, st = lp.pb, lp.pb.st
    lbj = lamp_bounds(lp, len(quads))[0]
    lamj = np.concatenate([pb.lam_k[lp.regions], lam_c])
    scale0 = prior_scale(pb.tr.A[np.ix_(crows, pb.active)], pb.w[crows])
    _, Ekc, cols = lamp_problem(lp, level, Gc, Ac, rows=crows)
    ej, _, _, _ = alternate(pb, level, Ekc, cols, lbj, lamj, st.sparsity, 3, scale0, rows=crows, on=pool)
    pw = (ej[lp.nr:] @ LUMINANCE_F64) * quad_area(quads)
    if pw.sum() <= 0:
        return None, None
    order = np.argsort(-pw)
    cum = np.cumsum(pw[order]) / float(pw.sum())
    return np.sort(order[:max(1, int(np.searchsorted(cum, st.support_share)) + 1)][:st.max_emitters]), pw


def _final_levels(lp: LampProblem, lq: np.ndarray, ln: np.ndarray, Gk: np.ndarray, Akeep: np.ndarray, pool,
                  summary: dict) -> Lamps:
    """With the lamps ``lq`` (normals ``ln``, light at the unseen cells ``Gk`` and at the points ``Akeep``) where
    they are, each channel's albedo level again at the residual's minimum, then with the pull of the brightest
    surfaces toward grey (or of the light toward white); the fit there without the prior."""
    pb, st, nr = lp.pb, lp.pb.st, lp.nr
    lbk, lamk = lamp_bounds(lp, len(lq))       # no prior from here on
    area_j = np.concatenate([pb.unk.area_k[lp.regions], quad_area(lq)])

    def objective3(lv: float) -> tuple[np.ndarray, np.ndarray]:
        _, Ekc, cols = lamp_problem(lp, np.full(3, lv), Gk, Akeep)
        ej3, _, _, obj = alternate(pb, np.full(3, lv), Ekc, cols, lbk, lamk, 0.0, 2)
        return obj, area_j @ ej3

    res3, power3 = level_search_with_power(objective3, pool)
    level0 = curve_minimum(np.asarray(ALBEDO_LEVELS), res3)
    summary["stage3_level_data"] = [round(float(x), 4) for x in level0]
    bright = None
    if st.white_patch > 0:   # the room's brightest surfaces at the data's levels, then pulled toward grey
        _, Ekc, cols = lamp_problem(lp, level0, Gk, Akeep)
        bright = brightest_colour(alternate(pb, level0, Ekc, cols, lbk, lamk, 0.0, 2)[1], pb.patch)
    if bright is not None:
        summary["brightest_albedo_data"] = finite(bright)
        level = grey_levels(res3, bright, level0, st.white_patch)
    else:
        level = white_levels(res3, power3, st.white_prior)
    Mc, Ekc, cols = lamp_problem(lp, level, Gk, Akeep)
    ej, rho3, E3, obj3 = alternate(pb, level, Ekc, cols, lbk, lamk, 0.0, 5, on=pool)
    e3 = pb.unk.lb.copy()
    e3[lp.regions] = ej[:nr]
    raised = colour_clipped(e3, pb.unk.lb, pb.edge_colour)
    el = ej[nr:]
    ua = unseen_albedo(pb, level)
    Lu3 = np.stack([Mc[c] @ (e3[:, c] + rho_unknown(pb, ua[c]) * (pb.tr.Eu[:, c] + Gk @ el[:, c]))
                    for c in range(3)], axis=1)
    return Lamps(e=e3, Lu=Lu3, E=E3, rho=rho3, quads=lq, normals=ln, emission=el, level=level, res_curve=res3,
                 obj=obj3, raised=raised, summary=summary)


def polish(lp: LampProblem, lv: np.ndarray, lq: np.ndarray, ln: np.ndarray, par: np.ndarray, power: np.ndarray,
           Gk: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Each cluster of touching lamps (``lq (J, 4, 3)``, normals ``ln``, box cells ``par``) with a lamp hung
    below its cell and at least POLISH_SHARE of their ``power`` becomes one rectangle, placed and sized by a
    coordinate search (:func:`coordinate_search`, ``polish`` evaluations each) on stage 3's objective at levels
    ``lv`` over stage 1's points, the other lamps held. Returns the lamps, their light at the unseen cells
    ``Gk (K, J')`` and the number of rectangles made."""
    pb, st = lp.pb, lp.pb.st
    BV, bnrm = pb.room.box_v, pb.room.box_normal
    groups = lamp_clusters(lq, ln, st.refine)
    share = np.array([power[g].sum() for g in groups]) / max(float(power.sum()), 1e-30)
    depth_l = np.einsum("ij,ij->i", lq.mean(axis=1) - BV[4 * par], bnrm[par])   # below each lamp's cell
    # only clusters with a lamp hung below its cell: the grid's depths are what it refines
    todo = [int(i) for i in np.argsort(-share, kind="stable")
            if share[i] >= POLISH_SHARE and (depth_l[groups[i]] > 1e-6).any()]
    if not todo:
        return lq, ln, Gk, 0
    seed = int(rng.integers(2 ** 63))
    nq, nn, ng, rect = _polish_start(lq, ln, Gk, groups, todo, power, depth_l, st.refine)
    K, nr, srows = pb.unk.K, lp.nr, pb.tr.srows
    Gn = np.zeros((K, len(nq)))
    An = np.zeros((len(srows), len(nq)))
    for j in range(len(nq)):
        An[:, j], g = lamp_columns(pb, nq[j], nn[j], seed)
        Gn[:, j] = g if ng[j] is None else ng[j]
    lbp, lamp = lamp_bounds(lp, len(nq))
    # the transport and the other lamps' columns do not change while one lamp moves: only its column
    Mc, Ekc, cols = lamp_problem(lp, lv, Gn, An, rows=srows)
    rho_c = [rho_unknown(pb, a) for a in unseen_albedo(pb, lv)]

    def column(a: np.ndarray, g: np.ndarray) -> list:
        """Each channel's column of a lamp lighting the points ``a`` and the unseen cells ``g``."""
        return [a + pb.tr.A1 @ (Mc[c] @ (rho_c[c] * g)) for c in range(3)]

    def score(j: int, a: np.ndarray, g: np.ndarray) -> float:
        """Stage 3's objective with lamp ``j`` lighting the points ``a`` and the unseen cells ``g``."""
        cj = [col.copy() for col in cols]
        for c, col in enumerate(column(a, g)):
            cj[c][:, nr + j] = col
        return float(alternate(pb, lv, Ekc, cj, lbp, lamp, 0.0, 2, rows=srows)[3].sum())

    for j, (c, u, v, depth) in rect.items():
        nq[j] = _polish_one(pb, nq, nn, j, c, u, v, depth, score, seed)
        An[:, j], Gn[:, j] = lamp_columns(pb, nq[j], nn[j], seed)
        for ch, col in enumerate(column(An[:, j], Gn[:, j])):
            cols[ch][:, nr + j] = col
    return nq, nn, Gn, len(rect)


def _polish_start(lq: np.ndarray, ln: np.ndarray, Gk: np.ndarray, groups: list, todo: list, power: np.ndarray,
                  depth_l: np.ndarray, size: float) -> tuple:
    """The lamps the polish starts from: one square of ``size`` per cluster of ``todo`` (where its first lamp
    was; at the cluster's light, in the plane of its brightest lamp), the rest as they are. Returns their
    corners (J', 4, 3), normals, light at the unseen cells (None: a new square's, to compute) and the squares to
    polish: {index: (centre, edge u, edge v, depth below its cell)}."""
    first = {int(groups[i][0]): i for i in todo}
    gone = {int(j) for i in todo for j in groups[i][1:]}
    rect, nq, nn, ng = {}, [], [], []
    for j in range(len(lq)):
        if j in gone:
            continue
        if j in first:
            g = groups[first[j]]
            at = int(np.argmax(power[g]))
            c, u, v = cluster_start(lq[g], power[g], at)      # in lamp at's plane: its depth
            rect[len(nq)] = (c, u, v, float(depth_l[g[at]]))
            nq.append(rectangle(c, u, v, 0.5 * size, 0.5 * size))
            ng.append(None)
        else:
            nq.append(lq[j])
            ng.append(Gk[:, j])
        nn.append(ln[j])
    return np.asarray(nq), np.asarray(nn), ng, rect


def lamp_columns(pb: Problem, q: np.ndarray, nrm: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """One lamp's (corners ``q``, normal ``nrm``) light at stage 1's points and at the unseen cells, with the same
    samples every time (``seed``: the search compares places, not noise)."""
    room, srows = pb.room, pb.tr.srows
    a = quad_columns(room.isect, pb.pts.P[srows], pb.pts.N[srows], q[None], nrm[None], pb.st.emitter_samples,
                     np.random.default_rng(seed), room.eps)
    return a[:, 0], cell_columns(pb, q[None], nrm[None], np.random.default_rng(seed + 1))[:, 0]


def _polish_one(pb: Problem, nq: np.ndarray, nn: np.ndarray, j: int, c: np.ndarray, u: np.ndarray, v: np.ndarray,
                depth: float, score, seed: int) -> np.ndarray:
    """Lamp ``j``'s rectangle (of the lamps ``nq``, normals ``nn``), from the square about ``c`` (edges ``u``,
    ``v``) ``depth`` below its ceiling cell: first its height on a grid POLISH_DEPTH_STEP_M apart, then height,
    place and half sizes (1 cm to a cell) by :func:`coordinate_search` on ``score``; within REFINE_DEPTHS of the
    cell, in free space no photo saw (:func:`hang_ok`), over no other lamp (in the trace the lamps are geometry:
    one under another shades it)."""
    room, st = pb.room, pb.st
    n_ = nn[j]
    blo, bhi = room.box_v.min(axis=0), room.box_v.max(axis=0)
    others = [k for k in range(len(nq)) if k != j and nn[k] @ n_ > 0.999]

    def place(x: np.ndarray) -> tuple[np.ndarray, float]:
        return c + x[0] * n_ + x[1] * u + x[2] * v, depth + x[0]

    def valid(x: np.ndarray) -> bool:
        centre, d = place(x)
        for k in others:   # no other lamp facing the same way may overlap it, seen along the normal
            o = nq[k].mean(axis=0) - centre
            ext_u = 0.5 * np.abs((nq[k][2] - nq[k][0]) @ u) + np.exp(x[3])
            ext_v = 0.5 * np.abs((nq[k][2] - nq[k][0]) @ v) + np.exp(x[4])
            if abs(o @ u) < ext_u and abs(o @ v) < ext_v:
                return False
        if d <= 1e-9:   # at the ceiling cell: inside the box
            return bool(np.all(centre >= blo - 1e-6) and np.all(centre <= bhi + 1e-6))
        return bool(centre @ room.up >= room.h_low + LAMP_MIN_M
                    and hang_ok(room.isect, centre[None], n_[None], np.array([d]), room.cameras, room.eps)[0])

    def evaluate(x: np.ndarray) -> float:
        centre, _ = place(x)
        return score(j, *lamp_columns(pb, rectangle(centre, u, v, np.exp(x[3]), np.exp(x[4])), n_, seed))

    lmin, lmax = np.log(POLISH_MIN_HALF_M), np.log(st.cell)
    x0 = np.array([0.0, 0.0, 0.0, np.log(0.5 * st.refine), np.log(0.5 * st.refine)])
    lo = np.array([-depth, -st.cell, -st.cell, lmin, lmin])
    hi = np.array([REFINE_DEPTHS[-1] - depth, st.cell, st.cell, lmax, lmax])
    ok = [t for t in np.arange(lo[0], hi[0] + 1e-9, POLISH_DEPTH_STEP_M) if valid(np.r_[t, x0[1:]])]
    fs = [evaluate(np.r_[t, x0[1:]]) for t in ok[:max(st.polish // 2, 1)]]
    if fs:
        x0[0] = ok[int(np.argmin(fs))]
    x, _, _ = coordinate_search(evaluate, x0, np.array(POLISH_STEPS), lo, hi, valid, st.polish - len(fs))
    centre, _ = place(x)
    return rectangle(centre, u, v, np.exp(x[3]), np.exp(x[4]))


def hang_ok(isect, cen: np.ndarray, nrm: np.ndarray, depth: np.ndarray, cams: list, eps: float) -> np.ndarray:
    """(C,) bool: a lamp centred at ``cen (C, 3)``, hanging ``depth (C,)`` metres along its normal ``nrm (C, 3)``
    below its ceiling cell, has free space up to that cell and no photo (``cams``) saw where it hangs."""
    ok = np.ones(len(cen), bool)
    if not len(cen):
        return ok
    dn = -np.asarray(nrm, np.float64)
    ok &= ~isect.occluded((cen + eps * dn).astype(np.float32), dn.astype(np.float32),
                          (np.asarray(depth, np.float64) - 2 * eps).astype(np.float32))
    for cam in cams:
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            break
        uv, z = cam.project(cen[idx])
        inside = (z > 1e-6) & np.all((uv >= 0) & (uv < [cam.width, cam.height]), axis=1)
        j = idx[inside]
        if j.size == 0:
            continue
        t = np.asarray(cam.center, np.float64)
        dv = cen[j] - t
        dist = np.linalg.norm(dv, axis=1)
        seen = ~isect.occluded(np.repeat(t[None], j.size, axis=0).astype(np.float32),
                               (dv / dist[:, None]).astype(np.float32), (dist - eps).astype(np.float32))
        ok[j[seen]] = False
    return ok


def lamp_candidates(isect, cells: np.ndarray, BV: np.ndarray, bnrm: np.ndarray, upv: np.ndarray, size: float,
                    h_min: float, cams: list, eps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Small lamps an emitting box cell may stand for: the cell cut into squares of about ``size`` metres, and
    for a ceiling cell the same squares hung ``REFINE_DEPTHS`` below it, in free space no photo saw
    (``cams``: the photos' :class:`~pipeline.camera.Camera`) and at least ``h_min`` high. Returns corners (C, 4, 3),
    normals (C, 3) and the cell each came from (C,)."""
    quads, nrm, parent, depth = [], [], [], []
    for c in cells:
        q = BV[4 * c: 4 * c + 4]
        a, b = q[1] - q[0], q[3] - q[0]
        na = max(1, int(round(np.linalg.norm(a) / size)))
        nb_ = max(1, int(round(np.linalg.norm(b) / size)))
        ceiling = float(bnrm[c] @ upv) < -0.5
        for d in (REFINE_DEPTHS if ceiling else (0.0,)):
            for i in range(na):
                for j in range(nb_):
                    o = q[0] + (i / na) * a + (j / nb_) * b + d * bnrm[c]
                    quads.append(np.stack([o, o + a / na, o + a / na + b / nb_, o + b / nb_]))
                    nrm.append(bnrm[c])
                    parent.append(c)
                    depth.append(d)
    if not quads:
        return np.zeros((0, 4, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    quads, nrm, parent, depth = np.asarray(quads), np.asarray(nrm), np.asarray(parent), np.asarray(depth)
    cen = quads.mean(axis=1)
    hung = depth > 0
    keep = ~hung | (cen @ upv >= h_min)
    idx = np.flatnonzero(hung & keep)
    keep[idx] = hang_ok(isect, cen[idx], nrm[idx], depth[idx], cams, eps)
    return quads[keep], nrm[keep], parent[keep]


def lamp_clusters(quads: np.ndarray, nrm: np.ndarray, size: float) -> list[np.ndarray]:
    """The lamps (corners ``quads (C, 4, 3)``, normals ``nrm (C, 3)``) that touch, as index arrays: facing one way,
    centres within 1.5 x ``size`` of one another across the normal (diagonal neighbours too), at any height along
    it (squares hung one above another light the room as one lamp, and a lamp under another would shade it).
    Each cluster's lamps in order, the clusters by their first lamp."""
    cen = np.asarray(quads, np.float64).mean(axis=1)
    root = np.arange(len(cen))

    def find(i: int) -> int:
        while root[i] != i:
            i = root[i]
        return i

    for i in range(len(cen)):
        d = cen[i + 1:] - cen[i]
        d = d - np.outer(d @ nrm[i], nrm[i])
        near = (nrm[i + 1:] @ nrm[i] > 0.999) & (np.linalg.norm(d, axis=1) <= 1.5 * size)
        for j in i + 1 + np.flatnonzero(near):
            root[find(int(j))] = find(i)
    labels = np.array([find(i) for i in range(len(cen))], np.int64)
    return [np.flatnonzero(labels == r) for r in sorted(set(labels.tolist()))]


def rectangle(centre: np.ndarray, u: np.ndarray, v: np.ndarray, hu: float, hv: float) -> np.ndarray:
    """(4, 3) corners of the rectangle about ``centre`` with unit edges ``u``, ``v`` and half sizes ``hu``, ``hv``,
    in the order of the squares :func:`lamp_candidates` cuts (corner, + u, + u + v, + v)."""
    o = centre - hu * u - hv * v
    return np.stack([o, o + 2 * hu * u, o + 2 * hu * u + 2 * hv * v, o + 2 * hv * v])


def cluster_start(quads: np.ndarray, power: np.ndarray, at: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the polish starts a cluster of lamps ``quads (m, 4, 3)`` (parallel, facing one way; emitted power
    ``power (m,)``): the power-weighted centre of their centres seen along the normal, in the plane of lamp
    ``at``; and the unit edges u, v of the first."""
    q = np.asarray(quads, np.float64)
    u = q[0, 1] - q[0, 0]
    v = q[0, 3] - q[0, 0]
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    cen = q.mean(axis=1)
    pw = np.maximum(np.asarray(power, np.float64), 0.0)
    wt = pw / pw.sum() if pw.sum() > 0 else np.full(len(q), 1.0 / len(q))
    d = wt @ (cen - cen[at])
    return cen[at] + (d @ u) * u + (d @ v) * v, u, v


def coordinate_search(evaluate, x0: np.ndarray, steps: np.ndarray, lo: np.ndarray, hi: np.ndarray, valid,
                      budget: int, halvings: int = POLISH_HALVINGS) -> tuple[np.ndarray, float, int]:
    """Minimise ``evaluate(x)`` from ``x0`` one coordinate at a time: steps one way while they lower it, else
    the other way (within ``lo``, ``hi`` and where ``valid(x)``); when a sweep over the coordinates lowers
    nothing, every step halves, ``halvings`` times. Stops early where a whole sweep changes nothing at all (the
    value does not depend on x) and after ``budget`` evaluations. Returns the best x, its value and the
    evaluations made."""
    x = np.asarray(x0, np.float64).copy()
    best = float(evaluate(x))
    n = 1
    step = np.asarray(steps, np.float64).copy()
    h = 0
    while h <= halvings and n < budget:
        better, moved = False, False
        for k in np.flatnonzero(step > 0):
            for sign in (1.0, -1.0):
                went = False
                while n < budget:
                    y = x.copy()
                    y[k] = np.clip(x[k] + sign * step[k], lo[k], hi[k])
                    if y[k] == x[k] or not valid(y):
                        break
                    f = float(evaluate(y))
                    n += 1
                    moved |= f != best
                    if f >= best:
                        break
                    best, x, better, went = f, y, True, True
                if went:
                    break
        if not moved:
            break
        if not better:
            step /= 2
            h += 1
    return x, best, n
