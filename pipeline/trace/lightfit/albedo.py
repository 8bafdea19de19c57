"""Step 6, albedo patches and the albedo level: what a diffuse photo cannot tell from the light on its own.

Albedo is one RGB value per patch of the mesh: cells of ``albedo_cell`` metres facing one of six directions,
joined where their photo chromaticity falls in one bin (one material seen under different light,
:func:`chromaticity_groups`), so the light explains the difference in brightness, not the albedo. The room's
overall albedo level per channel is searched on a grid (:func:`level_search`); the light the known surfaces send
each other pins it. The last level is taken with a prior: the room's brightest surfaces toward grey
(:func:`grey_levels`), or the light's colour toward the photos' white (:func:`white_levels`), because each
channel's objective is nearly flat about its minimum while the light's colour follows the level steeply.
"""

from __future__ import annotations

import functools

import numpy as np

from pipeline.color import LUMINANCE_F64
from pipeline.trace.lightfit.closure import LOW_FILL_M, nearest_facing
from pipeline.trace.lightfit.observe import MIN_FIT_POINTS
from pipeline.trace.lightfit.transport import in_order

ALBEDO_RANGE = (0.02, 0.95)   # plausible diffuse albedo of room surfaces (linear, per channel)
# the room's albedo level (per channel, the geometric mean over the photographed patches) is searched over these;
# a room with deep red or green walls or a dark floor has a channel well below 0.15
ALBEDO_LEVELS = (0.05, 0.075, 0.1, 0.125, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7, 0.75,
                 0.8, 0.85)
WALL_COS = 0.3                # a fit point whose normal is this close to horizontal (cosine to up) is on a wall
WEIGHT_NEIGHBOURS = 16        # points whose median photo luminance sets a point's least-squares weight
NORMAL_METRES = 2.0           # ... in a space where a unit normal counts as this many metres
BRIGHT_SHARE = 0.1            # the brightest surfaces: the brightest patches until they hold this share of the points
BRIGHT_MIN_SHARE = 0.01       # ... each holding at least this share (a lamp's edge or a sliver is no surface)
WHITE_GRID = 400              # levels (and mean log powers) the coloured level searches interpolate on


def patch_keys(P: np.ndarray, N: np.ndarray, cell: float) -> np.ndarray:
    """(n, 4) int64 albedo patch of points ``P`` with normals ``N``: their cell of ``cell`` metres and their
    normal's dominant axis and sign."""
    ax = np.argmax(np.abs(N), axis=1)
    side = N[np.arange(len(N)), ax] > 0
    return np.concatenate([np.floor(P / cell).astype(np.int64), (ax * 2 + side)[:, None]], axis=1)


def chromaticity_groups(cell: np.ndarray, keyp: np.ndarray, L: np.ndarray, bin_size: float) -> tuple[np.ndarray, int]:
    """Albedo patches that join the albedo cells ``cell (n,)`` (of keys ``keyp``, :func:`patch_keys`) whose
    photo chromaticity (r and g of the cell's summed ``L``) falls in one bin of ``bin_size`` and whose
    normal has one axis and sign: (patch per point (n,), patches).

    A room is a few materials (one wood, one paint, one floor), each lit unevenly. With an albedo of its own,
    a cell explains its light with its albedo; one albedo per material, seen across cells under different
    light, makes the light explain the difference instead."""
    nc = int(cell.max()) + 1
    tot = np.stack([np.bincount(cell, L[:, c], minlength=nc) for c in range(3)], axis=1)
    chroma = tot[:, :2] / np.maximum(tot.sum(axis=1, keepdims=True), 1e-12)
    axis = np.zeros(nc, np.int64)
    axis[cell] = keyp[:, 3]
    key = np.concatenate([np.floor(chroma / bin_size).astype(np.int64), axis[:, None]], axis=1)
    _, group = np.unique(key, axis=0, return_inverse=True)
    group = group.ravel()
    return group[cell], int(group.max()) + 1


def albedo_patches(P: np.ndarray, N: np.ndarray, L: np.ndarray, cell: float, group: float) -> tuple:
    """The albedo patch of each point ``P`` (normals ``N``, radiance ``L``): cells of ``cell`` metres by their
    normal's dominant axis, joined by chromaticity bins of ``group`` (0: not joined). Returns (patch per point
    (n,) int64, patches, cells)."""
    keyp = patch_keys(P, N, cell)
    _, patch = np.unique(keyp, axis=0, return_inverse=True)
    patch = patch.ravel()
    cells = npatch = int(patch.max()) + 1
    if group > 0:
        patch, npatch = chromaticity_groups(patch, keyp, L, group)
    return patch, npatch, cells


def relative_weights(P: np.ndarray, N: np.ndarray, lum: np.ndarray, k: int = WEIGHT_NEIGHBOURS) -> np.ndarray:
    """(n,) weights that make the fit's least squares relative: one over the median photo luminance of each
    point's ``k`` nearest points (in position and normal, a unit normal counting as ``NORMAL_METRES``:
    the neighbours are on the same surface, not across a crease), plus a floor of 5 % of the median
    luminance.

    One over each point's own luminance is biased: texture makes the photo vary at one light, and the bright
    texels get less say, so the fitted albedo x light comes out low. The neighbours' median is the light's
    level there without the texture."""
    from scipy.spatial import cKDTree

    floor = 0.05 * float(np.median(lum)) + 1e-9
    if len(lum) <= k:
        return 1.0 / (lum + floor)
    X = np.concatenate([P, NORMAL_METRES * N], axis=1)
    _, nb = cKDTree(X).query(X, k=k)
    return 1.0 / (np.median(lum[nb.reshape(len(X), -1)], axis=1) + floor)


def wall_ratio(L: np.ndarray, E: np.ndarray, w: np.ndarray, cos_up: np.ndarray, height: np.ndarray,
               level: np.ndarray) -> np.ndarray:
    """(3,) albedo of the room's upper walls over its albedo level ``level (3,)``. The upper walls are the
    fit points whose normal is within WALL_COS of horizontal (``cos_up``: its cosine to up) at least
    LOW_FILL_M above the scan's lowest point (``height``); their albedo is the one that explains their
    photographed radiance ``L (n, 3)`` under the fitted irradiance ``E (n, 3)`` best (weights ``w``), as
    one patch. The unseen walls above the scan reflect with it: the level also counts the floor and the
    furniture, darker and warmer than walls. 1 with fewer than MIN_FIT_POINTS such points."""
    wall = (np.abs(cos_up) < WALL_COS) & (height >= LOW_FILL_M)
    if int(wall.sum()) < MIN_FIT_POINTS:
        return np.ones(3)
    ww = (w[wall] ** 2)[:, None]
    num = np.sum(ww * L[wall] * E[wall], axis=0)
    den = np.sum(ww * E[wall] ** 2, axis=0)
    walls = np.where(den > 0, np.pi * num / np.maximum(den, 1e-30), np.asarray(level, np.float64))
    return walls / np.maximum(np.asarray(level, np.float64), 1e-6)


def vertex_albedo(V: np.ndarray, F: np.ndarray, P: np.ndarray, N: np.ndarray, rho_p: np.ndarray,
                  level: np.ndarray, reach: float, k: int = 8) -> np.ndarray:
    """(V, 3) albedo of the mesh's vertices: that of the nearest fit point ``P`` (normals ``N``, albedo
    ``rho_p (n, 3)``) within ``reach`` metres on a surface facing the same way (the vertex's area-weighted
    normal within 60 degrees, either way round: a mesh's winding need not face the cameras); ``level (3,)``
    where there is none (no photo saw it). Nearest, not by patch key: a vertex on a patch's boundary plane
    (a wall's own plane) falls in the next cell, which its surface's points do not."""
    from pipeline.trace.scene import vertex_normals

    out = np.tile(np.asarray(level, np.float64), (len(V), 1))
    if len(V) == 0 or len(F) == 0 or len(P) == 0:
        return out
    near = nearest_facing(P, N, V, vertex_normals(V, F).astype(np.float64), reach, k, either_way=True)
    out[near >= 0] = rho_p[near[near >= 0]]
    return out


def curve_minimum(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per column of ``y (len(x), C)``, where a parabola through the lowest sample and its two neighbours
    has its minimum (the lowest sample itself at either end of ``x``)."""
    out = np.empty(y.shape[1])
    for c in range(y.shape[1]):
        i = int(np.argmin(y[:, c]))
        out[c] = x[i]
        if 0 < i < len(x) - 1:
            (x0, x1, x2), (y0, y1, y2) = x[i - 1:i + 2], y[i - 1:i + 2, c]
            den = (x0 - x1) * (x0 - x2) * (x1 - x2)
            a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
            b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / den
            if a > 0:
                out[c] = float(np.clip(-b / (2 * a), x0, x2))
    return out


def within(y: np.ndarray, tolerance: float) -> np.ndarray:
    """(levels, C) bool: the levels whose objective ``y (levels, C)`` is within ``tolerance`` of each column's
    lowest (stage 1 takes the highest of them)."""
    return y <= y.min(axis=0) * (1 + tolerance)


def level_search(evaluate, pool, tolerance: float | None = None) -> np.ndarray:
    """(len(ALBEDO_LEVELS), 3) objective ``evaluate(level)`` (3,) of each channel on the level grid, inf where
    it was not needed: every other level first, then the levels next to what the search picks from them, until
    each channel's pick (its lowest level and, with ``tolerance``, its highest level within that share of the
    lowest objective) has both neighbours evaluated. Where each channel's objective falls and then rises over
    the grid, the picks are those of the whole grid (a parabola through the lowest level and its neighbours
    too). The levels of a round run on ``pool``'s threads."""
    m = len(ALBEDO_LEVELS)
    y = np.full((m, 3), np.inf)
    done = np.zeros(m, bool)
    todo = list(range(0, m, 2)) + ([m - 1] if (m - 1) % 2 else [])
    while todo:
        for i, v in zip(todo, in_order([functools.partial(evaluate, ALBEDO_LEVELS[i]) for i in todo], pool)):
            y[i], done[i] = v, True
        need = set()
        ok = within(y, tolerance) if tolerance is not None else None
        for c in range(3):
            picks = [int(np.argmin(y[:, c]))] + ([int(np.flatnonzero(ok[:, c]).max())] if ok is not None else [])
            need.update(j for i in picks for j in (i - 1, i + 1) if 0 <= j < m and not done[j])
        todo = sorted(need)
    return y


def level_search_with_power(evaluate, pool) -> tuple[np.ndarray, np.ndarray]:
    """:func:`level_search` of ``evaluate(level) -> (objective (3,), emitted power (3,))``: the objective and
    the power per channel at each level, (len(ALBEDO_LEVELS), 3) each (inf / NaN where not evaluated), for
    :func:`white_levels`."""
    power = np.full((len(ALBEDO_LEVELS), 3), np.nan)

    def objective(lv: float) -> np.ndarray:
        obj, power[ALBEDO_LEVELS.index(lv)] = evaluate(lv)
        return obj

    return level_search(objective, pool), power


def white_levels(res: np.ndarray, power: np.ndarray, prior: float, fine: int = WHITE_GRID) -> np.ndarray:
    """(3,) albedo level per channel minimising ``sum_c res_c(l_c) / min res_c + prior x sum_c (log P_c(l_c) -
    mean_c log P_c(l_c))^2``: each channel's objective ``res (len(ALBEDO_LEVELS), 3)`` relative to its lowest,
    plus a pull of the light's colour (the emitted power ``power`` per channel at each level) toward the
    photos' white. Both are interpolated in log level through the levels evaluated (finite ``res``, positive
    ``power``) by cubic splines (a monotone one would put each minimum on a level evaluated, losing what the
    parabola of :func:`curve_minimum` finds between them); the channels couple only through the mean, which
    is searched on a grid. Each channel's own minimum (:func:`curve_minimum`) where ``prior`` is 0 or a
    channel has fewer than three such levels.

    Why: each channel's objective is nearly flat about its minimum, while the light's power goes about as the
    inverse square of the level, so each channel's own minimum leaves the light's colour to a few per cent of
    residual (deep red walls come out lit red). A room's light is far more often near the white the camera was
    balanced for than the colour of its walls, and where a channel's objective is steep the data still decides."""
    from scipy.interpolate import CubicSpline

    lv = np.asarray(ALBEDO_LEVELS, np.float64)
    res = np.asarray(res, np.float64)
    power = np.asarray(power, np.float64)
    ok = np.isfinite(res) & np.isfinite(power) & (power > 0)
    if prior <= 0 or (ok.sum(axis=0) < 3).any():
        return curve_minimum(lv, res)
    lo = max(float(np.log(lv[ok[:, c]]).min()) for c in range(3))
    hi = min(float(np.log(lv[ok[:, c]]).max()) for c in range(3))
    if hi <= lo:
        return curve_minimum(lv, res)
    xf = np.linspace(lo, hi, fine)
    g = np.empty((fine, 3))
    y = np.empty((fine, 3))
    for c in range(3):
        x = np.log(lv[ok[:, c]])
        g[:, c] = CubicSpline(x, res[ok[:, c], c] / res[ok[:, c], c].min())(xf)
        y[:, c] = CubicSpline(x, np.log(power[ok[:, c], c]))(xf)
    ms = np.linspace(y.min(), y.max(), fine)
    f = g[None] + prior * (y[None] - ms[:, None, None]) ** 2        # (means, fine, 3)
    i = f.argmin(axis=1)                                           # (means, 3)
    tot = np.take_along_axis(f, i[:, None, :], axis=1)[:, 0].sum(axis=1)
    return np.exp(xf[i[int(np.argmin(tot))]])


def brightest_colour(rho: np.ndarray, patch: np.ndarray) -> np.ndarray | None:
    """(3,) mean albedo of the room's brightest surfaces: of the patches (albedo ``rho (npatch, 3)``, the points'
    patch ``patch (n,)``) holding at least BRIGHT_MIN_SHARE of the points each, the brightest (luminance) until
    they hold BRIGHT_SHARE of the points, weighted by their points. None without such a patch."""
    n = patch.size
    count = np.bincount(patch, minlength=len(rho))
    big = np.flatnonzero(count >= max(BRIGHT_MIN_SHARE * n, 1))
    if big.size == 0:
        return None
    big = big[np.argsort(-(rho[big] @ LUMINANCE_F64), kind="stable")]
    top = big[:int(np.searchsorted(np.cumsum(count[big]), BRIGHT_SHARE * n)) + 1]
    return (count[top, None] * rho[top]).sum(axis=0) / count[top].sum()


def grey_levels(res: np.ndarray, bright: np.ndarray, level: np.ndarray, prior: float) -> np.ndarray:
    """(3,) albedo level per channel minimising ``sum_c res_c(l_c) / min res_c + prior x sum_c (log T_c(l_c) -
    mean_c log T_c(l_c))^2``, ``T_c(l) = bright_c x l / level_c``: the room's brightest surfaces, of albedo
    ``bright (3,)`` at the levels ``level (3,)``, pulled toward grey (their pattern relative to each channel's level
    does not change with it). :func:`white_levels` with the brightest surfaces' albedo in the place of the
    light's power: the photo is fixed, so a channel's light goes as the inverse of its albedo.

    Why: a room's brightest surfaces (a ceiling, white walls, cabinets, doors) are far more often near grey
    than its light is near the camera's white: a warm lamp over white walls stays warm."""
    # both positive: levels come off ALBEDO_LEVELS, albedos are clipped to ALBEDO_RANGE
    scale = np.asarray(bright, np.float64) / np.asarray(level, np.float64)
    return white_levels(res, 1.0 / (np.asarray(ALBEDO_LEVELS, np.float64)[:, None] * scale), prior)


def finite(values, digits: int = 4) -> list:
    """A list of ``values`` rounded to ``digits``, None where not finite (a level the search did not need)."""
    return [round(float(v), digits) if np.isfinite(v) else None for v in np.asarray(values, np.float64).ravel()]
