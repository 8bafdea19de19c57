"""Sleeping: bodies at rest stop being integrated; moving bodies wake the sleepers they touch."""

from __future__ import annotations

import numpy as np

from pipeline.physics.types import Model


def wake(model: Model, pos: np.ndarray, vel: np.ndarray, angvel: np.ndarray,
         asleep: np.ndarray) -> np.ndarray:
    """(B,) bool new sleep flags: a sleeper whose bounding sphere (plus a margin) reaches an awake body
    moving faster than ``Options.wake_speed`` wakes up (repeated so a chain of touching sleepers wakes).
    """
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


def update_sleep(model: Model, vel: np.ndarray, angvel: np.ndarray, asleep: np.ndarray,
                 rest_time: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Advance rest timers and put bodies that rested ``Options.sleep_time`` to sleep.

    Returns new ``(vel, angvel, asleep, rest_time)``; sleeping bodies get zero velocity.
    """
    opt = model.opt
    still = (np.linalg.norm(vel, axis=1) < opt.sleep_linear) & (np.linalg.norm(angvel, axis=1) < opt.sleep_angular)
    rest_time = np.where(still | asleep, rest_time + opt.timestep, 0.0)
    asleep = asleep | (rest_time >= opt.sleep_time)
    vel = np.where(asleep[:, None], 0.0, vel)
    angvel = np.where(asleep[:, None], 0.0, angvel)
    return vel, angvel, asleep, rest_time
