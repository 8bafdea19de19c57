"""The fit's stages: where the light comes from, which few emitters carry it, and at which albedo levels.

1. Emission anywhere, priced by the sparsity prior; each channel's albedo level the highest (the least light)
   that explains the photos within ``level_tolerance`` of the best: with emission free everywhere the level is
   barely identifiable. The unseen walls then reflect like the upper walls the photos saw under that light.
2. Only the unknowns carrying ``support_share`` of that power emit (at most ``max_emitters``), the rest reflect;
   with the emitters pinned, the light the room's surfaces send each other identifies each channel's level.
3. Lamps smaller than a cell (:mod:`pipeline.trace.lightfit.lamps`), where ``refine`` is on.
With every light handed in (``known_complete``) nothing else emits and only the levels are searched.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field

import numpy as np

from pipeline.color import LUMINANCE_F64
from pipeline.trace.lightfit.albedo import (ALBEDO_LEVELS, curve_minimum, finite, level_search,
                                            level_search_with_power, wall_ratio, white_levels, within)
from pipeline.trace.lightfit.lamps import refine
from pipeline.trace.lightfit.solve import Problem, fit_at, sheet_light


@dataclass(frozen=True)
class Solution:
    """The fit's answer: the unknowns' emission, the lamps, the albedo and the levels."""

    e: np.ndarray              # (K, 3) float64 emission of the unknowns
    Lu: np.ndarray             # (K, 3) float64 their radiance: emitted and reflected
    E: np.ndarray              # (n, 3) float64 irradiance at the points
    rho: np.ndarray            # (npatch, 3) float64 patch albedo
    level: list | None         # albedo level per channel (None: nothing was fitted)
    res_curve: np.ndarray | list  # (len(ALBEDO_LEVELS),) objective (luminance) per level of the last search
    unseen_ratio: np.ndarray   # (3,) float64 the unseen walls' albedo over the level
    note: str = ""             # what was assumed where nothing could be fitted
    raised: float | None = None  # the most the edges' colour raised a clipped light (None: not coloured)
    lamp_q: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 3)))   # (J, 4, 3) stage 3's lamps
    lamp_n: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))      # (J, 3) their normals
    lamp_e: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))      # (J, 3) their radiance
    summary: dict = field(default_factory=dict)   # what was found (JSON-able)


def solve_lights(pb: Problem, rng: np.random.Generator, pool) -> Solution:
    """The :class:`Solution` of problem ``pb``: with the known lights complete, without anything to fit, or by
    the three stages."""
    if pb.room.known_quads and pb.st.known_complete:
        return known_complete(pb, pool)
    if pb.unk.K == 0 or pb.active.size == 0:
        # nothing unknown the points can see: the mesh and observed holes are the light (scan lighting)
        return Solution(e=pb.unk.lb.copy(), Lu=pb.unk.lb.copy(), rho=np.full((pb.npatch, 3), 0.5),
                        E=pb.tr.Ek + sheet_light(pb, pb.backs, np.full((pb.npatch + 1, 3), 0.5)),
                        level=None, res_curve=[], unseen_ratio=pb.unseen_ratio,
                        note="no unseen or clipped light source visible from the photographed surfaces: lit by "
                             "the scan itself")
    return staged(pb, rng, pool)


def _walls(pb: Problem, E: np.ndarray, level: np.ndarray, rows=None) -> Problem:
    """``pb`` with the unseen walls reflecting like the upper walls the points ``rows`` (all by default) show
    under irradiance ``E`` at levels ``level`` (:func:`~pipeline.trace.lightfit.albedo.wall_ratio`)."""
    P, N, L, w = pb.pts.P, pb.pts.N, pb.pts.L, pb.w
    if rows is not None:
        P, N, L, w = P[rows], N[rows], L[rows], w[rows]
    ratio = wall_ratio(L, E, w, N @ pb.room.up, P @ pb.room.up - pb.room.h_low, level)
    return dataclasses.replace(pb, unseen_ratio=np.array(ratio, np.float64))


def known_complete(pb: Problem, pool) -> Solution:
    """The lights handed in are every light in the room (``known_complete``): nothing else emits (the unknown
    cells reflect; those the photos saw clipped keep their lower bound), and with the lights' power and colour
    given, each channel's albedo level is where the photos are explained best (a parabola through the grid's
    lowest residual). Searched twice: the unseen walls reflect like the upper walls under the first level's light."""
    nothing = np.zeros(0, np.int64)
    for again in (True, False):
        def objective(lv: float, pb: Problem = pb) -> np.ndarray:
            return fit_at(pb, np.full(3, lv), iters=2, active=nothing, sparsity=0.0).obj

        res_curve = level_search(objective, pool)
        best_level = curve_minimum(np.asarray(ALBEDO_LEVELS), res_curve)
        f = fit_at(pb, best_level, iters=3, active=nothing, sparsity=0.0, on=pool)
        if again:
            pb = _walls(pb, f.E, best_level)
    return Solution(e=f.e, Lu=f.Lu, E=f.E, rho=f.rho, level=[float(x) for x in best_level],
                    res_curve=res_curve @ LUMINANCE_F64, unseen_ratio=pb.unseen_ratio,
                    summary={"unseen_albedo_ratio": [round(float(x), 4) for x in pb.unseen_ratio]})


def staged(pb: Problem, rng: np.random.Generator, pool) -> Solution:
    """Stage 1 (where the light is) on every other point, then stages 2 and 3 (:func:`few_emitters`); stage 1's
    answer fitted to all the points where there is no second stage. The levels of a search are independent:
    on the pool's threads, numpy's products run side by side."""
    st, srows = pb.st, pb.tr.srows
    summary: dict = {}

    def objective(lv: float, **kw) -> np.ndarray:
        return fit_at(pb, np.full(3, lv), iters=2, **kw).obj

    res_curve = level_search(functools.partial(objective, rows=srows), pool, st.level_tolerance)  # (levels, 3)
    ok = within(res_curve, st.level_tolerance)
    level1 = np.asarray(ALBEDO_LEVELS)[[int(np.flatnonzero(ok[:, c]).max()) for c in range(3)]]
    summary["stage1_residuals"] = finite(res_curve @ LUMINANCE_F64, 3)
    f = fit_at(pb, level1, iters=3, rows=srows, on=pool)
    # the unseen cells reflect like the upper walls under this light from here on
    pb = _walls(pb, f.E, level1, rows=srows)
    summary["unseen_albedo_ratio"] = [round(float(x), 4) for x in pb.unseen_ratio]
    sol = Solution(e=f.e, Lu=f.Lu, E=f.E, rho=f.rho, level=level1, res_curve=res_curve, unseen_ratio=pb.unseen_ratio)
    if st.max_emitters > 0:
        sol = few_emitters(pb, sol, level1, rng, pool, summary)
    if len(sol.E) < pb.pts.n:   # no second stage: stage 1's answer, fitted to all the points
        f = fit_at(pb, level1, iters=3, on=pool, final=True)
        sol = dataclasses.replace(sol, e=f.e, Lu=f.Lu, E=f.E, rho=f.rho, raised=f.raised)
    return dataclasses.replace(sol, level=[float(x) for x in sol.level], res_curve=sol.res_curve @ LUMINANCE_F64,
                               summary=summary)


def few_emitters(pb: Problem, sol: Solution, level1: np.ndarray, rng: np.random.Generator, pool,
                 summary: dict) -> Solution:
    """Stage 2 from stage 1's answer ``sol`` (at levels ``level1``): only the unknowns carrying
    ``support_share`` of its power (and the clipped regions) emit, each channel's level at the residual's
    minimum; then stage 3 where ``refine`` is on. ``summary`` takes what was found. ``sol`` unchanged where
    nothing emits."""
    st, unk, active = pb.st, pb.unk, pb.active
    pw = sol.e @ LUMINANCE_F64 * unk.area_k
    order = np.argsort(-pw)
    cum = np.cumsum(pw[order]) / max(float(pw.sum()), 1e-30)
    keep = order[:max(1, int(np.searchsorted(cum, st.support_share)) + 1)][:st.max_emitters]
    sup = np.union1d(np.intersect1d(keep, active), np.intersect1d(np.arange(unk.nbu, unk.K), active))
    if not sup.size:
        return sol

    def objective2(lv: float) -> tuple[np.ndarray, np.ndarray]:
        f2 = fit_at(pb, np.full(3, lv), iters=2, active=sup, sparsity=0.0)
        return f2.obj, unk.area_k @ f2.e

    res2, power2 = level_search_with_power(objective2, pool)
    best_level = np.asarray(ALBEDO_LEVELS)[np.argmin(res2, axis=0)]
    if st.refine <= 0 and st.white_prior > 0:   # stage 2 is the last: the light's colour prior
        best_level = white_levels(res2, power2, st.white_prior)
    f = fit_at(pb, best_level, iters=5, active=sup, sparsity=0.0, on=pool, final=True)
    summary["stage1_level"] = [float(x) for x in level1]
    summary["level_residuals_rgb"] = [finite(r) for r in (res2 / res2.min(axis=0)).T]
    summary["support_cells"] = int(sup.size)
    sol = dataclasses.replace(sol, e=f.e, Lu=f.Lu, E=f.E, rho=f.rho, level=best_level, res_curve=res2,
                              raised=f.raised)
    lamps = refine(pb, np.asarray(best_level), sup, rng, pool) if st.refine > 0 else None
    if lamps is not None:
        summary.update(lamps.summary)
        summary["stage2_residual"] = round(float(f.obj @ LUMINANCE_F64), 3)
        summary["stage3_residual"] = round(float(lamps.obj @ LUMINANCE_F64), 3)
        return dataclasses.replace(sol, e=lamps.e, Lu=lamps.Lu, E=lamps.E, rho=lamps.rho, lamp_q=lamps.quads,
                                   lamp_n=lamps.normals, lamp_e=lamps.emission, level=lamps.level,
                                   res_curve=lamps.res_curve, raised=lamps.raised)
    if st.refine > 0 and st.white_prior > 0:   # stage 3 found no lamps: stage 2 is the last
        best_level = white_levels(res2, power2, st.white_prior)
        f = fit_at(pb, best_level, iters=5, active=sup, sparsity=0.0, on=pool, final=True)
        sol = dataclasses.replace(sol, e=f.e, Lu=f.Lu, E=f.E, rho=f.rho, level=best_level, raised=f.raised)
    return sol
