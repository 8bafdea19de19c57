"""``step(model, state) -> State``: one time step made of named sub-steps.

``wake`` -> external forces -> ``collide`` -> ``rolling_resistance`` -> ``solve_contacts`` ->
``integrate`` -> ``ccd.advance``
-> ``update_sleep``. No validation here: :func:`~pipeline.physics.types.build_model` did it once.
"""

from __future__ import annotations

import numpy as np

from pipeline.physics.ccd import advance
from pipeline.physics.collide import Contacts, collide
from pipeline.physics.integrate import integrate
from pipeline.physics.sleep import update_sleep, wake
from pipeline.physics.solve import rolling_resistance, solve_contacts
from pipeline.physics.types import Model, State


def warm_start(state: State, contacts: Contacts) -> np.ndarray:
    """(C, 3) impulses of the previous step for contacts with the same feature key, else zeros."""
    out = np.zeros((contacts.count, 3))
    if len(state.ws_key) == 0 or contacts.count == 0:
        return out
    order = np.argsort(state.ws_key)
    keys = state.ws_key[order]
    i = np.clip(np.searchsorted(keys, contacts.key), 0, len(keys) - 1)
    same = keys[i] == contacts.key
    out[same] = state.ws_impulse[order[i[same]]]
    return out


def external(model: Model, state: State, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Velocities after gravity for the active bodies (sleeping ones stay at zero)."""
    g = np.asarray(model.opt.gravity, float)
    vel = np.where(active[:, None], state.vel + model.opt.timestep * g, state.vel)
    return vel, state.angvel.copy()


def step(model: Model, state: State) -> State:
    """Advance ``state`` by ``model.opt.timestep`` seconds.

    Loops of steps should run under :func:`pipeline.physics.drop.one_blas_thread` (as
    :func:`~pipeline.physics.drop.run` does): the solver's products are small and a threaded BLAS makes
    them many times slower on a busy machine.
    """
    asleep = wake(model, state.pos, state.vel, state.angvel, state.asleep)
    state = state.replace(asleep=asleep, rest_time=np.where(state.asleep & ~asleep, 0.0, state.rest_time))
    active = ~asleep
    vel_free, angvel_free = external(model, state, active)
    contacts = collide(model, state)
    warm = warm_start(state, contacts)
    # rolling resistance from last step's normal impulses, before the solve so contacts stay consistent
    angvel_free = rolling_resistance(model, state, contacts, warm, angvel_free, active)
    sol = solve_contacts(model, state, contacts, vel_free, angvel_free, active, warm)
    pos, quat, angvel = integrate(model, state, sol.vel, sol.angvel, active)
    pos, quat, vel, angvel, _ = advance(model, state.pos, state.quat, pos, quat, sol.vel, angvel, active)
    vel, angvel, asleep, rest, apos, aquat = update_sleep(model, vel, angvel, asleep, state.rest_time, pos,
                                                          quat, state.anchor_pos, state.anchor_quat)
    pen = float(max(0.0, -contacts.dist.min())) if contacts.count else 0.0
    keep = np.any(sol.impulse != 0, axis=1)
    return State(time=state.time + model.opt.timestep, pos=pos, quat=quat, vel=vel, angvel=angvel,
                 asleep=asleep, rest_time=rest, ws_key=contacts.key[keep], ws_impulse=sol.impulse[keep],
                 max_penetration=pen, anchor_pos=apos, anchor_quat=aquat)


def penetration(model: Model, state: State) -> float:
    """Deepest penetration (m) of any contact at ``state``, every body considered awake."""
    c = collide(model, state.replace(asleep=np.zeros(model.nbody, bool)))
    return float(max(0.0, -c.dist.min())) if c.count else 0.0
