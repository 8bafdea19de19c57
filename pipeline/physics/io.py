"""Building and validating physics models and states (MJX's ``io.py``): the boundary where caller input
becomes the frozen types of :mod:`pipeline.physics.types`, checked once.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np

from pipeline.errors import InputError
from pipeline.physics.types import KIND_POLY, KIND_SPHERE, PAD_PLANE_OFFSET, Body, Model, Options, Room, State

if TYPE_CHECKING:
    from pipeline.physics.roommesh import RoomMesh


# ---------------------------------------------------------------------------------------------------
# Geometry helpers
# ---------------------------------------------------------------------------------------------------

def hull_planes(points: np.ndarray, *, max_vertices: int = 48, max_points: int = 64,
                edge_spacing: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Convex hull of ``points`` reduced to at most ``max_vertices`` extreme vertices.

    Parameters
    ----------
    points
        (N, 3) float64, m.
    max_vertices
        Largest number of hull vertices kept (farthest-point subset of the hull's vertices).
    max_points
        Largest number of contact points (hull vertices first, then points along the edges).
    edge_spacing
        Spacing of the edge points, m (raised when ``max_points`` would be exceeded).

    Returns
    -------
    verts : (V, 3) float64 hull vertices followed by edge points (contact points)
    planes : (F, 4) float64 outward unit normals and offsets (n.x <= d inside), coplanar faces merged
    """
    from scipy.spatial import ConvexHull

    pts = np.asarray(points, float)
    hull = ConvexHull(pts)
    verts = pts[hull.vertices]
    if len(verts) > max_vertices:
        verts = farthest_points(verts, max_vertices)
        hull = ConvexHull(verts)
        verts = verts[hull.vertices]
        hull = ConvexHull(verts)
    eq = hull.equations  # (F, 4): n.x + c <= 0 inside
    # points along the hull's edges (and triangle diagonals): contacts where edges cross faces
    # (two boxes turned against each other touch where their edges cross, not at vertices)
    e = np.sort(np.concatenate([hull.simplices[:, [0, 1]], hull.simplices[:, [1, 2]],
                                hull.simplices[:, [2, 0]]]), axis=1)
    e = np.unique(e, axis=0)
    p0, p1 = hull.points[e[:, 0]], hull.points[e[:, 1]]
    length = np.linalg.norm(p1 - p0, axis=1)
    bound = float(np.linalg.norm(verts - verts.mean(0), axis=1).max())
    spacing = max(edge_spacing, bound / 3, float(length.sum()) / max(max_points - len(verts), 1))
    extra = [verts]
    for k in range(1, int(np.ceil(length.max() / spacing)) if len(length) else 1):
        cnt = np.ceil(length / spacing)
        sel = k < cnt
        extra.append(p0[sel] + (p1[sel] - p0[sel]) * (k / cnt[sel])[:, None])
    verts = np.concatenate(extra)[:max_points]
    planes = np.concatenate([eq[:, :3], -eq[:, 3:4]], axis=1)
    # merge coplanar triangles (same plane up to rounding)
    keyed = np.round(planes / np.array([1e-6, 1e-6, 1e-6, 1e-7]))
    _, idx = np.unique(keyed, axis=0, return_index=True)
    return verts, planes[np.sort(idx)]


def surface_points(points: np.ndarray, max_points: int = 256) -> np.ndarray:
    """The body's points that touch the room: its convex hull's vertices, a farthest-point subset of at
    most ``max_points`` of them (the first is the one farthest from their mean).

    The collision hull (:func:`hull_planes`) keeps few vertices, so its faces cut up to several
    millimetres inside a rounded object; against the scanned surface the object itself must touch, so
    room contacts are taken at these points instead.
    """
    from scipy.spatial import ConvexHull

    pts = np.asarray(points, float)
    verts = pts[ConvexHull(pts).vertices]
    return verts if len(verts) <= max_points else farthest_points(verts, max_points)


def farthest_points(verts: np.ndarray, k: int) -> np.ndarray:
    """``k`` of ``verts`` by farthest-point sampling, which keeps the extreme shape; the first is the
    point farthest from their mean."""
    chosen = [int(np.argmax(np.linalg.norm(verts - verts.mean(0), axis=1)))]
    d = np.linalg.norm(verts - verts[chosen[0]], axis=1)
    for _ in range(k - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(verts - verts[i], axis=1))
    return verts[np.array(chosen)]


def box_body(half_extents, mass: float, *, friction: float = -1.0) -> Body:
    """A solid box centred at the origin with the given half extents (m)."""
    h = np.asarray(half_extents, float)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * h
    ext = 2 * h
    inertia = mass / 12.0 * np.diag([ext[1] ** 2 + ext[2] ** 2, ext[0] ** 2 + ext[2] ** 2,
                                     ext[0] ** 2 + ext[1] ** 2])
    return Body(vertices=corners, mass=mass, com=np.zeros(3), inertia=inertia, friction=friction)


def sphere_body(radius: float, mass: float, *, friction: float = -1.0) -> Body:
    """A solid sphere centred at the origin."""
    return Body(vertices=np.zeros((1, 3)), mass=mass, com=np.zeros(3),
                inertia=np.eye(3) * 0.4 * mass * radius ** 2, friction=friction, radius=radius)


# ---------------------------------------------------------------------------------------------------
# Validation at the boundary
# ---------------------------------------------------------------------------------------------------

def _check_finite(name: str, a: np.ndarray) -> None:
    if not np.all(np.isfinite(a)):
        raise InputError(f"physics model: {name} has non-finite values; fix the object's mesh/solid")


def build_model(bodies: list[Body], *, planes: np.ndarray | None = None,
                room: Room | None = None, room_thickness: float = 0.01,
                opt: Options | None = None, max_vertices: int = 48) -> Model:
    """Validate bodies and the static world and build a frozen :class:`Model`.

    Per body :func:`_principal_frame` then :func:`_collider`; the bodies' geometry is padded to common
    sizes (:func:`_pad_geometry`); the static world is checked by :func:`_static_planes` and
    :func:`_room_grid`.

    Parameters
    ----------
    bodies
        Body descriptions in their object-model frames.
    planes
        (P, 4) static half-spaces ``n.x >= d`` (n need not be unit); None = none.
    room
        The room (:func:`room_from_arrays`; its surface mesh is shared across the drops of one room), or None.
    room_thickness
        Half-thickness of the room surface shell, m (scan surfaces have no inside).
    opt
        Options; defaults when None.
    max_vertices
        Hull vertices kept per body.
    """
    opt = opt or Options()
    if opt.timestep <= 0 or not math.isfinite(opt.timestep):
        raise InputError(f"physics options: timestep = {opt.timestep}; must be a positive number of seconds")
    B = len(bodies)
    masses, inertias, kinds, radii, frics, verts, rverts, plns, Rs, ts, bounds = ([] for _ in range(11))
    for i, b in enumerate(bodies):
        m = float(b.mass)
        if not (m > 0 and math.isfinite(m)):
            raise InputError(f"physics model: body {i} has mass {m}; give a positive mass (kg)")
        w, R_m2b, t_m2b = _principal_frame(i, b)
        fr = opt.friction if b.friction < 0 else float(b.friction)
        kind, radius, vb, pb, rb, bound = _collider(i, b, R_m2b, t_m2b, max_vertices, room is not None)
        kinds.append(kind)
        radii.append(radius)
        masses.append(m)
        inertias.append(w)
        frics.append(fr)
        verts.append(vb)
        rverts.append(rb)
        plns.append(pb)
        Rs.append(R_m2b)
        ts.append(t_m2b)
        bounds.append(bound)
    body_verts, room_verts, body_planes = _pad_geometry(verts, rverts, plns)
    pl = _static_planes(planes)
    udf, spacing, origin, room_mesh = _room_grid(room)
    return Model(body_mass=np.array(masses, float).reshape(B), body_inertia=np.array(inertias).reshape(B, 3),
                 body_kind=np.array(kinds, np.int32).reshape(B), body_radius=np.array(radii).reshape(B),
                 body_friction=np.array(frics).reshape(B), body_verts=body_verts,
                 body_nvert=np.array([len(v) for v in verts], np.int32).reshape(B), body_planes=body_planes,
                 body_bound=np.array(bounds).reshape(B), body_R_m2b=np.array(Rs).reshape(B, 3, 3),
                 body_t_m2b=np.array(ts).reshape(B, 3), plane=pl, room_origin=origin,
                 room_spacing=spacing, room_udf=udf, room_thickness=float(room_thickness), opt=opt,
                 room_mesh=room_mesh, body_room_verts=room_verts if room is not None else None,
                 body_room_nvert=np.array([len(v) for v in rverts], np.int32).reshape(B) if room is not None else None)


def _principal_frame(i: int, b: Body) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Body ``i``'s principal moments and the map from its object-model frame into its body frame (the
    centre of mass with the principal axes, right-handed), after checking that its inertia belongs to a
    real body.

    Returns ``(moments (3,) kg m^2, R_m2b (3, 3), t_m2b (3,) m)``.
    """
    I = np.asarray(b.inertia, float).reshape(3, 3)
    com = np.asarray(b.com, float).reshape(3)
    _check_finite(f"body {i} inertia", I)
    _check_finite(f"body {i} com", com)
    I = 0.5 * (I + I.T)
    w, V = np.linalg.eigh(I)
    if w[0] <= 0:
        raise InputError(f"physics model: body {i} inertia is not positive definite "
                         f"(eigenvalues {w}); recompute the solid's mass properties")
    if w[0] + w[1] < w[2] * (1 - 1e-6):
        raise InputError(f"physics model: body {i} inertia violates the triangle inequality "
                         f"(principal moments {w}); it cannot belong to a real body")
    if np.linalg.det(V) < 0:
        V[:, 2] *= -1
    R_m2b = V.T
    t_m2b = -R_m2b @ com
    return w, R_m2b, t_m2b


def _collider(i: int, b: Body, R_m2b: np.ndarray, t_m2b: np.ndarray, max_vertices: int, with_room: bool
              ) -> tuple[int, float, np.ndarray, np.ndarray, np.ndarray, float]:
    """Body ``i``'s collision geometry in its body frame: a sphere, or the convex hull of its vertices
    (cached on the :class:`Body`: the hull does not change between the models of a drop).

    Returns ``(kind, radius m, hull vertices (V, 3), face planes (F, 4), room contact points (Vr, 3),
    bound m)``; the bound covers the room contact points too when ``with_room``.
    """
    if b.radius > 0:
        vb = np.zeros((1, 3))
        return KIND_SPHERE, float(b.radius), vb, np.zeros((0, 4)), vb, float(b.radius)
    pts = np.asarray(b.vertices, float).reshape(-1, 3)
    _check_finite(f"body {i} vertices", pts)
    if len(pts) < 4:
        raise InputError(f"physics model: body {i} has {len(pts)} vertices; a solid needs >= 4")
    pts_b = pts @ R_m2b.T + t_m2b
    ck = (max_vertices, pts_b.tobytes())
    if ck in b.hull_cache:
        vb, pb, rb = b.hull_cache[ck]
    else:
        try:
            vb, pb = hull_planes(pts_b, max_vertices=max_vertices)
            rb = surface_points(pts_b)
        except Exception as e:  # qhull errors: flat or degenerate point sets
            raise InputError(f"physics model: body {i} vertices span no volume ({e}); "
                             f"a collider needs a 3D hull") from None
        b.hull_cache.clear()
        b.hull_cache[ck] = (vb, pb, rb)
    bound = float(np.linalg.norm(vb, axis=1).max())
    if with_room:
        bound = max(bound, float(np.linalg.norm(rb, axis=1).max()))
    return KIND_POLY, 0.0, vb, pb, rb, bound


def _pad_geometry(verts: list[np.ndarray], rverts: list[np.ndarray], plns: list[np.ndarray]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The bodies' hull vertices (B, V, 3), room contact points (B, Vr, 3) and face planes (B, F, 4) as
    arrays: vertices padded by repeating the first, planes by ones that never win a max."""
    B = len(verts)
    V = max([len(v) for v in verts], default=1)
    F = max([len(p) for p in plns], default=1) or 1
    body_verts = np.zeros((B, V, 3))
    Vr = max([len(v) for v in rverts], default=1)
    room_verts = np.zeros((B, Vr, 3))
    body_planes = np.zeros((B, F, 4))
    body_planes[:, :, 3] = PAD_PLANE_OFFSET
    for i in range(B):
        n = len(verts[i])
        body_verts[i, :n] = verts[i]
        body_verts[i, n:] = verts[i][0]
        room_verts[i, :len(rverts[i])] = rverts[i]
        room_verts[i, len(rverts[i]):] = rverts[i][0]
        body_planes[i, :len(plns[i])] = plns[i]
    return body_verts, room_verts, body_planes


def _static_planes(planes: np.ndarray | None) -> np.ndarray:
    """(P, 4) float64 static half-spaces with unit normals (``planes`` checked: finite, no zero normal)."""
    pl = np.zeros((0, 4)) if planes is None else np.asarray(planes, float).reshape(-1, 4)
    _check_finite("planes", pl)
    nn = np.linalg.norm(pl[:, :3], axis=1)
    if np.any(nn <= 0):
        raise InputError("physics model: a static plane has a zero normal")
    return pl / nn[:, None]


def _room_grid(room: Room | None) -> tuple[np.ndarray, float, np.ndarray, RoomMesh | None]:
    """The room's distance grid, checked: ``(udf, spacing, origin, mesh)``; an empty grid when no room."""
    if room is not None:
        udf, spacing, origin, room_mesh = room.udf, room.spacing, room.origin, room.mesh
        if udf.ndim != 3 or min(udf.shape) < 2:
            raise InputError(f"room proxy: udf has shape {udf.shape}; expected a 3D grid >= 2 per axis")
        if not spacing > 0:
            raise InputError(f"room proxy: spacing = {spacing}; must be positive metres")
        _check_finite("room udf", udf)
    else:
        udf, spacing, origin = np.zeros((0, 0, 0), np.float32), 0.0, np.zeros(3)
        room_mesh = None
    return udf, spacing, origin, room_mesh


def make_state(model: Model, R_m2w: np.ndarray, t_m2w: np.ndarray, *, vel: np.ndarray | None = None,
               angvel: np.ndarray | None = None) -> State:
    """Initial state from object-model poses in the world (model frame, not com frame).

    Parameters
    ----------
    R_m2w
        (B, 3, 3) float64 model-to-world rotations.
    t_m2w
        (B, 3) float64, m, model-to-world translations.
    vel, angvel
        (B, 3) float64 initial com velocity (m/s) and angular velocity (rad/s, world); zeros if None.
    """
    from pipeline.physics.integrate import mat_to_quat

    B = model.nbody
    R_m2w = np.asarray(R_m2w, float).reshape(B, 3, 3)
    t_m2w = np.asarray(t_m2w, float).reshape(B, 3)
    R_b2w = R_m2w @ np.transpose(model.body_R_m2b, (0, 2, 1))
    pos = t_m2w - np.einsum("bij,bj->bi", R_b2w, model.body_t_m2b)
    z = np.zeros((B, 3))
    return State(time=0.0, pos=pos, quat=mat_to_quat(R_b2w),
                 vel=z.copy() if vel is None else np.asarray(vel, float).reshape(B, 3),
                 angvel=z.copy() if angvel is None else np.asarray(angvel, float).reshape(B, 3),
                 asleep=np.zeros(B, bool), rest_time=np.zeros(B))


def model_poses(model: Model, state: State) -> tuple[np.ndarray, np.ndarray]:
    """Object-model-to-world poses of every body: ``(R_m2w (B,3,3), t_m2w (B,3))``."""
    from pipeline.physics.integrate import quat_to_mat

    R_b2w = quat_to_mat(state.quat)
    R_m2w = R_b2w @ model.body_R_m2b
    t_m2w = np.einsum("bij,bj->bi", R_b2w, model.body_t_m2b) + state.pos
    return R_m2w, t_m2w


def room_from_arrays(arrays: Mapping[str, np.ndarray]) -> Room:
    """A :class:`~pipeline.physics.types.Room` from prep's room proxy arrays: ``origin`` (3,), ``spacing``,
    ``udf`` (nx, ny, nz), and ``mesh_vertices`` (V, 3) / ``mesh_faces`` (T, 3) when present (the
    surface's BVH is built here, once per room)."""
    mesh = None
    if "mesh_vertices" in arrays and "mesh_faces" in arrays:
        from pipeline.physics.roommesh import RoomMesh

        mesh = RoomMesh(arrays["mesh_vertices"], arrays["mesh_faces"])
    return Room(origin=np.asarray(arrays["origin"], float).reshape(3), spacing=float(arrays["spacing"]),
                udf=np.ascontiguousarray(arrays["udf"], np.float32), mesh=mesh)
