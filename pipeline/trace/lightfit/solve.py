"""Step 5, the solve: the unknowns' emission by non-negative least squares with a sparsity prior, alternated
with the patches' albedo, at each channel's albedo level.

At the fit's points ``L = rho / pi * (E_known + A e)``. The least squares are relative (each point weighed by
its neighbourhood's photo level, :func:`~pipeline.trace.lightfit.albedo.relative_weights`), and an L1 prior on
the emission (each unknown weighed by the light it sends to the points, as a lasso on normalised columns is)
prefers few, bright emitters. The unseen cells reflect as well as emit: their radiance is
``L_u = (I - rho_u / pi G)^-1 (e + rho_u / pi Eu)``, their albedo the upper walls' (the ceiling's white paint
on the box's top), so only emission pays the prior. Each solve alternates the emission (all emitters one
colour per kind, :mod:`pipeline.trace.lightfit.colour`) with the patch albedo, whose overall level per channel
the caller holds fixed.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from pipeline.color import LUMINANCE_F64
from pipeline.trace.lightfit.albedo import ALBEDO_RANGE, albedo_patches, relative_weights
from pipeline.trace.lightfit.closure import Room, sheet_backs
from pipeline.trace.lightfit.colour import colour_clipped, shared_colour
from pipeline.trace.lightfit.nnls import nnls
from pipeline.trace.lightfit.observe import FitPoints
from pipeline.trace.lightfit.settings import FitSettings
from pipeline.trace.lightfit.transport import Transport, in_order
from pipeline.trace.lightfit.unknowns import Unknowns

PRIOR_ALBEDO = 0.5            # albedo at which the sparsity prior's weight is measured against the data term
SLIVER_SHARE = 0.02           # an unknown the points see less than this share as well as expected is not fitted


@dataclass(frozen=True)
class Problem:
    """Everything the emission and albedo solves read: the room, its unknowns, the points and the transport,
    with the albedo patches, the least-squares weights and the prior."""

    room: Room
    unk: Unknowns
    pts: FitPoints
    tr: Transport
    st: FitSettings
    patch: np.ndarray          # (n,) int64 albedo patch of each point
    npatch: int
    backs: object              # (n, npatch + 1) scipy.sparse, light from the sheets' unseen sides per unit albedo
    w: np.ndarray              # (n,) float64 least-squares weight of each point (relative)
    lam_k: np.ndarray          # (K,) float64 prior weight of each unknown (per unit of the prior's scale)
    active: np.ndarray         # (k,) int64 unknowns the fit may light (sending light to the points, no sliver)
    med: float                 # the median unknown's column norm on stage 1's points
    dens: float                # ... per m^2 of its area
    reflect: np.ndarray        # (K,) float64 1 where an unknown reflects with the unseen walls' albedo
    ceiling: np.ndarray        # (K,) float64 1 where it reflects with the ceiling's (the box's top)
    unseen_ratio: np.ndarray   # (3,) float64 the unseen walls' albedo over the room's level (1 until known)
    edge_colour: np.ndarray | None  # (3,) colour of the lights seen clipped, from their edges
    summary: dict = field(default_factory=dict)   # what was set up (JSON-able)


@dataclass(frozen=True)
class Fit:
    """The emission and albedo at one set of albedo levels (:func:`fit_at`)."""

    e: np.ndarray              # (K, 3) float64 emission of the unknowns
    Lu: np.ndarray             # (K, 3) float64 radiance of the unknowns: emitted and reflected
    E: np.ndarray              # (rows, 3) float64 irradiance at the points
    rho: np.ndarray            # (npatch, 3) float64 patch albedo
    obj: np.ndarray            # (3,) float64 each channel's objective: data and prior
    raised: float | None       # the most the edges' colour raised a clipped light (None: not coloured)


def make_problem(room: Room, unk: Unknowns, pts: FitPoints, tr: Transport, edge_colour, st: FitSettings) -> Problem:
    """The :class:`Problem` of the unknowns ``unk`` at the points ``pts`` with transport ``tr``."""
    K, nbu = unk.K, unk.nbu
    reflect = np.zeros(K)
    reflect[:nbu] = 1.0                      # clipped mesh regions are lamps: they do not reflect here
    ceiling = np.zeros(K)                    # the ceiling's cells reflect as white paint, whatever the walls
    if st.ceiling_albedo > 0:
        ceiling[:nbu] = room.ceiling_cell[unk.box_unknown]
        reflect -= ceiling
    patch, npatch, cells = albedo_patches(pts.P, pts.N, pts.L, st.albedo_cell, st.albedo_group)
    backs = sheet_backs(pts.P, pts.N, patch, npatch, tr.back_owner, tr.back_pos, tr.back_normal, st.albedo_cell,
                        np.pi / st.gather_rays)
    w = relative_weights(pts.P, pts.N, pts.L @ LUMINANCE_F64)
    # the prior weighs each unknown by how much light it sends to the photographed points (its column's norm):
    # weighing emitted power instead favours cells close to the points, which explain them with the least power
    cn = np.linalg.norm(tr.A1, axis=0) if K else np.zeros(0)
    med = float(np.median(cn[cn > 0])) if (cn > 0).any() else 1.0
    seen_ok, lam_k = sliver_rule(cn, np.full(K, med), med)
    active = tr.active[seen_ok[tr.active]]
    # the median cell's column per unit of its area (stage 3's lamps are held to it)
    dens = float(np.median(cn[active] / np.maximum(unk.area_k[active], 1e-12))) if active.size else 0.0
    return Problem(room=room, unk=unk, pts=pts, tr=tr, st=st, patch=patch, npatch=npatch, backs=backs, w=w,
                   lam_k=lam_k, active=active, med=med, dens=dens, reflect=reflect, ceiling=ceiling,
                   unseen_ratio=np.ones(3), edge_colour=edge_colour,
                   summary={"ceiling_cells": int(ceiling.sum()), "albedo_cells": cells, "albedo_patches": npatch})


def sliver_rule(norms: np.ndarray, expected: np.ndarray, med: float) -> tuple[np.ndarray, np.ndarray]:
    """The sparsity prior's guard against unknowns the points see only through slivers (a gap between the
    mesh and the box, a grazing angle, a box square behind a wall): their columns ``norms`` are tiny, so
    they would explain anything with implausible radiance at no cost. Each is priced (weight relative to
    the median cell's column ``med``) at least as if it were seen as well as ``expected`` (the median cell,
    or for a lamp the median cell per unit area times its own area), and those under SLIVER_SHARE of that
    are not fitted at all. Returns (fitted?, price)."""
    expected = np.asarray(expected, np.float64)
    return norms >= SLIVER_SHARE * expected, np.maximum(norms, expected) / max(med, 1e-12)


def prior_scale(A: np.ndarray, w: np.ndarray) -> float:
    """The sparsity prior's scale for columns ``A (n, K)`` at points of weights ``w``: the data term's mean
    column norm squared at ``PRIOR_ALBEDO`` (1 without columns)."""
    return float(np.mean(np.sum((A * (w * PRIOR_ALBEDO / np.pi)[:, None]) ** 2, axis=0))) if A.shape[1] else 1.0


def _channel_solves(rho_pt, Ek, A_ch, L, w, lb, lam_k, sparsity, scale, pool) -> tuple[np.ndarray, np.ndarray, list]:
    """Each channel's emission solved on its own: the emission (K, 3), the prior's cost per channel (3,) and
    each channel's (B, y, Q, g, prior weights) for :func:`~pipeline.trace.lightfit.colour.shared_colour`."""
    K = A_ch[0].shape[1]
    e = np.zeros((K, 3))
    cost = np.zeros(3)

    def gram(ch: int) -> tuple:
        s = w * rho_pt[:, ch] / np.pi                   # row scale
        B = A_ch[ch] * s[:, None]
        return s, B, B.T @ B

    # channels with the same columns and albedo (stage 1's searches start each level grey) share one product,
    # the solve's largest: the same bytes, once
    lead = [next(c for c in range(ch + 1) if A_ch[c] is A_ch[ch] and np.array_equal(rho_pt[:, c], rho_pt[:, ch]))
            for ch in range(3)]
    shared = {c: gram(c) for c in set(lead) if lead.count(c) > 1}

    def channel(ch: int) -> tuple:
        A = A_ch[ch]
        s, B, Q = shared[lead[ch]] if lead[ch] in shared else gram(ch)
        y = w * L[:, ch] - s * (Ek[:, ch] + A @ lb[:, ch])
        g = B.T @ y
        # the prior's weight is the data term's scale at a fixed albedo, not at the level being tried: scaled
        # with the level it would price the light a low level needs below a high level's
        sc = (1.0 if sparsity == 0 else scale[ch] if isinstance(scale, (list, tuple)) else
              scale if scale is not None else prior_scale(A, w))
        lam = sparsity * sc * lam_k
        return (B, y, Q, g, lam), nnls(Q, g, lam)

    parts = []
    for ch, (part, x) in enumerate(in_order([functools.partial(channel, ch) for ch in range(3)], pool)):
        e[:, ch] = lb[:, ch] + x
        cost[ch] = float(part[4] @ x)      # the prior's part of the objective (the data part: the caller's)
        parts.append(part)
    return e, cost, parts


def solve_channels(rho_pt: np.ndarray, Ek: np.ndarray, A_ch, L: np.ndarray, w: np.ndarray, lb: np.ndarray,
                   lam_k: np.ndarray, sparsity: float, scale: float | list | None = None,
                   pool=None) -> tuple[np.ndarray, np.ndarray]:
    """Emission (K, 3) >= lb minimising, channel by channel, the weighted residual of ``L = rho/pi (Ek + A e)``
    (``rho_pt (n, 3)`` each point's albedo, ``A_ch`` each channel's columns (n, K), ``w (n,)`` the weights) plus
    an L1 prior on emitted power (``sparsity x scale x lam_k``; ``scale`` one for all channels, one per channel,
    or by default each channel's :func:`prior_scale`, not computed where ``sparsity`` is 0); returns it and the
    prior's value per channel (3,). The channels' products and solves run on ``pool``'s threads if given (the
    caller's own thread must not be one of them)."""
    e, cost, _ = _channel_solves(rho_pt, Ek, A_ch, L, w, lb, lam_k, sparsity, scale, pool)
    return e, cost


def solve_emission(rho_pt: np.ndarray, Ek: np.ndarray, A_ch, L: np.ndarray, w: np.ndarray, lb: np.ndarray,
                   lam_k: np.ndarray, sparsity: float, scale: float | list | None = None,
                   pool=None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`solve_channels`, the emission above the lower bound then one colour per kind of unknown
    (:func:`~pipeline.trace.lightfit.colour.shared_colour`): those the photos saw clipped (a positive lower
    bound) and those no photo saw. Returns the emission (K, 3) and the prior's value per channel (3,)."""
    e, cost, parts = _channel_solves(rho_pt, Ek, A_ch, L, w, lb, lam_k, sparsity, scale, pool)
    if A_ch[0].shape[1]:
        x, col = shared_colour(parts, e - lb, (lb.max(axis=1) > 0).astype(np.int64))
        e = lb + x[:, None] * col
        cost = np.array([float(parts[c][4] @ (x * col[:, c])) for c in range(3)])
    return e, cost


def unseen_albedo(pb: Problem, level: np.ndarray) -> np.ndarray:
    """(3,) albedo of the unseen cells at the room's albedo levels ``level (3,)``."""
    return np.clip(np.asarray(level, np.float64) * pb.unseen_ratio, *ALBEDO_RANGE)


def rho_unknown(pb: Problem, albedo_c: float) -> np.ndarray:
    """(K,) albedo over pi of the unknowns when the unseen side cells' albedo is ``albedo_c`` (the ceiling's
    is ``ceiling_albedo``; clipped regions do not reflect)."""
    return (albedo_c * pb.reflect + pb.st.ceiling_albedo * pb.ceiling) / np.pi


def inverse_transport(pb: Problem, albedo_c: float) -> np.ndarray:
    """(K, K) ``(I - rho_u / pi G)^-1`` for an unseen cell albedo of ``albedo_c``: the unknowns' radiance per
    unit of their own emission and of the light they receive from the known room."""
    return np.linalg.inv(np.eye(pb.unk.K) - rho_unknown(pb, albedo_c)[:, None] * pb.tr.G)


def design(pb: Problem, level: np.ndarray, cols: np.ndarray, fixed: np.ndarray, extra: np.ndarray | None = None,
           rows: np.ndarray | None = None) -> tuple[list, list, np.ndarray]:
    """Per channel at albedo levels ``level (3,)``: the transport of the unknown cells, the irradiance at
    the points per unit emission of the unknowns ``cols`` (then of the ``extra (K, J)`` sources that
    light the unseen cells, if given), and the known light at the points: direct, reflected once more by
    the unseen cells, and sent by the unknowns ``fixed`` at their lower bound. Only the columns asked for
    are multiplied out: A (M x) costs the points x K per column, (A M) the points x K x K. ``rows``:
    all points (None), or a subset (stage 1's ``srows``, or stage 3's)."""
    tr, lb = pb.tr, pb.unk.lb
    Ar, Ekr = (tr.A, tr.Ek) if rows is None else (tr.A1, tr.Ek[tr.srows]) if rows is tr.srows else (tr.A[rows],
                                                                                                       tr.Ek[rows])
    ua = unseen_albedo(pb, level).tolist()
    Ms = {a: inverse_transport(pb, a) for a in set(ua)}
    Mc = [Ms[a] for a in ua]
    Ac = {}
    for a, M in Ms.items():
        rhs = M[:, cols] if extra is None else np.concatenate([M[:, cols], M @ (rho_unknown(pb, a)[:, None] * extra)],
                                                              1)
        Ac[a] = Ar @ rhs
    Ae = [Ac[a] for a in ua]
    Ekc = np.stack([Ekr[:, c] + Ar @ (Mc[c] @ (rho_unknown(pb, ua[c]) * tr.Eu[:, c]) + Mc[c][:, fixed] @ lb[fixed, c])
                    for c in range(3)], axis=1)
    return Mc, Ae, Ekc


def sheet_light(pb: Problem, br, albedo: np.ndarray) -> np.ndarray:
    """(rows, 3) irradiance the sheets' unseen sides send the points of ``br`` (rows of ``pb.backs``) at
    albedo ``albedo (npatch + 1, 3)``: each patch's, then the room's level."""
    return (br @ albedo) * pb.unk.low_rad[None, :]


def alternate(pb: Problem, level: np.ndarray, Ekc: np.ndarray, cols: list, lbj: np.ndarray, lamj: np.ndarray,
              sparsity: float, iters: int, scale: float | list | None = None, rows: np.ndarray | None = None,
              on=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Alternate the emission of columns ``cols`` (per channel (n, J): irradiance at the points per unit
    radiance, bounded below by ``lbj``, prior weights ``lamj``) and the patch albedo, each channel's albedo
    level held at ``level (3,)``; ``Ekc`` the irradiance nothing fitted here sends. Returns the emission (J, 3),
    the patch albedo, the irradiance at the points and each channel's objective (channels are independent).
    ``rows``: the points ``Ekc`` and ``cols`` are given for (all by default). ``on``: the pool for the
    channels' solves, where this runs outside it (the fits between the level searches)."""
    pt, wr, Lr, br = pb.patch, pb.w, pb.pts.L, pb.backs
    if rows is not None:
        pt, wr, Lr, br = pb.patch[rows], pb.w[rows], pb.pts.L[rows], pb.backs[rows]
    rho = np.tile(level, (pb.npatch, 1))
    ej = lbj.copy()
    Ek0 = Ekc

    def known(rho: np.ndarray) -> np.ndarray:
        """``Ekc`` and the light the sheets' unseen sides send at patch albedo ``rho`` (the level where
        no patch is near)."""
        return Ek0 + sheet_light(pb, br, np.vstack([rho, level[None]]))

    Ekc = known(rho)
    if scale is None and sparsity != 0:   # the prior's scale does not change with the albedo: once
        scale = [prior_scale(cols[c], wr) for c in range(3)]
    l1 = np.zeros(3)
    for _ in range(iters):
        ej, l1 = solve_emission(rho[pt], Ekc, cols, Lr, wr, lbj, lamj, sparsity, scale, on)
        E = Ekc + np.stack([cols[c] @ ej[:, c] for c in range(3)], axis=1)
        rho = _patch_albedo(pt, wr, Lr, E, level, pb.npatch)
        Ekc = known(rho)
    E = Ekc + np.stack([cols[c] @ ej[:, c] for c in range(3)], axis=1)
    pred = rho[pt] / np.pi * E
    res = np.sum((wr[:, None] * (pred - Lr)) ** 2, axis=0)
    return ej, rho, E, res + 2 * l1          # the objective: data + few-bright-emitters prior


def _patch_albedo(pt: np.ndarray, wr: np.ndarray, Lr: np.ndarray, E: np.ndarray, level: np.ndarray,
                  npatch: int) -> np.ndarray:
    """(npatch, 3) albedo of each patch that best explains its points' radiance ``Lr`` under irradiance ``E``
    (weights ``wr``; ``level`` where a patch gets no light), within ALBEDO_RANGE and rescaled so that each
    channel's geometric mean is ``level``: the search over levels sets the level, the alternation the pattern."""
    rho_new = np.empty((npatch, 3))
    for ch in range(3):
        num = np.bincount(pt, weights=wr * wr * Lr[:, ch] * E[:, ch], minlength=npatch)
        den = np.bincount(pt, weights=wr * wr * E[:, ch] ** 2, minlength=npatch)
        rho_new[:, ch] = np.where(den > 0, np.pi * num / np.maximum(den, 1e-30), level[ch])
    rho_new = np.clip(rho_new, *ALBEDO_RANGE)
    lvl = np.exp(np.mean(np.log(rho_new), axis=0))
    return np.clip(rho_new * (level / np.maximum(lvl, 1e-9)), *ALBEDO_RANGE)


def fit_at(pb: Problem, level: np.ndarray, iters: int = 4, active: np.ndarray | None = None,
           sparsity: float | None = None, rows: np.ndarray | None = None, on=None, final: bool = False) -> Fit:
    """Emission of the unknowns ``active`` (default ``pb.active``; the others stay at their lower bound) and
    albedo at each channel's albedo level ``level (3,)``, with the prior's weight ``sparsity`` (default the
    settings'), on the points ``rows`` (all by default). ``final``: the fit's answer (the lights seen clipped
    take their edges' colour, where the photos show it)."""
    active = pb.active if active is None else active
    sparsity = pb.st.sparsity if sparsity is None else sparsity
    lb = pb.unk.lb
    Mc, Ae, Ekc = design(pb, level, active, np.setdiff1d(np.arange(pb.unk.K), active), rows=rows)
    ea, rho, E, obj = alternate(pb, level, Ekc, Ae, lb[active], pb.lam_k[active], sparsity, iters, rows=rows, on=on)
    e = lb.copy()
    e[active] = ea
    raised = colour_clipped(e, lb, pb.edge_colour) if final else None
    ua = unseen_albedo(pb, level)
    Lu = np.stack([Mc[c] @ (e[:, c] + rho_unknown(pb, ua[c]) * pb.tr.Eu[:, c]) for c in range(3)], axis=1)
    return Fit(e=e, Lu=Lu, E=E, rho=rho, obj=obj, raised=raised)
