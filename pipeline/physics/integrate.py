"""Semi-implicit (symplectic) Euler integration with unit quaternions, vectorised over bodies.

Velocities are updated first (by the caller: gravity, then contact impulses), positions and
orientations second, with the new velocities. Rotation is integrated with the exponential map of the
angular velocity at the half-step orientation (midpoint rule); the angular velocity is then re-derived from the conserved angular
momentum (``L = I_w w``) at the new orientation, so torque-free spin conserves L exactly (MuJoCo's
Euler integrator drops the gyroscopic term; this keeps it without an explicit, energy-pumping torque).
"""

from __future__ import annotations

import numpy as np

from pipeline.physics.types import Model, State


def quat_to_mat(q: np.ndarray) -> np.ndarray:
    """(B, 4) unit quaternions (w, x, y, z) -> (B, 3, 3) rotation matrices."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    R = np.empty((len(q), 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - w * z)
    R[:, 0, 2] = 2 * (x * z + w * y)
    R[:, 1, 0] = 2 * (x * y + w * z)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - w * x)
    R[:, 2, 0] = 2 * (x * z - w * y)
    R[:, 2, 1] = 2 * (y * z + w * x)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def mat_to_quat(R: np.ndarray) -> np.ndarray:
    """(B, 3, 3) rotation matrices -> (B, 4) unit quaternions (w, x, y, z), w >= 0."""
    R = np.asarray(R, float).reshape(-1, 3, 3)
    q = np.empty((len(R), 4))
    tr = np.trace(R, axis1=1, axis2=2)
    # Shepperd's method: pick the largest of 4 candidates for stability
    cand = np.stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], axis=1)
    k = np.argmax(cand, axis=1)
    for i in range(len(R)):
        r = R[i]
        if k[i] == 0:
            s = np.sqrt(1 + tr[i]) * 2
            q[i] = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
        elif k[i] == 1:
            s = np.sqrt(1 + r[0, 0] - r[1, 1] - r[2, 2]) * 2
            q[i] = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
        elif k[i] == 2:
            s = np.sqrt(1 + r[1, 1] - r[0, 0] - r[2, 2]) * 2
            q[i] = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
        else:
            s = np.sqrt(1 + r[2, 2] - r[0, 0] - r[1, 1]) * 2
            q[i] = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (B, 4) quaternions."""
    aw, ax, ay, az = a.T
    bw, bx, by, bz = b.T
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=1)


def quat_exp(rotvec: np.ndarray) -> np.ndarray:
    """(B, 3) rotation vectors (rad) -> (B, 4) unit quaternions."""
    th = np.linalg.norm(rotvec, axis=1)
    half = 0.5 * th
    s = np.where(th > 1e-12, np.sin(half) / np.maximum(th, 1e-300), 0.5 - th * th / 48.0)
    return np.concatenate([np.cos(half)[:, None], rotvec * s[:, None]], axis=1)


def inertia_world_inv(R: np.ndarray, inertia: np.ndarray) -> np.ndarray:
    """(B, 3, 3) inverse world inertia ``R diag(1/I) R^T`` from rotations (B,3,3) and moments (B,3)."""
    return np.einsum("bij,bj,bkj->bik", R, 1.0 / inertia, R)


def inertia_world(R: np.ndarray, inertia: np.ndarray) -> np.ndarray:
    """(B, 3, 3) world inertia ``R diag(I) R^T``."""
    return np.einsum("bij,bj,bkj->bik", R, inertia, R)


def integrate(model: Model, state: State) -> State:
    """Advance positions and orientations of the awake bodies by one step with the state's velocities.

    ``state`` holds the poses at the start of the step and the velocities after gravity and contact
    impulses; asleep bodies keep their pose. The returned state has the new com positions and
    orientations, and the angular velocity re-derived from the angular momentum at the new orientation.
    """
    vel, angvel, active = state.vel, state.angvel, ~state.asleep
    dt = model.opt.timestep
    pos = state.pos.copy()
    quat = state.quat.copy()
    w = angvel.copy()
    if not np.any(active):
        return state.replace(pos=pos, quat=quat, angvel=w)
    a = active
    pos[a] = state.pos[a] + dt * vel[a]
    R0 = quat_to_mat(state.quat[a])
    L = np.einsum("bij,bj->bi", inertia_world(R0, model.body_inertia[a]), angvel[a])
    # midpoint rule: rotate by the angular velocity the momentum has at the half-step orientation
    # (second order; L is conserved exactly, the rotational energy to O(dt^2))
    qh = quat_mul(quat_exp(0.5 * dt * angvel[a]), state.quat[a])
    wh = np.einsum("bij,bj->bi", inertia_world_inv(quat_to_mat(qh), model.body_inertia[a]), L)
    q = quat_mul(quat_exp(dt * wh), state.quat[a])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    quat[a] = q
    R1 = quat_to_mat(q)
    w[a] = np.einsum("bij,bj->bi", inertia_world_inv(R1, model.body_inertia[a]), L)
    return state.replace(pos=pos, quat=quat, angvel=w)
