"""Continuous collision against the room: conservative advancement of hull points along their sweep.

Speculative contacts (see :mod:`pipeline.physics.collide`) stop almost every approach. This is the
backstop for what they miss (rotation sweeping a point in, a second surface reached in the same step):
each moved body's hull points are checked at sub-step fractions of their straight sweep spaced at most
``room_thickness / 2`` apart, so no sweep can jump over the surface shell; a body whose point would
enter the shell deeper than half its thickness is stopped at the last safe fraction and loses its
velocity into the surface. A paper-thin scan surface is therefore never crossed between steps.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from pipeline.physics.collide import room_distance
from pipeline.physics.integrate import quat_to_mat
from pipeline.physics.types import Model, State


def _nlerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    q1 = np.where((np.sum(q0 * q1, axis=-1) < 0)[..., None], -q1, q1)
    q = q0 * (1 - s)[..., None] + q1 * s[..., None]
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


class Advanced(NamedTuple):
    """What :func:`advance` returns."""

    state: State          # the state with the clipped poses and velocities
    clipped: np.ndarray   # (B,) bool, bodies whose motion was clipped


def advance(model: Model, start: State, state: State) -> Advanced:
    """Clip each awake body's motion from its pose in ``start`` to its pose in ``state`` (the same step
    integrated) at the room surface."""
    pos, quat, vel, angvel, hit = _advance(model, start.pos, start.quat, state.pos, state.quat, state.vel,
                                           state.angvel, ~state.asleep)
    return Advanced(state.replace(pos=pos, quat=quat, vel=vel, angvel=angvel), hit)


def _advance(model: Model, pos0: np.ndarray, quat0: np.ndarray, pos1: np.ndarray, quat1: np.ndarray,
             vel: np.ndarray, angvel: np.ndarray, moved: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Clip each moved body's motion from (pos0, quat0) to (pos1, quat1) at the room surface.

    Parameters
    ----------
    pos0, quat0, pos1, quat1
        (B, 3) m and (B, 4) start and end poses of the step.
    vel, angvel
        (B, 3) velocities after the step.
    moved
        (B,) bool, bodies integrated this step.

    Returns
    -------
    pos, quat, vel, angvel, hit: the clipped poses and velocities, and (B,) bool bodies that were clipped.
    """
    hit = np.zeros(len(pos0), bool)
    if not (model.opt.ccd and model.has_room) or not np.any(moved):
        return pos1, quat1, vel, angvel, hit
    idx = np.flatnonzero(moved)
    h = 0.5 * model.room_thickness
    tol = 0.5 * model.room_thickness
    dq = np.abs(np.sum(quat0[idx] * quat1[idx], axis=1)).clip(0, 1)
    ang = 2 * np.arccos(dq)
    sweep = np.linalg.norm(pos1[idx] - pos0[idx], axis=1) + ang * model.body_bound[idx]
    # the trilinear distance changes by at most sqrt(3) per metre moved: a sweep shorter than
    # tol / sqrt(3) cannot enter the shell by more than tol, so it needs no check (resting bodies)
    need = sweep * np.sqrt(3.0) >= tol
    # ... nor can a body whose centre stays farther from the surface than its points can reach
    c0, _ = room_distance(model, pos0[idx], gradient=False)
    need &= ~(c0 - np.sqrt(3.0) * (model.body_bound[idx] + sweep) - model.room_thickness
              - model.body_radius[idx] > 0)
    idx, sweep = idx[need], sweep[need]
    if not len(idx):
        return pos1, quat1, vel, angvel, hit
    if model.room_mesh is not None:
        return _advance_exact(model, idx, pos0, quat0, pos1, quat1, vel, angvel, hit)
    nsub = np.maximum(1, np.ceil(sweep / h)).astype(int)
    pos1, quat1, vel, angvel = pos1.copy(), quat1.copy(), vel.copy(), angvel.copy()
    rad = model.body_radius
    for n in np.unique(nsub):
        grp = idx[nsub == n]
        V = model.body_verts.shape[1]
        s = np.arange(n + 1) / n                                              # (S,)
        G = len(grp)
        P = pos0[grp, None, :] * (1 - s)[None, :, None] + pos1[grp, None, :] * s[None, :, None]
        Q = _nlerp(np.repeat(quat0[grp, None, :], n + 1, 1), np.repeat(quat1[grp, None, :], n + 1, 1),
                   np.broadcast_to(s, (G, n + 1)))
        R = quat_to_mat(Q.reshape(-1, 4)).reshape(G, n + 1, 3, 3)
        pts = np.einsum("gsij,gvj->gsvi", R, model.body_verts[grp]) + P[:, :, None, :]
        udf, grad = room_distance(model, pts)
        phi = udf - model.room_thickness - rad[grp, None, None]                # (G, S, V)
        valid = np.arange(V)[None, None, :] < model.body_nvert[grp, None, None]
        phi = np.where(valid & np.isfinite(phi), phi, np.inf)
        allowed = np.minimum(phi[:, :1, :], 0.0) - tol
        bad = np.any(phi < allowed, axis=2)                                    # (G, S)
        bad[:, 0] = False
        for gi in np.flatnonzero(np.any(bad, axis=1)):
            j = int(np.argmax(bad[gi]))
            body = grp[gi]
            hit[body] = True
            pos1[body] = P[gi, j - 1]
            quat1[body] = Q[gi, j - 1]
            v = int(np.argmin(phi[gi, j] - allowed[gi, 0]))
            nrm = grad[gi, j - 1, v]
            vn = float(vel[body] @ nrm)
            if vn < 0:
                vel[body] = vel[body] - vn * nrm
            angvel[body] = 0.5 * angvel[body]
    return pos1, quat1, vel, angvel, hit


def _advance_exact(model: Model, idx: np.ndarray, pos0: np.ndarray, quat0: np.ndarray, pos1: np.ndarray,
                   quat1: np.ndarray, vel: np.ndarray, angvel: np.ndarray, hit: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`advance` against the room mesh: each hull point's sweep (a polyline through poses at
    sub-step fractions, so a spin is followed to within a centimetre) is cast against the surface. A
    point that would cross a sheet towards its far side (seen from the body's centre) limits the body's
    motion to the fraction where the point has covered half its remaining way into the shell (never
    deeper than half the shell); crossings away from the far side (a point leaving a sheet it was
    pushed through) are free. The grid's trilinear values are off by mm near the sheet, so this exact
    test is what makes a thin shell (a few mm) safe.
    """
    pos1, quat1, vel, angvel = pos1.copy(), quat1.copy(), vel.copy(), angvel.copy()
    th = model.room_thickness
    V = model.body_verts.shape[1]
    dq = np.abs(np.sum(quat0[idx] * quat1[idx], axis=1)).clip(0, 1)
    arc = 2 * np.arccos(dq) * model.body_bound[idx]
    nseg = np.maximum(1, np.ceil(arc / 0.01)).astype(int)                 # chord error <= ~1 cm / 8
    S = int(nseg.max())
    G = len(idx)
    s = np.minimum(np.arange(S + 1)[None, :] / nseg[:, None], 1.0)        # (G, S+1); repeats past 1
    P = pos0[idx, None, :] * (1 - s)[..., None] + pos1[idx, None, :] * s[..., None]
    Q = _nlerp(np.repeat(quat0[idx, None, :], S + 1, 1), np.repeat(quat1[idx, None, :], S + 1, 1), s)
    R = quat_to_mat(Q.reshape(-1, 4)).reshape(G, S + 1, 3, 3)
    pts = np.einsum("gsij,gvj->gsvi", R, model.body_verts[idx]) + P[:, :, None, :]   # (G, S+1, V, 3)
    valid = np.arange(V)[None, :] < model.body_nvert[idx, None]                       # (G, V)
    seg = pts[:, 1:] - pts[:, :-1]                                                     # (G, S, V, 3)
    live = valid[:, None, :] & (np.arange(S)[None, :, None] < nseg[:, None, None]) \
        & (np.linalg.norm(seg, axis=-1) > 1e-9)
    g_, k_, v_ = np.nonzero(live)
    if not len(g_):
        return pos1, quat1, vel, angvel, hit
    t, n = model.room_mesh.cast(pts[g_, k_, v_], seg[g_, k_, v_])
    # orient each hit face towards the body's centre at the segment start: the side the body is on
    hp = pts[g_, k_, v_] + np.where(np.isfinite(t), t, 0.0)[:, None] * seg[g_, k_, v_]
    n *= np.where(np.sum((P[g_, k_] - hp) * n, axis=1) < 0, -1.0, 1.0)[:, None]
    d = seg[g_, k_, v_]
    rate = -np.sum(d * n, axis=1)                       # approach speed towards the sheet per unit s
    entering = np.isfinite(t) & (rate > 0)
    if not np.any(entering):
        return pos1, quat1, vel, angvel, hit
    g_, k_, t, n, rate = g_[entering], k_[entering], t[entering], n[entering], rate[entering]
    h0 = t * rate                                       # distance to the sheet's plane at the start
    stop = (h0 - 0.5 * np.minimum(h0, th)) / rate       # fraction of the segment allowed
    frac = (k_ + np.clip(stop, 0.0, 1.0)) / nseg[g_]    # fraction of the whole step
    for gi in np.unique(g_):
        sel = np.flatnonzero(g_ == gi)
        j = sel[np.argmin(frac[sel])]
        body = idx[gi]
        f = float(frac[j])
        if f >= 1.0:
            continue
        hit[body] = True
        pos1[body] = pos0[body] * (1 - f) + pos1[body] * f
        quat1[body] = _nlerp(quat0[body][None], quat1[body][None], np.array([f]))[0]
        nrm = n[j]
        vn = float(vel[body] @ nrm)
        if vn < 0:
            vel[body] = vel[body] - vn * nrm
        angvel[body] = 0.5 * angvel[body]
    return pos1, quat1, vel, angvel, hit
