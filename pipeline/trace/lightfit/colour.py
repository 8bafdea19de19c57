"""Step 7, the light's colour: one colour per kind of emitter, and the clipped lights' own from their edges.

The channels solved on their own are each free to put their light anywhere (coloured walls come out lit by
lamps of the other walls' colours); a room's lamps, windows and panels are one colour far more often than its
walls. So the emitters share one fitted colour per kind: those the photos saw clipped (a lamp or a window in
view) one, those no photo saw (the box's cells, the lamps hung below them) another. A light seen clipped shows
its own colour at its edges (:func:`pipeline.trace.lightfit.observe.clipped_edge_excess`); where they show it,
the clipped emitters take it at the luminance the fit found.
"""

from __future__ import annotations

import logging

import numpy as np

from pipeline.color import LUMINANCE_F64
from pipeline.trace.lightfit.nnls import nnls

log = logging.getLogger(__name__)

EDGE_RAISE_WARN = 1.5         # the edges' colour raising a clipped light's brightness more than this is said
COLOUR_ROUNDS = 3             # alternations of the emission and the colours


def shared_colour(parts: list, x0: np.ndarray, kind: np.ndarray, iters: int = COLOUR_ROUNDS
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Emission ``x (K,) >= 0`` times one colour ``col_g (3,) >= 0`` (mean 1) per kind ``g`` of unknown
    (``kind (K,)`` in 0..G-1), minimising the three channels' objectives together: ``parts`` holds each channel's
    (B, y, Q = B'B, g = B'y, prior weights), ``x0 (K, 3)`` each channel's own solution (its totals per kind start
    the colours). Alternates the emission (one non-negative least squares over the channels' stacked rows at the
    colours) and the colours (per channel, the best non-negative scales of each kind's ``B x``). Returns ``x``
    and each unknown's colour, (K, 3)."""
    K = x0.shape[0]
    G = int(kind.max()) + 1 if K else 1
    members = [kind == g for g in range(G)]
    col = np.ones((G, 3))
    for g, m in enumerate(members):
        tot = x0[m].sum(axis=0)
        if tot.mean() > 0:
            col[g] = tot / tot.mean()
    x = np.zeros(K)
    for _ in range(iters):
        d = [col[kind, c] for c in range(3)]            # each unknown's scale in channel c
        x = nnls(sum(d[c][:, None] * parts[c][2] * d[c][None, :] for c in range(3)),
                 sum(d[c] * parts[c][3] for c in range(3)), sum(d[c] * parts[c][4] for c in range(3)))
        X = np.zeros((K, G))                              # x on each kind's rows
        X[np.arange(K), kind] = x
        for c, (B, y, _, _, lam) in enumerate(parts):
            U = B @ X                                     # each kind's light at unit colour
            col[:, c] = nnls(U.T @ U, U.T @ y, lam @ X)
        for g, m in enumerate(members):
            mean = float(col[g].mean())
            if mean <= 0:                                 # a kind that explains nothing in any channel: dark
                x[m], col[g] = 0.0, 1.0
            else:
                col[g] /= mean
                x[m] *= mean
        if not x.any():
            break
    return x, col[kind]


def edge_coloured(e: np.ndarray, lb: np.ndarray, colour: np.ndarray) -> tuple[np.ndarray, float]:
    """Emission ``e (k, 3)`` of lights seen clipped, in ``colour (3,)`` (positive) at its luminance, or brighter
    where that leaves a channel under its lower bound ``lb (k, 3)`` (clipped: at least sensor white there), and
    the most the luminance of a light the fit lit above that bound was raised for it (1: none; a light held at
    its bound had no luminance of its own to keep)."""
    e, lb = np.asarray(e, np.float64), np.asarray(lb, np.float64)
    c = np.asarray(colour, np.float64)
    keep = (e @ LUMINANCE_F64) / float(c @ LUMINANCE_F64)
    scale = np.maximum(keep, np.max(lb / c[None], axis=1))
    lit = (e @ LUMINANCE_F64) > 1.001 * (lb @ LUMINANCE_F64)
    return scale[:, None] * c[None], float(np.max(scale[lit] / keep[lit])) if lit.any() else 1.0


def colour_clipped(e: np.ndarray, lb: np.ndarray, colour: np.ndarray | None) -> float | None:
    """The fit's answer ``e (K, 3)``, in place: the unknowns the photos saw clipped (a positive lower bound
    ``lb``) take their edges' ``colour`` (None: the photos do not show it; nothing changes). Returns how much
    that raised a clipped light's luminance (:func:`edge_coloured`), None where nothing changed. The fit's own
    colour for them comes from the albedo's, which the photos barely tell; its luminance stays the fit's unless
    a channel would fall under sensor white."""
    if colour is None:
        return None
    seen = np.flatnonzero(lb.max(axis=1) > 0)
    e[seen], raised = edge_coloured(e[seen], lb[seen], colour)
    return raised


def say_edge_raise(name: str, colour: np.ndarray, raised: float) -> None:
    """One warning where the edges' ``colour`` raised a clipped light's brightness over EDGE_RAISE_WARN times
    (``raised``): a clipped light's lower bound is sensor white in every channel (the fit's throughout), so one
    clipped in one channel only, and deeply coloured, would come out that much too bright. Said, with the fix."""
    if raised > EDGE_RAISE_WARN:
        log.warning("light fit of %s: the clipped lights take the colour at their edges (green / red %.2f, blue / red "
                    "%.2f), %.1fx brighter than the fit found so that every channel stays at least sensor white, as "
                    "in a light clipped in every channel; one clipped in fewer channels comes out too bright: "
                    "trace.fit_edge_colour = false keeps the fit's colour", name, colour[1], colour[2], raised)
