"""Contact solve: soft constraints in MuJoCo's formulation, Coulomb friction, vectorised iterations.

Each contact has three rows (normal, two tangents). With ``u = J v`` the row velocities at the start of
the step and ``r`` the signed distance, MuJoCo's reference acceleration is
``aref = -b u - k d(r) r`` with ``b = 2 / (dmax tc)``, ``k = 1 / (dmax^2 tc^2 zeta^2)`` from
``solref = (tc, zeta)`` and the impedance ``d(r)`` from ``solimp`` (MuJoCo's sigmoid, mid 0.5, power 2).
Softness enters as the regulariser ``R = (1 - d) / d * A_ii`` (friction rows ``R / impratio``). In
impulse form (impulse ``p = f dt``) each active row satisfies ``J v+ + R p = u + dt aref``.
Speculative contacts (``r > 0``) are hard: ``J_n v+ >= -r / dt`` (arrive, never cross). With the default
``tc = 2 dt`` (``b dt = 1``) a body that reaches a surface therefore stops on it within a step, where
MuJoCo's continuous dynamics let it sink ~``v tc / e`` and spring back; ``Options.soft_impact`` follows
those (soft from arrival, implicit reference acceleration: :func:`_soft_impact_rows`). It is off by default:
against thin scan surfaces the sinking wedges bodies (see bench/results/physics.json's notes).

The resulting cone-constrained problem ``min 1/2 p^T (A + R) p - p^T c`` with ``p_n >= 0`` and
``|p_t| <= mu p_n`` (elliptic cone) is solved in two ways, both vectorised over contacts:

1. a direct solve on an active set grown from the warm start (loaded contacts taken as sticking),
   accepted only when it meets the optimality conditions: exact, and what resting contacts get;
2. otherwise accelerated projected gradient iterations (Nesterov with adaptive restart),
   Jacobi-preconditioned per contact, ``A = J M^-1 J^T`` formed once when that is cheaper than two
   products with the Jacobian per iteration, until no body's velocity changes by more than
   ``Options.tolerance`` in an iteration. The per-contact projection (clamp the normal impulse, then
   clip the friction impulse to the disc of radius mu p_n) makes every fixed point satisfy Coulomb's
   law with maximal dissipation (no lift-off artefact of the convex relaxation).

Impulses are warm-started from the previous step through persistent contact keys. Stopping early is not
harmless: unconverged impulses pump energy into resting piles (see the tests).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.physics.collide import Contacts
from pipeline.physics.integrate import inertia_world_inv, quat_to_mat
from pipeline.physics.types import Model, Options, State


@dataclass(frozen=True)
class SolveResult:
    """Output of :func:`solve_contacts`."""

    vel: np.ndarray        # (B, 3) float64, m/s, velocities after the contact impulses
    angvel: np.ndarray     # (B, 3) float64, rad/s, world
    impulse: np.ndarray    # (C, 3) float64, N s, (normal, t1, t2) per contact (0 for dropped rows)
    iterations: int        # iterations run
    residual: float        # last change of the impulses, N s


def tangent_frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (C, 3) orthogonal to unit normals ``n`` (C, 3)."""
    a = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def impedance(r: np.ndarray, solimp: tuple[float, float, float]) -> np.ndarray:
    """MuJoCo's constraint impedance d(r) in (0, 1) for violations ``r`` (m), mid 0.5, power 2."""
    dmin, dmax, width = solimp
    x = np.clip(np.abs(r) / max(width, 1e-12), 0.0, 1.0)
    y = np.where(x <= 0.5, 2 * x * x, 1 - 2 * (1 - x) ** 2)
    return dmin + (dmax - dmin) * y


def project_cone(p: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """Clamp normal impulses to >= 0 and clip friction impulses to the disc of radius ``mu p_n``.

    Parameters
    ----------
    p
        (C, 3) impulses (normal, t1, t2).
    mu
        (C,) friction coefficients.
    """
    out = np.empty_like(p)
    pn = np.maximum(p[:, 0], 0.0)
    out[:, 0] = pn
    t1, t2 = p[:, 1], p[:, 2]
    m = np.sqrt(t1 * t1 + t2 * t2)
    lim = mu * pn
    s = np.where(m > lim, lim / np.maximum(m, 1e-300), 1.0)
    out[:, 1] = t1 * s
    out[:, 2] = t2 * s
    return out


def solve_contacts(model: Model, state: State, free: State, contacts: Contacts,
                   warm: np.ndarray | None = None) -> SolveResult:
    """Contact impulses and the velocities they produce.

    The sub-steps: :func:`contact_jacobian` (rows of the contacts that touch an awake body),
    :func:`contact_rows` (MuJoCo's reference velocities and regularisers), :class:`ContactSystem` (the
    cone problem), :func:`_active_set_solve` (exact at rest), then :func:`_projected_gradient` (the
    iterations, when the direct solve does not meet the optimality conditions).

    Parameters
    ----------
    model, state
        Model and the state at the start of the step (velocities ``u`` for the reference acceleration).
    free
        The state with the velocities after external forces (gravity) only; its awake bodies move this
        step (sleeping bodies act as static).
    contacts
        From :func:`~pipeline.physics.collide.collide`.
    warm
        (C, 3) initial impulses (warm start), or None for zeros.
    """
    vel_free, angvel_free, dynamic = free.vel, free.angvel, ~free.asleep
    opt = model.opt
    C = contacts.count
    vel = vel_free.copy()
    angvel = angvel_free.copy()
    imp = np.zeros((C, 3))
    if C == 0:
        return SolveResult(vel, angvel, imp, 0, 0.0)
    a, b = contacts.body_a, contacts.body_b
    dyn_a = dynamic[a]
    dyn_b = (b >= 0) & dynamic[np.maximum(b, 0)]
    use = dyn_a | dyn_b
    if not np.any(use):
        return SolveResult(vel, angvel, imp, 0, 0.0)
    ci = np.flatnonzero(use)
    K = len(ci)
    bodies = np.flatnonzero(dynamic)
    nd = len(bodies)
    Jf, Wf = contact_jacobian(model, state, contacts, ci, dyn_a[ci], dyn_b[ci], bodies)
    # A = J M^-1 J^T is never formed: A y = J (M^-1 J^T y) costs 2 (3K)(6 nd) instead of (3K)^2
    Adiag = np.einsum("ij,ij->i", Wf, Jf)
    v0 = np.concatenate([state.vel[bodies], state.angvel[bodies]], axis=1).reshape(-1)
    vf = np.concatenate([vel_free[bodies], angvel_free[bodies]], axis=1).reshape(-1)
    u = (Jf @ v0).reshape(K, 3)
    uf = (Jf @ vf).reshape(K, 3)
    Ann = Adiag[0::3]
    target, soft, Rrow = contact_rows(opt, u, contacts.dist[ci], Ann)
    mu = contacts.friction[ci]
    # H = A + R formed once (3K x 3K) while that is cheaper than two products with the Jacobian: each
    # iteration is then one matrix-vector product (the call count, not the flops, costs at these sizes)
    system = ContactSystem.build(Jf, Wf, Rrow.reshape(-1), (target - uf).reshape(-1), mu, dense=3 * K <= 12 * nd)
    # Jacobi preconditioner: one scalar per contact (keeps the cone projection a projection)
    pre = np.repeat(1.0 / (Ann + Rrow[:, 0]), 3)
    step = _step_size(system, pre)
    p = np.zeros((K, 3)) if warm is None else project_cone(warm[ci], mu)
    p, exact = _active_set_solve(p, system.hmul, system.c, mu, Jf, Wf, system.Rv, system.H, soft)
    p, it, res = _projected_gradient(system, p.reshape(-1), step, exact, model.body_bound[bodies], opt)
    dv = (Wf.T @ p).reshape(nd, 6)
    vel[bodies] += dv[:, :3]
    angvel[bodies] += dv[:, 3:]
    imp[ci] = p.reshape(K, 3)
    return SolveResult(vel, angvel, imp, it, res)


def contact_jacobian(model: Model, state: State, contacts: Contacts, ci: np.ndarray, dyn_a: np.ndarray,
                     dyn_b: np.ndarray, bodies: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The contact Jacobian and the inverse mass applied to it, for the contacts ``ci``.

    Three rows per contact (normal, two tangents of :func:`tangent_frame`), six columns (linear,
    angular) per awake body; a sleeping body or the static world has no columns (it acts as static).

    Parameters
    ----------
    ci
        (K,) int64, the contacts that touch an awake body.
    dyn_a, dyn_b
        (K,) bool, whether body a / body b of each of those contacts is awake.
    bodies
        (nd,) int64, the awake bodies, in column order.

    Returns
    -------
    Jf : (3K, 6 nd) float64, row velocities ``u = Jf v``
    Wf : (3K, 6 nd) float64, ``J M^-1`` (the velocity change per unit row impulse is ``Wf^T``)
    """
    a, b = contacts.body_a[ci], contacts.body_b[ci]
    n = contacts.normal[ci]
    t1, t2 = tangent_frame(n)
    D = np.stack([n, t1, t2], axis=1)                                # (K, 3, 3) rows
    K = len(ci)
    col = -np.ones(model.nbody, np.int64)
    col[bodies] = np.arange(len(bodies))
    nd = len(bodies)
    Rb = quat_to_mat(state.quat[bodies])
    Iinv = inertia_world_inv(Rb, model.body_inertia[bodies])          # (nd, 3, 3)
    invm = 1.0 / model.body_mass[bodies]
    # Jacobian (K, 3 rows, nd, 6)
    J = np.zeros((K, 3, nd, 6))
    ra = contacts.pos[ci] - state.pos[a]
    ka = np.flatnonzero(dyn_a)
    J[ka, :, col[a[ka]], :3] = D[ka]
    J[ka, :, col[a[ka]], 3:] = np.cross(ra[ka, None, :], D[ka])
    kb = np.flatnonzero(dyn_b)
    if len(kb):
        rb = contacts.pos[ci[kb]] - state.pos[b[kb]]
        J[kb, :, col[b[kb]], :3] -= D[kb]
        J[kb, :, col[b[kb]], 3:] -= np.cross(rb[:, None, :], D[kb])
    Jf = J.reshape(3 * K, nd * 6)
    W = J.copy()
    W[..., :3] *= invm[None, None, :, None]
    W[..., 3:] = np.einsum("kcbj,bjl->kcbl", J[..., 3:], Iinv)
    Wf = W.reshape(3 * K, nd * 6)
    return Jf, Wf


def contact_rows(opt: Options, u: np.ndarray, r: np.ndarray, Ann: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """MuJoCo's soft-constraint targets and regularisers of the contact rows (see the module docstring).

    Parameters
    ----------
    opt
        The options (``timestep``, ``solref``, ``solimp``, ``impratio``, ``soft_impact``).
    u
        (K, 3) float64, m/s, row velocities at the start of the step.
    r
        (K,) float64, m, signed distances (< 0: penetration).
    Ann
        (K,) float64, diagonal of ``A = J M^-1 J^T`` on the normal rows.

    Returns
    -------
    target : (K, 3) float64, m/s, the row velocities the impulses aim for
    soft : (K,) bool, the normal row is soft (penetrating, or arriving with ``soft_impact``)
    Rrow : (K, 3) float64, the regulariser ``R`` of each row (a hard row gets ``1e-9 A_nn``)
    """
    dt = opt.timestep
    K = len(r)
    tc = max(opt.solref[0], 2 * dt)
    zeta = opt.solref[1]
    dmax = opt.solimp[1]
    kk = 1.0 / (dmax ** 2 * tc ** 2 * zeta ** 2)
    bb = 2.0 / (dmax * tc)
    dimp = impedance(np.minimum(r, 0.0), opt.solimp)
    Rn = (1 - dimp) / dimp * Ann
    soft = r <= 0
    target = np.empty((K, 3))
    if opt.soft_impact:
        target[:, 0], soft, Rn_n = _soft_impact_rows(u[:, 0], r, dimp, Rn, dt, bb, kk)
    else:
        target[:, 0] = np.where(soft, u[:, 0] + dt * (-bb * u[:, 0] - kk * dimp * r), -r / dt)
        Rn_n = Rn
    target[:, 1:] = u[:, 1:] * max(0.0, 1 - bb * dt)   # never reverse the slip (energy)
    Rrow = np.stack([np.where(soft, Rn_n, 1e-9 * Ann), Rn / opt.impratio, Rn / opt.impratio], axis=1)
    return target, soft, Rrow


@dataclass(frozen=True)
class ContactSystem:
    """The cone-constrained problem ``min 1/2 p^T H p - p^T c`` with ``H = A + R``, ``A = J M^-1 J^T``."""

    Jf: np.ndarray               # (3K, 6 nd) float64, contact Jacobian
    Wf: np.ndarray               # (3K, 6 nd) float64, J M^-1
    Rv: np.ndarray               # (3K,) float64, regulariser per row
    c: np.ndarray                # (3K,) float64, m/s, target minus the free row velocities
    mu: np.ndarray               # (K,) float64, friction coefficients
    H: np.ndarray | None         # (3K, 3K) float64, formed when dense, else None
    WfT: np.ndarray | None       # (6 nd, 3K) float64, contiguous Wf^T when H is not formed

    @staticmethod
    def build(Jf: np.ndarray, Wf: np.ndarray, Rv: np.ndarray, c: np.ndarray, mu: np.ndarray, *,
              dense: bool) -> "ContactSystem":
        """The system, with ``H`` formed once when ``dense`` (else products with the Jacobian)."""
        if dense:
            H = Jf @ Wf.T
            H[np.diag_indices_from(H)] += Rv
            return ContactSystem(Jf, Wf, Rv, c, mu, H, None)
        return ContactSystem(Jf, Wf, Rv, c, mu, None, np.ascontiguousarray(Wf.T))

    def hmul(self, v: np.ndarray) -> np.ndarray:
        """``H v`` (3K,)."""
        if self.H is not None:
            return self.H @ v
        return self.Jf @ (self.WfT @ v) + self.Rv * v


def _step_size(system: ContactSystem, pre: np.ndarray) -> np.ndarray:
    """(3K,) step of the preconditioned gradient iterations: ``pre / L`` with ``L`` the largest eigenvalue
    of the preconditioned ``H`` (10 power iterations, 5 % margin)."""
    hmul = system.hmul
    sq = np.sqrt(pre)
    x = np.ones(len(pre))
    for _ in range(10):
        x = sq * hmul(sq * x)
        x /= np.linalg.norm(x)
    L = float(x @ (sq * hmul(sq * x))) * 1.05 + 1e-12
    return pre / L


def _projected_gradient(system: ContactSystem, p: np.ndarray, step: np.ndarray, exact: bool, bnd: np.ndarray,
                        opt: Options) -> tuple[np.ndarray, int, float]:
    """Accelerated projected gradient iterations (Nesterov, adaptive restart) from the impulses ``p`` (3K,).

    Each iteration takes ``z = y - step (H y - c)`` and projects it on the cones (:func:`project_cone`,
    inlined); it stops when no body's velocity (spin times its bound radius ``bnd`` (nd,), m) changes by
    more than ``opt.tolerance`` or after ``opt.iterations``. None run when ``exact`` (the active-set
    solve found the solution). Returns ``(p (3K,), iterations, residual)``.
    """
    Jf, Wf, Rv, c, mu = system.Jf, system.Wf, system.Rv, system.c, system.mu
    dense = system.H is not None
    K = len(mu)
    nd = len(bnd)
    # projected gradient step z = y - step (H y - c) = M y + step c
    sc = step * c
    if dense:
        M = -step[:, None] * system.H
        M[np.diag_indices_from(M)] += 1.0
    else:
        WfT = system.WfT
        nstepJ = -step[:, None] * Jf
    wr = 1.0 / step                  # metric of the gradient mapping (restart test)
    # impulse change -> velocity change of the bodies (m/s; spin x bound radius): the stopping measure.
    # Redundant contacts (a face on a plane) make the impulses' split ill-conditioned, not the motion
    Ws = (Wf * np.concatenate([np.ones((nd, 3)), np.repeat(bnd[:, None], 3, 1)], axis=1).reshape(-1)).T.copy()
    dv_it = np.empty(6 * nd)
    y = p.copy()
    theta = 1.0
    it = 0
    res = 0.0 if exact else np.inf
    z = np.empty(3 * K)
    zK = z.reshape(K, 3)
    tm = np.empty(K)
    lim = np.empty(K)
    dp = np.empty(3 * K)
    tmp = np.empty(3 * K)
    p_new = np.empty(3 * K)
    for it in range(1, 0 if exact else opt.iterations + 1):
        if dense:
            np.dot(M, y, out=z)
        else:
            np.dot(nstepJ, WfT @ y, out=z)
            z -= step * Rv * y
            z += y
        z += sc
        # project_cone, inlined (this loop is the solver's cost)
        pv = p_new.reshape(K, 3)
        np.maximum(zK[:, 0], 0.0, out=pv[:, 0])
        np.hypot(zK[:, 1], zK[:, 2], out=tm)
        np.multiply(mu, pv[:, 0], out=lim)
        np.maximum(tm, 1e-300, out=tm)
        np.divide(lim, tm, out=lim)
        np.minimum(lim, 1.0, out=lim)
        np.multiply(zK[:, 1:], lim[:, None], out=pv[:, 1:])
        np.subtract(p_new, p, out=dp)
        np.dot(Ws, dp, out=dv_it)
        res = float(np.abs(dv_it).max())
        np.subtract(y, p_new, out=tmp)
        tmp *= wr
        if tmp @ dp > 0:  # adaptive restart (O'Donoghue & Candes): momentum points uphill
            theta = 1.0
            y = p_new.copy()
        else:
            th2 = 0.5 * (1 + np.sqrt(1 + 4 * theta * theta))
            y = p_new + ((theta - 1) / th2) * dp
            theta = th2
        p, p_new = p_new, p
        if res < opt.tolerance:
            break
    return p, it, res


def _soft_impact_rows(u: np.ndarray, r: np.ndarray, dimp: np.ndarray, Rn: np.ndarray, dt: float, bb: float,
                      kk: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal rows for ``Options.soft_impact``: MuJoCo's continuous soft contact through the impact.

    A speculative contact that the body reaches within the step (``0 < r < -u dt``) is soft from the
    moment ``ts = r / -u`` it arrives (MuJoCo, with a short step, sees it penetrate and lets the spring
    act), not a hard "arrive, never cross" row. Soft rows take the reference acceleration implicitly over
    their time in contact ``tau`` (``dt``, or ``dt - ts`` on arrival): ``aref = -b v+ - k d (r + tau v+)``,
    so ``J v+ + R/s p = (u - tau k d r) / s`` with ``s = 1 + tau b + tau^2 k d``. The explicit form with
    ``b dt = 1`` (``tc = 2 dt``, the default) stops the body in one step; the implicit one lets it sink
    and spring back over ~``tc`` as MuJoCo's continuous dynamics do.

    Parameters
    ----------
    u, r, dimp, Rn
        (K,) normal velocity at the start of the step (m/s), signed distance (m), impedance, regulariser.
    dt, bb, kk
        Step (s) and MuJoCo's damping (1/s) and stiffness (1/s^2).

    Returns ``(target (K,) m/s, soft (K,) bool, R (K,))``.
    """
    soft = r <= 0
    with np.errstate(divide="ignore"):
        ts = np.where(u < 0, r / np.maximum(-u, 1e-300), np.inf)
    arrive = ~soft & (ts < dt)
    tau = np.where(arrive, dt - ts, dt)
    soft = soft | arrive
    s = 1 + tau * bb + tau * tau * kk * dimp
    target = np.where(soft, (u - tau * kk * dimp * np.minimum(r, 0.0)) / s, -r / dt)
    return target, soft, np.where(soft, Rn / s, Rn)


def _active_set_solve(p0: np.ndarray, hmul, c: np.ndarray, mu: np.ndarray, Jf: np.ndarray, Wf: np.ndarray,
                      Rv: np.ndarray, H: np.ndarray | None, soft: np.ndarray, rounds: int = 4
                      ) -> tuple[np.ndarray, bool]:
    """Direct solves on an active set grown from the warm start, checked against the optimality
    conditions.

    Contacts that carried load last step (``p0`` normal > 0) are taken as sticking: their rows solve
    ``H_AA p_A = c_A`` exactly, the others get zero. The result is the solution when every loaded
    contact lies inside its friction cone and every unloaded one is not pulled in (``g = H p - c`` in
    the dual cone: ``g_n >= mu |g_t|``). Unloaded contacts that are pulled in join the set and loaded
    ones with a negative normal impulse leave it, for a few rounds. At rest this ends in the solution
    and no iteration is needed; otherwise (sliding contacts: on the cone's boundary) the projected
    result is a warm start for the iterations. Only penetrating (soft) contacts take part: a loaded
    speculative contact's hard row makes the system near-singular, so the iterations handle those steps.

    Returns ``(p (K, 3), exact)``.
    """
    K = len(p0)
    act = p0[:, 0] > 0
    if not act.any() or np.any(act & ~soft):
        return p0, False
    scale = 1e-9 * (np.abs(c).max() + 1e-300)
    cK = p0
    for _ in range(rounds):
        rows = np.repeat(act, 3)
        if H is not None:
            HA = H[np.ix_(rows, rows)]
        else:
            HA = Jf[rows] @ Wf[rows].T
            HA[np.diag_indices_from(HA)] += Rv[rows]
        try:
            pa = np.linalg.solve(HA, c[rows])
        except np.linalg.LinAlgError:
            return p0, False
        cand = np.zeros(3 * K)
        cand[rows] = pa
        cK = cand.reshape(K, 3)
        if np.any(np.hypot(cK[act, 1], cK[act, 2]) > mu[act] * cK[act, 0]):
            break                                   # sliding (or pulling) contacts: iterate instead
        g = (hmul(cand) - c).reshape(K, 3)
        pulled = ~act & (g[:, 0] + scale < mu * np.hypot(g[:, 1], g[:, 2]))
        if not pulled.any():
            return cK, True
        if np.any(pulled & ~soft):
            break
        act = act | pulled
    return project_cone(cK, mu), False


def rolling_resistance(model: Model, state: State, contacts: Contacts, impulse: np.ndarray) -> State:
    """Rolling and torsional resistance: each awake body's angular momentum shrinks by up to
    ``Options.rolling`` (m) times the normal impulse it received (``impulse``, N s, per contact).

    Point contacts cannot stop a ball rolling or a body spinning about its contact normal; real
    contacts have a patch that does. This is a simple isotropic stand-in for MuJoCo's condim 6 rolling
    and torsional friction. Returns the state with the new angular velocities.
    """
    angvel, dynamic = state.angvel, ~state.asleep
    mu_r = model.opt.rolling
    if mu_r <= 0 or contacts.count == 0:
        return state
    B = model.nbody
    pn = impulse[:, 0]
    N = np.bincount(contacts.body_a, pn, minlength=B)
    ob = contacts.body_b >= 0
    N += np.bincount(contacts.body_b[ob], pn[ob], minlength=B)
    act = np.flatnonzero(dynamic & (N > 0))
    if not len(act):
        return state
    R = quat_to_mat(state.quat[act])
    from pipeline.physics.integrate import inertia_world

    L = np.einsum("bij,bj->bi", inertia_world(R, model.body_inertia[act]), angvel[act])
    Lm = np.linalg.norm(L, axis=1)
    cut = np.minimum(mu_r * N[act], Lm)
    L_new = L * (1 - cut / np.maximum(Lm, 1e-300))[:, None]
    out = angvel.copy()
    out[act] = np.einsum("bij,bj->bi", inertia_world_inv(R, model.body_inertia[act]), L_new)
    return state.replace(angvel=out)
