"""``step(model, state) -> State``: one time step made of named sub-steps.

``wake`` -> ``collide`` -> external forces -> ``rolling_resistance`` -> ``solve_contacts`` ->
``integrate`` -> ``ccd.advance`` -> ``update_sleep``, each ``(model, state) -> state`` (collide and the
solver return their named results). No validation here: :func:`~pipeline.physics.io.build_model` did it
once.
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


def external(model: Model, state: State) -> State:
    """The state with the velocities after gravity for the awake bodies (sleeping ones stay at zero)."""
    g = np.asarray(model.opt.gravity, float)
    vel = np.where(~state.asleep[:, None], state.vel + model.opt.timestep * g, state.vel)
    return state.replace(vel=vel, angvel=state.angvel.copy())


def step(model: Model, state: State) -> State:
    """Advance ``state`` by ``model.opt.timestep`` seconds; every sub-step maps a state to a state.

    Loops of steps should run under :func:`pipeline.threads.one_blas_thread` (as
    :func:`~pipeline.physics.drop.run` does): the solver's products are small and a threaded BLAS makes
    them many times slower on a busy machine.
    """
    state = wake(model, state)
    contacts = collide(model, state)
    warm = warm_start(state, contacts)
    # rolling resistance from last step's normal impulses, before the solve so contacts stay consistent
    free = rolling_resistance(model, external(model, state), contacts, warm)
    sol = solve_contacts(model, state, free, contacts, warm)
    moved = integrate(model, state.replace(vel=sol.vel, angvel=sol.angvel))
    out = update_sleep(model, advance(model, state, moved).state)
    pen = float(max(0.0, -contacts.dist.min())) if contacts.count else 0.0
    keep = np.any(sol.impulse != 0, axis=1)
    return out.replace(time=state.time + model.opt.timestep, ws_key=contacts.key[keep],
                       ws_impulse=sol.impulse[keep], max_penetration=pen)


def penetration(model: Model, state: State) -> float:
    """Deepest penetration (m) of any contact at ``state``, every body considered awake."""
    c = collide(model, state.replace(asleep=np.zeros(model.nbody, bool)))
    return float(max(0.0, -c.dist.min())) if c.count else 0.0
