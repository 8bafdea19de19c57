"""A drop: N objects spawned above a room, simulated until they all sleep or the time limit.

The spawn box follows the published recipe: in a gravity-aligned frame of the room's bounds it covers
most of the horizontal extent (``spawn_xy`` of it, centred) and a slab slightly above the vertical
centre (``spawn_z`` as fractions of the height). Poses are sampled without overlap (bounding spheres
apart from each other and from the room surface); orientations are uniform; with probability
``p_velocity`` a body also gets a random initial velocity and spin (without it, objects land in the same
spots every time). The verdict is ``accepted`` or ``rejected:<reason>`` with reasons ``left-room`` (a
body fell out of the room's grid, e.g. through a hole in the scan), ``never-settled`` (not all asleep at
``max_time``), ``penetration`` (deeper than ``max_penetration``) and ``spawn`` (no free spawn pose).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from pipeline.physics.step import penetration, step
from pipeline.physics.io import build_model, make_state, model_poses
from pipeline.physics.types import Body, Model, Options, Room, State
from pipeline.threads import one_blas_thread

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DropSettings:
    """Plain values controlling one drop."""

    timestep: float = 0.02                 # s (published default)
    max_time: float = 40.0                 # s (published default)
    spawn_xy: float = 0.8                  # share of the room's horizontal extent covered, centred
    spawn_z: tuple[float, float] = (0.5, 0.65)  # spawn slab, fractions of the room height from its floor
    p_velocity: float = 0.0                # probability that a body gets a random initial velocity/spin
    max_speed: float = 1.0                 # m/s, largest random initial speed
    max_spin: float = 6.0                  # rad/s, largest random initial spin
    max_penetration: float = 0.002         # m, deeper final penetration rejects the drop
    room_thickness: float = 0.01           # m, half-thickness of the scan surface shell while bodies fall
    #                                        and tumble: it bridges small holes, keeps sweeps from
    #                                        jumping through paper-thin surfaces and bodies from wedging
    #                                        into scan clutter (5 mm measured worse on the 7-Scenes room)
    rest_thickness: float = 0.001          # m: once every body sleeps on that shell, the shell shrinks to
    #                                        this and the bodies settle again onto the surface itself
    #                                        (they move by the difference, slowly: nothing tunnels or
    #                                        wedges). >= room_thickness turns the settling off
    settle_time: float = 3.0               # s, longest the settling onto the surface may take
    friction: float = 0.5                  # Coulomb coefficient
    spawn_tries: int = 200                 # samples per body before giving up
    floor_plane: bool = True               # a static plane at the scan's floor catches bodies that fall
    #                                        through holes of the scanned floor (real scans have many)


@dataclass(frozen=True)
class DropResult:
    """Outcome of one drop."""

    R_m2w: np.ndarray         # (N, 3, 3) float64 final model-to-world rotations
    t_m2w: np.ndarray         # (N, 3) float64, m, final model-to-world translations
    at_rest: np.ndarray       # (N,) bool, asleep at the end
    max_penetration: float    # m, deepest contact penetration at the end
    verdict: str              # "accepted" | "rejected:<reason>"
    sim_time: float           # s simulated
    steps: int


def gravity_frame(up: np.ndarray) -> np.ndarray:
    """(3, 3) rotation world -> gravity frame whose z axis is ``up``."""
    u = np.asarray(up, float) / np.linalg.norm(up)
    a = np.array([1.0, 0, 0]) if abs(u[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(a, u)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(u, x), u])


def _surface_points(room: Room | np.ndarray) -> np.ndarray:
    """(N, 3) float64 world grid nodes at the room surface; ``room`` may already be such points
    (:func:`surface_points` computed once and passed to several of the functions below)."""
    if isinstance(room, np.ndarray):
        return room
    udf = np.asarray(room.udf)
    sp = float(room.spacing)
    ijk = np.argwhere(udf < 0.75 * sp)
    if len(ijk) == 0:
        raise ValueError("room proxy has no surface (udf never below the grid spacing)")
    return np.asarray(room.origin, float) + ijk * sp


def surface_points(room: Room) -> np.ndarray:
    """(N, 3) float64 world grid nodes at the room surface (udf below 0.75 spacing), m; accepted in
    place of the room by :func:`room_frame`, :func:`floor_height` and :func:`room_bounds`."""
    return _surface_points(room)


def room_frame(room: Room | np.ndarray, up: np.ndarray) -> np.ndarray:
    """(3, 3) world -> room frame: z = up, x/y = principal horizontal axes of the room surface (so the
    spawn box of a room whose walls are not aligned with the world axes stays inside the walls)."""
    R = gravity_frame(up)
    g = _surface_points(room) @ R.T
    xy = g[:, :2] - g[:, :2].mean(0)
    _, vecs = np.linalg.eigh(xy.T @ xy)
    a = vecs[:, 1]
    Rz = np.array([[a[0], a[1], 0.0], [-a[1], a[0], 0.0], [0.0, 0.0, 1.0]])
    return Rz @ R


def floor_height(room: Room | np.ndarray, R_w2g: np.ndarray) -> float:
    """Height (along the frame's z = up) of the floor: the most populated 1 cm height bin of the room
    surface among its lowest 30 % (the floor is the largest horizontal surface at the bottom)."""
    z = (_surface_points(room) @ R_w2g.T)[:, 2]
    low = z[z <= np.percentile(z, 30)]
    bins = np.arange(low.min(), low.max() + 0.02, 0.01)
    h, e = np.histogram(low, bins=bins)
    return float(e[np.argmax(h)] + 0.005)


def room_bounds(room: Room | np.ndarray, R_w2g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bounds (lo, hi) (3,) of the room surface in the frame ``R_w2g`` (0.5 / 99.5 percentiles of the
    grid nodes at the surface, so stray reconstruction blobs do not stretch them)."""
    g = _surface_points(room) @ R_w2g.T
    return np.percentile(g, 0.5, axis=0), np.percentile(g, 99.5, axis=0)


@dataclass(frozen=True)
class RoomInfo:
    """What drops need from a room's surface, computed once per room by :func:`room_info` (finding the
    surface nodes of a large grid costs tens of milliseconds, as much as a few dozen steps)."""

    surface: np.ndarray   # (N, 3) float64, m, world grid nodes at the surface (:func:`surface_points`)
    R_w2g: np.ndarray     # (3, 3) float64 world -> room frame (:func:`room_frame`, z = up)
    lo: np.ndarray        # (3,) float64, m, room bounds in that frame (:func:`room_bounds`)
    hi: np.ndarray        # (3,) float64, m
    floor: float          # m, floor height in that frame (:func:`floor_height`)


def room_info(room: Room, up: np.ndarray) -> RoomInfo:
    """:class:`RoomInfo` of a room proxy for the world up vector ``up`` (3,)."""
    u = np.asarray(up, float) / np.linalg.norm(up)
    surf = surface_points(room)
    R = room_frame(surf, u)
    lo, hi = room_bounds(surf, R)
    return RoomInfo(surface=surf, R_w2g=R, lo=lo, hi=hi, floor=floor_height(surf, R))


def _random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.random(n, random_state=rng).as_matrix()


def spawn(bodies: list[Body], model: Model, up: np.ndarray, settings: DropSettings,
          rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, R_w2g: np.ndarray | None = None
          ) -> tuple[np.ndarray, np.ndarray] | None:
    """Non-overlapping random model-to-world poses in the spawn box, or None when none was found.

    With a room, a spawn point must also be clear of the surface and have the room's surface somewhere
    below it (not beside the room, where the spawn box of a non-rectangular room pokes out).

    Returns ``(R_m2w (N,3,3), t_m2w (N,3))``.
    """
    from pipeline.physics.collide import room_distance

    R_w2g = gravity_frame(up) if R_w2g is None else R_w2g
    ext = hi - lo
    m = 0.5 * (1 - settings.spawn_xy)
    box_lo = np.array([lo[0] + m * ext[0], lo[1] + m * ext[1], lo[2] + settings.spawn_z[0] * ext[2]])
    box_hi = np.array([hi[0] - m * ext[0], hi[1] - m * ext[1], lo[2] + settings.spawn_z[1] * ext[2]])
    N = len(bodies)
    Rs = _random_rotations(rng, N)
    com_w = np.zeros((N, 3))
    for i in range(N):
        r = model.body_bound[i]
        for _ in range(settings.spawn_tries):
            c = R_w2g.T @ rng.uniform(box_lo, box_hi)
            if i and np.any(np.linalg.norm(com_w[:i] - c, axis=1) < model.body_bound[:i] + r + 0.005):
                continue
            if model.has_room:
                d, _ = room_distance(model, c[None], gradient=False)
                if not d[0] > r + model.room_thickness + 0.005:
                    continue
                # surface below the whole footprint (centre and four points a bound radius out):
                # scans have holes, and a body dropped over one leaves the room
                feet = c + np.array([[0, 0], [r, 0], [-r, 0], [0, r], [0, -r]]) @ R_w2g[:2]
                drop_line = np.arange(0.0, 1.2 * ext[2], model.room_spacing)
                below = feet[:, None, :] - drop_line[None, :, None] * R_w2g[2]
                db, _ = room_distance(model, below, gradient=False)
                if not np.all(np.any(db < 1.5 * model.room_spacing, axis=1)):
                    continue
            com_w[i] = c
            break
        else:
            return None
    # com_w is the body frame origin (com); convert to model-frame translations
    R_b2w = Rs @ np.transpose(model.body_R_m2b, (0, 2, 1))
    t = com_w + np.einsum("bij,bj->bi", R_b2w, model.body_t_m2b)
    return Rs, t


def simulate_drop(bodies: list[Body], *, room: Room | None, up: np.ndarray, settings: DropSettings,
                  rng: np.random.Generator, planes: np.ndarray | None = None,
                  bounds: tuple[np.ndarray, np.ndarray] | None = None,
                  spawn_bounds: tuple[np.ndarray, np.ndarray] | None = None,
                  info: RoomInfo | None = None) -> DropResult:
    """Spawn ``bodies`` above the room and simulate them to rest.

    Parameters
    ----------
    bodies
        Body descriptions (object-model frames, metres, kg).
    room
        Room proxy (``origin``, ``spacing``, ``udf``); None with ``planes`` for plane-only scenes.
    up
        (3,) world up vector (gravity is ``-9.81 up``).
    settings
        :class:`DropSettings`.
    rng
        The drop's own generator.
    planes
        (P, 4) extra static half-spaces.
    bounds
        (lo, hi) spawn reference bounds in the gravity frame; from the room when None.
    spawn_bounds
        (lo, hi) replacing ``bounds`` as the spawn reference only (same frame: the room frame when
        ``bounds`` is None); the room's bounds still decide whether a body left the room. Used by the
        simulate stage to spawn above a surface the selected cameras see (pipeline/view_spawn.py).
    info
        :func:`room_info` of ``room`` for ``up``, computed once and shared by the drops of a room;
        computed here when None.
    """
    up = np.asarray(up, float) / np.linalg.norm(up)
    opt = Options(timestep=settings.timestep, gravity=tuple(-9.81 * up), friction=settings.friction)
    if bounds is None:
        if room is None:
            raise ValueError("simulate_drop needs a room or explicit spawn bounds")
        info = room_info(room, up) if info is None else info
        R_w2g = info.R_w2g
        bounds = (info.lo, info.hi)
        if settings.floor_plane:
            # under the floor (the lower edge of its 1 cm height bin): it only catches what falls
            # through a hole; bodies rest on the scanned floor itself
            fl = np.array([[*up, info.floor - 0.005]])
            planes = fl if planes is None else np.concatenate([np.asarray(planes, float).reshape(-1, 4), fl])
    else:
        R_w2g = gravity_frame(up)
    model = build_model(bodies, planes=planes, room=room, room_thickness=settings.room_thickness, opt=opt)
    lo, hi = bounds
    s_lo, s_hi = (lo, hi) if spawn_bounds is None else spawn_bounds
    poses = spawn(bodies, model, up, settings, rng, s_lo, s_hi, R_w2g)
    N = len(bodies)
    if poses is None:
        return DropResult(np.repeat(np.eye(3)[None], N, 0), np.zeros((N, 3)), np.zeros(N, bool), 0.0,
                          "rejected:spawn", 0.0, 0)
    R0, t0 = poses
    vel = np.zeros((N, 3))
    ang = np.zeros((N, 3))
    kick = rng.random(N) < settings.p_velocity
    if np.any(kick):
        k = int(kick.sum())
        dirs = rng.normal(size=(k, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        vel[kick] = dirs * rng.uniform(0, settings.max_speed, (k, 1))
        axes = rng.normal(size=(k, 3))
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        ang[kick] = axes * rng.uniform(0, settings.max_spin, (k, 1))
    state = make_state(model, R0, t0, vel=vel, angvel=ang)
    return run(model, state, settings, R_w2g=R_w2g, floor=lo[2], lo=lo, hi=hi)


def left_room(model: Model, state: State, R_w2g: np.ndarray, floor: float,
              lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: body centres outside the room grid, more than 0.5 m below the room's floor, or (with
    ``lo``/``hi``, room-frame bounds) outside the room's horizontal extent."""
    g = state.pos @ R_w2g.T
    out = g[:, 2] < floor - 0.5
    if lo is not None:
        out |= np.any((g[:, :2] < lo[:2]) | (g[:, :2] > hi[:2]), axis=1)
    if model.has_room:
        out |= np.any((state.pos < model.room_origin) | (state.pos > model.room_upper), axis=1)
    return out


def run(model: Model, state: State, settings: DropSettings, *, R_w2g: np.ndarray | None = None,
        floor: float = -np.inf, lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> DropResult:
    """Step until every body sleeps, a body leaves the room, or ``settings.max_time``."""
    with one_blas_thread():
        return _run(model, state, settings, R_w2g=R_w2g, floor=floor, lo=lo, hi=hi)


def _run(model: Model, state: State, settings: DropSettings, *, R_w2g: np.ndarray | None,
         floor: float, lo: np.ndarray | None, hi: np.ndarray | None) -> DropResult:
    R_w2g = np.eye(3) if R_w2g is None else R_w2g
    nsteps = int(round(settings.max_time / model.opt.timestep))
    verdict = "accepted"
    k = 0
    for k in range(1, nsteps + 1):
        state = step(model, state)
        if k % 10 == 0 and np.any(left_room(model, state, R_w2g, floor, lo, hi)):
            verdict = "rejected:left-room"
            break
        if np.all(state.asleep):
            break
    if verdict == "accepted" and np.any(left_room(model, state, R_w2g, floor, lo, hi)):
        verdict = "rejected:left-room"
    settle = 0
    if (verdict == "accepted" and np.all(state.asleep) and model.has_room
            and settings.rest_thickness < model.room_thickness):
        model, state, settle = settle_onto_surface(model, state, settings)
        if np.any(left_room(model, state, R_w2g, floor, lo, hi)):
            verdict = "rejected:left-room"
    pen = penetration(model, state)
    if verdict == "accepted" and not np.all(state.asleep):
        verdict = "rejected:never-settled"
    if verdict == "accepted" and pen > settings.max_penetration:
        verdict = "rejected:penetration"
    R, t = model_poses(model, state)
    return DropResult(R, t, state.asleep.copy(), pen, verdict, state.time, k + settle)


def settle_onto_surface(model: Model, state: State, settings: DropSettings) -> tuple[Model, State, int]:
    """Shrink the room shell to ``settings.rest_thickness`` and step the woken bodies until they sleep
    again (at most ``settings.settle_time``): bodies that came to rest on the shell come down onto the
    scanned surface. Room contacts are now taken at the object's own hull vertices, not at the few
    vertices of its collision hull (whose faces cut up to 8 mm inside the LM-O models): against a thin
    shell the object, not its proxy, must stop at the surface. Returns the thin-shell model, the state
    and the steps taken."""
    import dataclasses

    model = dataclasses.replace(model, room_thickness=float(settings.rest_thickness), exact_room_contacts=True)
    B = model.nbody
    state = state.replace(asleep=np.zeros(B, bool), rest_time=np.zeros(B), anchor_pos=None, anchor_quat=None)
    n = int(round(settings.settle_time / model.opt.timestep))
    k = 0
    for k in range(1, n + 1):
        state = step(model, state)
        if np.all(state.asleep):
            break
    return model, state, k
