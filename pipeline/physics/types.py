"""The physics types: frozen model, state, options and body description (structure of arrays).

A leaf module (it imports nothing of the project), as MJX's ``types.py``. The engine follows MuJoCo's
split: a static :class:`Model` (bodies, collision geometry, the static world, options) and a dynamic
:class:`State` (poses, velocities, sleep bookkeeping, solver warm start). Every sub-step of
``step(model, state) -> State`` takes and returns these and never validates;
:func:`pipeline.physics.io.build_model` builds and validates a model once, at the boundary.

Conventions: metres, kilograms, seconds, world frame of the scan. A body's frame is its centre of mass
with its principal axes; ``body_R_m2b``/``body_t_m2b`` map the object model's own frame into it, so a
model-to-world pose is ``R_b2w @ R_m2b`` and ``R_b2w @ t_m2b + pos``. Quaternions are (w, x, y, z),
body-to-world.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pipeline.physics.roommesh import RoomMesh

KIND_POLY = 0    # convex polyhedron: hull vertices + face planes
KIND_SPHERE = 1  # sphere: one point (the centre) plus a radius

PAD_PLANE_OFFSET = 1e9  # offset of padding face planes: n = 0, so n.x - d = -1e9 never wins a max


@dataclass(frozen=True)
class Options:
    """Simulation options (MuJoCo names where one exists)."""

    timestep: float = 0.02           # s
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)  # m/s^2, world frame
    friction: float = 0.5            # Coulomb coefficient used when a body gives none
    solref: tuple[float, float] = (0.04, 1.0)   # (time constant s, damping ratio); tc >= 2 dt enforced
    solimp: tuple[float, float, float] = (0.99, 0.99, 0.001)  # (dmin, dmax, width m); dmin = dmax
    # keeps impacts inelastic without a rebound through the surface (b dt and R cancel exactly)
    impratio: float = 10.0           # friction rows are impratio x harder than normal rows
    soft_impact: bool = False        # MuJoCo's continuous soft impact: bodies sink ~v tc / e into what
    #                                  they hit and spring back (the MuJoCo comparison); off: a body
    #                                  reaching a surface stops on it in one step (scan sheets, piles)
    rolling: float = 0.002           # m, rolling/torsional resistance length (0 = off)
    iterations: int = 100            # solver iterations per step (upper bound; resting contacts need none)
    tolerance: float = 1e-5          # m/s: solver stops when no body's velocity (any point within its
    #                                  bounding sphere) changes by more than this in an iteration
    margin: float = 0.005            # contact detection distance beyond speculative margins, m
    contacts_per_pair: int = 6       # contact points kept per (body, body or static) pair and side
    sleep_linear: float = 0.01       # m/s below which a body may fall asleep
    sleep_angular: float = 0.1       # rad/s below which a body may fall asleep
    sleep_time: float = 0.4          # s of continuous rest before a body sleeps
    sleep_drift: float = 0.002       # m: a body whose points stay within this of where its rest began
    #                                  also counts as resting (contact jitter without net motion)
    wake_speed: float = 0.05         # m/s: a body moving faster wakes sleeping bodies it touches
    ccd: bool = True                 # conservative advancement against the room distance field


@dataclass(frozen=True)
class Room:
    """The scanned room the bodies collide with (built by :func:`pipeline.physics.io.room_from_arrays`)."""

    origin: np.ndarray           # (3,) float64, m, world position of udf[0, 0, 0]
    spacing: float               # m, grid spacing
    udf: np.ndarray              # (nx, ny, nz) float32, m, unsigned distance to the room surface
    mesh: RoomMesh | None = None  # the surface itself, for exact distances at contacts (the grid's
    #                               trilinear gradient near the surface is off by millimetres)


@dataclass(frozen=True)
class Model:
    """Static description of a scene: bodies, their geometry, the static world and options."""

    body_mass: np.ndarray        # (B,) float64, kg
    body_inertia: np.ndarray     # (B, 3) float64, principal moments about the com, kg m^2
    body_kind: np.ndarray        # (B,) int32, KIND_POLY | KIND_SPHERE
    body_radius: np.ndarray      # (B,) float64, m: sphere radius (0 for polyhedra)
    body_friction: np.ndarray    # (B,) float64, Coulomb coefficient
    body_verts: np.ndarray       # (B, V, 3) float64, m, body frame; hull vertices (padded by repetition)
    body_nvert: np.ndarray       # (B,) int32, valid entries of body_verts
    body_planes: np.ndarray      # (B, F, 4) float64: outward unit normal n and offset d, n.x <= d inside
    body_bound: np.ndarray       # (B,) float64, m, radius of a sphere about the com holding the body
    body_R_m2b: np.ndarray       # (B, 3, 3) float64, object-model frame -> body frame rotation
    body_t_m2b: np.ndarray       # (B, 3) float64, m, object-model frame -> body frame translation
    plane: np.ndarray            # (P, 4) float64, static half-spaces n.x >= d (n unit, pointing out of them)
    room_origin: np.ndarray      # (3,) float64, m, world position of udf[0, 0, 0]
    room_spacing: float          # m, grid spacing of the room distance field (0 = no room)
    room_udf: np.ndarray         # (nx, ny, nz) float32, m, unsigned distance to the room surface
    room_thickness: float        # m, the surface counts as a shell of this half-thickness
    opt: Options = field(default_factory=Options)
    room_mesh: RoomMesh | None = None  # exact closest-point queries on the room surface, None = grid only
    body_room_verts: np.ndarray | None = None  # (B, Vr, 3) float64, m, body frame: the object's own hull
    #                                            vertices (padded by repetition), built with a room
    body_room_nvert: np.ndarray | None = None  # (B,) int32, valid entries of body_room_verts
    exact_room_contacts: bool = False  # room contacts at body_room_verts (the object itself touches the
    #                                    surface) instead of body_verts (the collision hull, inside it by
    #                                    up to millimetres: fine against a thick shell)

    @property
    def nbody(self) -> int:
        return int(self.body_mass.shape[0])

    @property
    def has_room(self) -> bool:
        return self.room_spacing > 0 and self.room_udf.size > 0

    @property
    def room_upper(self) -> np.ndarray:
        """(3,) float64, m, world position of the last grid node."""
        return self.room_origin + self.room_spacing * (np.array(self.room_udf.shape, float) - 1)


@dataclass(frozen=True)
class State:
    """Dynamic state of every body (structure of arrays)."""

    time: float                  # s
    pos: np.ndarray              # (B, 3) float64, m, com in world
    quat: np.ndarray             # (B, 4) float64, (w, x, y, z) body-to-world, unit
    vel: np.ndarray              # (B, 3) float64, m/s, com velocity in world
    angvel: np.ndarray           # (B, 3) float64, rad/s, angular velocity in world
    asleep: np.ndarray           # (B,) bool, body is not integrated
    rest_time: np.ndarray        # (B,) float64, s, time spent below the sleep thresholds
    ws_key: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (K,) contact feature keys
    ws_impulse: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))   # (K, 3) N s, last impulses
    max_penetration: float = 0.0  # m, deepest contact penetration at the last step
    anchor_pos: np.ndarray | None = None   # (B, 3) m, pose where each body's current rest began
    anchor_quat: np.ndarray | None = None  # (B, 4) orientation where each body's current rest began

    def replace(self, **kw) -> "State":
        return replace(self, **kw)


@dataclass(frozen=True)
class Body:
    """One body's description as given by a caller (validated by :func:`pipeline.physics.io.build_model`)."""

    vertices: np.ndarray         # (V, 3) float64, m, object-model frame; hull vertices (or any points)
    mass: float                  # kg
    com: np.ndarray              # (3,) float64, m, object-model frame
    inertia: np.ndarray          # (3, 3) float64, kg m^2, about the com, object-model frame axes
    friction: float = -1.0       # < 0: Options.friction
    radius: float = 0.0          # > 0 makes a sphere of this radius centred at com (vertices ignored)
    # the body's hull in its body frame, computed once by build_model and reused by later models
    # (a drop builds a new model every time; the hull does not change)
    hull_cache: dict = field(default_factory=dict, compare=False, repr=False)
