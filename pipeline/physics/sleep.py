"""Sleeping: bodies at rest stop being integrated; moving bodies wake the sleepers they touch."""

from __future__ import annotations

import numpy as np

from pipeline.physics.types import Model, State


def wake(model: Model, state: State) -> State:
    """A sleeper whose bounding sphere (plus a margin) reaches an awake body moving faster than
    ``Options.wake_speed`` wakes up (repeated so a chain of touching sleepers wakes); its rest timer
    restarts."""
    asleep = _woken(model, state.pos, state.vel, state.angvel, state.asleep)
    return state.replace(asleep=asleep, rest_time=np.where(state.asleep & ~asleep, 0.0, state.rest_time))


def _woken(model: Model, pos: np.ndarray, vel: np.ndarray, angvel: np.ndarray, asleep: np.ndarray) -> np.ndarray:
    asleep = asleep.copy()
    if not np.any(asleep) or np.all(asleep):
        return asleep
    dt = model.opt.timestep
    speed = np.linalg.norm(vel, axis=1) + np.linalg.norm(angvel, axis=1) * model.body_bound
    reach = model.body_bound[:, None] + model.body_bound[None, :] + model.opt.margin \
        + dt * (speed[:, None] + speed[None, :])
    touch = np.linalg.norm(pos[:, None] - pos[None, :], axis=2) < reach
    np.fill_diagonal(touch, False)
    waker = ~asleep & (speed > model.opt.wake_speed)
    while True:
        woken = asleep & np.any(touch & waker[None, :], axis=1)
        if not np.any(woken):
            return asleep
        asleep[woken] = False
        waker = woken


def update_sleep(model: Model, state: State) -> State:
    """Advance rest timers and put bodies that rested ``Options.sleep_time`` to sleep.

    A body rests while it is slow (``sleep_linear``/``sleep_angular``) or while none of its points has
    moved more than ``sleep_drift`` from where its rest began (the anchor): contact jitter on rough scan
    surfaces kicks velocities without moving the body anywhere. Sleeping bodies get zero velocity.
    """
    opt = model.opt
    vel, angvel, asleep, rest_time = state.vel, state.angvel, state.asleep, state.rest_time
    pos, quat, anchor_pos, anchor_quat = state.pos, state.quat, state.anchor_pos, state.anchor_quat
    still = (np.linalg.norm(vel, axis=1) < opt.sleep_linear) & (np.linalg.norm(angvel, axis=1) < opt.sleep_angular)
    if anchor_pos is None:
        anchor_pos, anchor_quat = pos.copy(), quat.copy()
    dq = np.abs(np.sum(quat * anchor_quat, axis=1)).clip(0, 1)
    drift = np.linalg.norm(pos - anchor_pos, axis=1) + 2 * np.arccos(dq) * model.body_bound
    near = drift < opt.sleep_drift
    # slow bodies always rest; fast ones only while they jitter in place (no more than 10x)
    calm = (np.linalg.norm(vel, axis=1) < 10 * opt.sleep_linear) & \
        (np.linalg.norm(angvel, axis=1) < 10 * opt.sleep_angular)
    resting = still | (near & calm)
    moved = ~near
    anchor_pos = np.where(moved[:, None], pos, anchor_pos)
    anchor_quat = np.where(moved[:, None], quat, anchor_quat)
    still = resting & ~moved | still & moved
    rest_time = np.where(still | asleep, rest_time + opt.timestep, 0.0)
    asleep = asleep | (rest_time >= opt.sleep_time)
    vel = np.where(asleep[:, None], 0.0, vel)
    angvel = np.where(asleep[:, None], 0.0, angvel)
    return state.replace(vel=vel, angvel=angvel, asleep=asleep, rest_time=rest_time, anchor_pos=anchor_pos,
                         anchor_quat=anchor_quat)
