"""The exact non-negative least squares every emission solve of the light fit ends in."""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)


def nnls(Q: np.ndarray, g: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """``argmin_x>=0 0.5 x'Qx - g'x + lam'x`` (``Q`` symmetric positive semi-definite), solved exactly.

    With ``Q = R'R`` (Cholesky of the unit-diagonal rescaling plus a ridge of 1e-10, more where rounding
    leaves it indefinite) it is the non-negative least squares ``min ||R x - R'^-1 (g - lam)||``, solved by
    Lawson and Hanson's active set (``scipy.optimize.nnls``) on a unit right-hand side (scipy 1.12-1.14 stop
    on an absolute tolerance). Exact, because the level searches compare objectives, which must be minima.
    Where there is no answer (non-finite input, no factor, no convergence) it says so and leaves the emission
    at zero.
    """
    from scipy.linalg import solve_triangular
    from scipy.optimize import nnls as active_set

    x = np.zeros(g.shape[0])
    dq = np.diag(Q)
    use = np.flatnonzero(dq > 1e-300)      # a column that sends no light stays at zero (lam >= 0)
    if use.size == 0:
        return x

    def none(why: str) -> np.ndarray:
        log.warning("light fit: no emission solve for %d unknowns (%s); left at zero", use.size, why)
        return x

    if not (np.all(np.isfinite(Q)) and np.all(np.isfinite(g)) and np.all(np.isfinite(lam))):
        return none("non-finite input")
    d = np.sqrt(dq[use])
    Qs = Q[np.ix_(use, use)] / d[:, None] / d[None, :]
    for ridge in (1e-10, 1e-8, 1e-6, 1e-4):
        try:
            R = np.linalg.cholesky(Qs + ridge * np.eye(use.size)).T
            break
        except np.linalg.LinAlgError:
            continue
    else:
        return none("no Cholesky factor")
    b = solve_triangular(R.T, (g[use] - lam[use]) / d, lower=True)
    bn = float(np.linalg.norm(b))
    if bn == 0:
        return x
    try:
        z, _ = active_set(R, b / bn, maxiter=50 * use.size)
    except RuntimeError:
        return none("the active set did not settle")
    x[use] = z * bn / d
    return x
