"""Collision detection: contact points between bodies, static planes and the room distance field.

Every contact is a point on body ``a`` pushed along ``normal`` (pointing from ``b`` to ``a``) with a
signed distance ``dist`` (negative = penetration). Contacts are *speculative*: pairs closer than the
distance the bodies can travel in one step (plus ``Options.margin``) produce contacts with a positive
distance, which the solver turns into "arrive, do not cross" constraints; this is what keeps fast bodies
from tunnelling through thin surfaces (the CCD backstop in :mod:`pipeline.physics.ccd` catches the rest).

* body - plane: hull vertices (sphere centres minus the radius) against each half-space;
* body - room: hull vertices against the room's unsigned distance field minus the shell thickness
  (scan surfaces are open, one-sided and paper thin); normal = gradient of the field. With the room
  mesh (:class:`RoomMesh`), vertices the grid puts within reach are re-measured exactly (closest point
  on the mesh; a vertex has crossed the sheet when the sheet cuts the segment from its body's centre);
* body - body: hull vertices of one body against the face planes of the other, both ways (the signed
  distance of a point to a convex polytope is the largest plane distance); spheres by centre distance.

Per (body, other, side) only the ``Options.contacts_per_pair`` deepest points are kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.physics.integrate import quat_to_mat
from pipeline.physics.types import KIND_SPHERE, Model, State


@dataclass(frozen=True)
class Contacts:
    """Contact points (structure of arrays)."""

    body_a: np.ndarray    # (C,) int32, body owning the contact point
    body_b: np.ndarray    # (C,) int32, other body, -1 for the static world
    pos: np.ndarray       # (C, 3) float64, m, world contact point (on body a's surface)
    normal: np.ndarray    # (C, 3) float64, unit, world, from b to a
    dist: np.ndarray      # (C,) float64, m, signed distance (< 0: penetration)
    friction: np.ndarray  # (C,) float64, Coulomb coefficient of the pair
    key: np.ndarray       # (C,) int64, persistent feature id (warm start)

    @property
    def count(self) -> int:
        return int(self.body_a.shape[0])


def empty_contacts() -> Contacts:
    z = np.zeros(0)
    return Contacts(np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, 3)), np.zeros((0, 3)),
                    z, z.copy(), np.zeros(0, np.int64))


def world_vertices(model: Model, R: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """(B, V, 3) float64 hull vertices in the world for rotations (B,3,3) and com positions (B,3)."""
    return np.einsum("bij,bvj->bvi", R, model.body_verts) + pos[:, None, :]


def room_distance(model: Model, points: np.ndarray, *, gradient: bool = True
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """Trilinear unsigned distance to the model's room surface and its gradient (:func:`grid_distance`)."""
    return grid_distance(model.room_origin, model.room_spacing, model.room_udf, points, gradient=gradient)


def grid_distance(origin: np.ndarray, spacing: float, udf: np.ndarray, points: np.ndarray, *,
                  gradient: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """Trilinear unsigned distance to a surface from its distance grid (a :class:`Room`'s ``origin``,
    ``spacing`` and C-contiguous ``udf``), and its gradient.

    Parameters
    ----------
    points
        (..., 3) float64 world points, m.

    Returns
    -------
    udf : (...) float64, m; ``inf`` outside the grid
    grad : (..., 3) float64 unit direction away from the surface (None when not asked)
    """
    shp = points.shape[:-1]
    p = points.reshape(-1, 3)
    g = (p - origin) / spacing
    n = np.array(udf.shape)
    inside = np.all((g >= 0) & (g <= n - 1), axis=1)
    gi = np.clip(np.floor(g), 0, n - 2).astype(np.int64)
    f = np.clip(g - gi, 0.0, 1.0)
    u = udf
    sx, sy, sz = int(n[1] * n[2]), int(n[2]), 1    # C order (room_from_arrays makes the grid contiguous)
    lin = gi @ np.array([sx, sy, sz], np.int64)
    corner = np.array([dx * sx + dy * sy + dz * sz for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)])
    c = np.take(u.reshape(-1), lin[:, None] + corner[None, :]).astype(float).reshape(len(p), 2, 2, 2)
    fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
    cx = c[:, 0] * (1 - fx)[:, None, None] + c[:, 1] * fx[:, None, None]      # (N, 2, 2) over y, z
    cxy = cx[:, 0] * (1 - fy)[:, None] + cx[:, 1] * fy[:, None]               # (N, 2) over z
    d = cxy[:, 0] * (1 - fz) + cxy[:, 1] * fz
    d = np.where(inside, d, np.inf)
    if not gradient:
        return d.reshape(shp), None
    gz = cxy[:, 1] - cxy[:, 0]
    gy = (cx[:, 1] - cx[:, 0])
    gy = gy[:, 0] * (1 - fz) + gy[:, 1] * fz
    dxx = c[:, 1] - c[:, 0]                                                    # (N, 2, 2)
    dxy = dxx[:, 0] * (1 - fy)[:, None] + dxx[:, 1] * fy[:, None]
    gx = dxy[:, 0] * (1 - fz) + dxy[:, 1] * fz
    grad = np.stack([gx, gy, gz], axis=1)
    nrm = np.linalg.norm(grad, axis=1, keepdims=True)
    grad = np.where(nrm > 1e-12, grad / np.maximum(nrm, 1e-300), np.array([0.0, 0.0, 1.0]))
    return d.reshape(shp), grad.reshape(shp + (3,))


def speculative_margin(model: Model, state: State) -> np.ndarray:
    """(B,) float64, m: how far any point of each body can move this step, plus ``Options.margin``."""
    dt = model.opt.timestep
    g = float(np.linalg.norm(model.opt.gravity))
    sp = (np.linalg.norm(state.vel, axis=1) + np.linalg.norm(state.angvel, axis=1) * model.body_bound
          + g * dt) * dt
    return np.where(state.asleep, 0.0, sp) + model.opt.margin


def _select(d: np.ndarray, pts: np.ndarray, k: int, patch: float) -> np.ndarray:
    """Contact reduction: indices (G, k) into the last axis of ``d`` (G, V) of a spread-out support set.

    The deepest point first, then repeatedly the candidate farthest from those chosen, among points
    within ``patch`` of the deepest depth (the touching patch: a face resting on a plane keeps its
    corners, not an arbitrary cluster). Unused slots repeat the deepest point (the caller dedups by
    requiring distinct indices). Rows whose entries are all ``inf`` give index 0.
    """
    G, V = d.shape
    first = np.argmin(d, axis=1)
    dmin = d[np.arange(G), first]
    cand = d <= (dmin + patch)[:, None]
    chosen = [first]
    mind = np.linalg.norm(pts - pts[np.arange(G), first][:, None, :], axis=2)
    for _ in range(min(k, V) - 1):
        score = np.where(cand, mind, -1.0)
        nxt = np.argmax(score, axis=1)
        ok = score[np.arange(G), nxt] > 1e-9
        nxt = np.where(ok, nxt, first)
        chosen.append(nxt)
        mind = np.minimum(mind, np.linalg.norm(pts - pts[np.arange(G), nxt][:, None, :], axis=2))
    idx = np.stack(chosen, axis=1)
    # slots the patch could not fill take the next deepest points (speculative cover of the rest)
    dup = np.zeros_like(idx, bool)
    dup[:, 1:] = idx[:, 1:] == idx[:, :1]
    rows = np.flatnonzero(dup.any(axis=1))
    if len(rows):
        kk = idx.shape[1]
        order = np.argsort(d[rows], axis=1)[:, :2 * kk]                      # (R, <=2k) deepest first
        sub = idx[rows]
        free = ~np.any(order[:, :, None] == sub[:, None, :], axis=2)          # not chosen yet
        comp = np.take_along_axis(order, np.argsort(~free, axis=1, kind="stable"), 1)  # free ones first
        nfree = free.sum(axis=1)
        dsub = dup[rows]
        rank = np.cumsum(dsub, axis=1) - 1                                    # j-th unfilled slot
        fill = dsub & (rank < nfree[:, None])
        r_, s_ = np.nonzero(fill)
        sub[r_, s_] = comp[r_, rank[r_, s_]]
        idx[rows] = sub
    return idx


def _pick(d: np.ndarray, pts: np.ndarray, k: int, patch: float, reach: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Selected (row, column) pairs and their depths: ``(rows, cols, dist)`` for entries < reach."""
    reach = np.broadcast_to(reach, (d.shape[0], 1))
    live = np.flatnonzero(d.min(axis=1) < reach[:, 0])      # rows with anything in reach
    if not len(live):
        z = np.zeros(0, np.int64)
        return z, z.copy(), np.zeros(0)
    d, pts, reach = d[live], pts[live], reach[live]
    idx = _select(d, pts, k, patch)
    dk = np.take_along_axis(d, idx, 1)
    ok = dk < reach
    ok[:, 1:] &= idx[:, 1:] != idx[:, :1]
    rows, slot = np.nonzero(ok)
    return live[rows], idx[rows, slot], dk[rows, slot]


@dataclass(frozen=True)
class PosedBodies:
    """The bodies' collision geometry placed in the world at one state, shared by the collision sub-steps."""

    R: np.ndarray        # (B, 3, 3) float64, body-to-world rotations
    Wv: np.ndarray       # (B, V, 3) float64, m, world hull vertices (padded)
    vmask: np.ndarray    # (B, V) bool, valid entries of Wv
    Wrv: np.ndarray      # (B, Vr, 3) float64, m, world vertices that touch the room (Wv or the object's own)
    rmask: np.ndarray    # (B, Vr) bool, valid entries of Wrv
    spec: np.ndarray     # (B,) float64, m, speculative margin (:func:`speculative_margin`)
    awake: np.ndarray    # (B,) bool
    k: int               # contact points kept per (body, other, side)
    patch: float         # m, points this close to the deepest one form the touching patch
    n_other: int         # number of "other" ids in a contact key (bodies, planes, the room)
    n_feat: int          # number of feature ids per (body, other) in a contact key


# One group of contacts found by a sub-step: (body_a int32, body_b int32, pos, normal, dist, key int64).
ContactRows = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def collide(model: Model, state: State) -> Contacts:
    """All contacts of the awake bodies (and between awake and sleeping ones) at ``state``.

    Contacts between two sleeping bodies, or a sleeping body and the static world, are skipped. The
    sub-steps, in the order their contacts are listed: :func:`plane_contacts`, :func:`room_contacts`,
    :func:`body_pair_contacts`.
    """
    B = model.nbody
    if B == 0:
        return empty_contacts()
    g = pose_bodies(model, state)
    out: list[ContactRows] = []
    aw = np.flatnonzero(g.awake)
    if len(aw):
        out += plane_contacts(model, g, aw)
        out += room_contacts(model, state, g, aw)
    if B > 1:
        out += body_pair_contacts(model, state, g)
    if not out:
        return empty_contacts()
    a = np.concatenate([o[0] for o in out])
    b = np.concatenate([o[1] for o in out])
    fa = model.body_friction[a]
    fb = np.where(b >= 0, model.body_friction[np.maximum(b, 0)], fa)
    return Contacts(body_a=a, body_b=b, pos=np.concatenate([o[2] for o in out]),
                    normal=np.concatenate([o[3] for o in out]), dist=np.concatenate([o[4] for o in out]),
                    friction=np.maximum(fa, fb), key=np.concatenate([o[5] for o in out]))


def pose_bodies(model: Model, state: State) -> PosedBodies:
    """The world geometry of every body at ``state`` (computed once per step, read by every sub-step)."""
    B = model.nbody
    k = model.opt.contacts_per_pair
    patch = 1e-3   # m: points this close to the deepest one form the touching patch
    R = quat_to_mat(state.quat)
    Wv = world_vertices(model, R, state.pos)                        # (B, V, 3)
    V = Wv.shape[1]
    vmask = np.arange(V)[None, :] < model.body_nvert[:, None]     # (B, V)
    spec = speculative_margin(model, state)
    awake = ~state.asleep
    P = len(model.plane)
    n_other = B + P + 1
    if not model.exact_room_contacts or model.body_room_verts is None:
        Wrv, rmask = Wv, vmask
    else:
        Wrv = np.einsum("bij,bvj->bvi", R, model.body_room_verts) + state.pos[:, None, :]
        rmask = np.arange(Wrv.shape[1])[None, :] < model.body_room_nvert[:, None]
    n_feat = max(2 * V + 1, Wrv.shape[1])
    return PosedBodies(R=R, Wv=Wv, vmask=vmask, Wrv=Wrv, rmask=rmask, spec=spec, awake=awake, k=k, patch=patch,
                       n_other=n_other, n_feat=n_feat)


def _rows(g: PosedBodies, a: np.ndarray, b: np.ndarray, pos: np.ndarray, n: np.ndarray, d: np.ndarray,
          other: int | np.ndarray, vidx: np.ndarray) -> ContactRows:
    """One group of contacts (C,) with its persistent keys from (body a, other: body, plane or room, feature)."""
    return (a.astype(np.int32), b.astype(np.int32), pos, n, d,
            (a.astype(np.int64) * g.n_other + other) * g.n_feat + vidx)


def plane_contacts(model: Model, g: PosedBodies, aw: np.ndarray) -> list[ContactRows]:
    """Contacts of the awake bodies ``aw`` (A,) with the static planes: hull vertices (sphere centres
    minus the radius) against each half-space."""
    B = model.nbody
    Wv, vmask, rad, spec, k, patch = g.Wv, g.vmask, model.body_radius, g.spec, g.k, g.patch
    out = []
    for p in range(len(model.plane)):
        n = model.plane[p, :3]
        d = Wv[aw] @ n - model.plane[p, 3] - rad[aw, None]            # (A, V)
        d = np.where(vmask[aw], d, np.inf)
        bi, vi, dk = _pick(d, Wv[aw], k, patch, spec[aw, None])
        body = aw[bi]
        pts = Wv[body, vi] - n * rad[body, None]
        out.append(_rows(g, body, np.full(len(body), -1), pts, np.broadcast_to(n, pts.shape).copy(), dk, B + p, vi))
    return out


def room_contacts(model: Model, state: State, g: PosedBodies, aw: np.ndarray) -> list[ContactRows]:
    """Contacts of the awake bodies ``aw`` (A,) with the room: their vertices against the room's distance
    field minus the shell thickness, re-measured on the room mesh where the grid puts them within reach."""
    if not model.has_room:
        return []
    B, P = model.nbody, len(model.plane)
    rad, spec, k, patch = model.body_radius, g.spec, g.k, g.patch
    # broad phase: the trilinear field changes by at most sqrt(3) per metre, so a body whose
    # centre is farther from the surface than its points can reach has no candidate
    cu, _ = room_distance(model, state.pos[aw], gradient=False)
    ar = aw[~(cu - np.sqrt(3.0) * model.body_bound[aw] > model.room_thickness + rad[aw] + spec[aw]
              + 0.5 * model.room_spacing)]
    if not len(ar):
        return []
    near = model.room_thickness + rad[ar, None] + spec[ar, None]
    vm = g.rmask[ar]
    Wr = g.Wrv[ar]
    udf, grad = room_distance(model, Wr)
    if model.room_mesh is not None:
        sel = vm & (udf < near + 0.5 * model.room_spacing)
        if np.any(sel):
            de, ne = model.room_mesh.closest(
                Wr[sel], np.broadcast_to(state.pos[ar][:, None, :], Wr.shape)[sel])
            udf[sel] = de
            grad[sel] = ne
    d = udf - model.room_thickness - rad[ar, None]
    d = np.where(vm, d, np.inf)
    bi, vi, dk = _pick(d, Wr, k, patch, spec[ar, None])
    body = ar[bi]
    nrm = grad[bi, vi]
    pts = g.Wrv[body, vi] - nrm * rad[body, None]
    return [_rows(g, body, np.full(len(body), -1), pts, nrm, dk, B + P, vi)]


def body_pair_contacts(model: Model, state: State, g: PosedBodies) -> list[ContactRows]:
    """Contacts between pairs of bodies whose bounding spheres come within reach (at least one awake):
    :func:`_sphere_pairs`, :func:`_sphere_polyhedron_pairs`, then :func:`_polyhedron_pairs`."""
    B = model.nbody
    spec, awake = g.spec, g.awake
    I, J = np.triu_indices(B)
    off = I != J
    I, J = I[off], J[off]
    reach = model.body_bound[I] + model.body_bound[J] + spec[I] + spec[J]
    close = np.linalg.norm(state.pos[I] - state.pos[J], axis=1) < reach
    close &= awake[I] | awake[J]
    I, J = I[close], J[close]
    if not len(I):
        return []
    sph = (model.body_kind[I] == KIND_SPHERE) & (model.body_kind[J] == KIND_SPHERE)
    out = []
    if np.any(sph):
        out.append(_sphere_pairs(model, state, g, I[sph], J[sph]))
    out += _sphere_polyhedron_pairs(model, state, g, I[~sph], J[~sph])
    # polyhedron pairs: vertices of each body against the face planes of the other
    pp = (model.body_kind[I] != KIND_SPHERE) & (model.body_kind[J] != KIND_SPHERE)
    if np.any(pp):
        out += _polyhedron_pairs(model, state, g, I[pp], J[pp])
    return out


def _sphere_pairs(model: Model, state: State, g: PosedBodies, a: np.ndarray, b: np.ndarray) -> ContactRows:
    """Sphere - sphere contacts of the pairs ``(a, b)`` (Q,) by centre distance."""
    rad, spec = model.body_radius, g.spec
    dv = state.pos[a] - state.pos[b]
    dist = np.linalg.norm(dv, axis=1)
    n = dv / np.maximum(dist, 1e-12)[:, None]
    d = dist - rad[a] - rad[b]
    s = d < spec[a] + spec[b]
    a, b, n, d = a[s], b[s], n[s], d[s]
    return _rows(g, a, b, state.pos[a] - n * rad[a, None], n, d, b, np.zeros(len(a), np.int64))


def _sphere_polyhedron_pairs(model: Model, state: State, g: PosedBodies, I: np.ndarray, J: np.ndarray
                             ) -> list[ContactRows]:
    """Sphere - polyhedron contacts among the pairs ``(I, J)`` (Q,), both ways: the sphere's centre
    against the polyhedron's face planes (the largest plane distance is the signed distance)."""
    R, rad, spec = g.R, model.body_radius, g.spec
    out = []
    for A_, B_ in ((I, J), (J, I)):
        sel = (model.body_kind[A_] == KIND_SPHERE) & (model.body_kind[B_] != KIND_SPHERE)
        A_, B_ = A_[sel], B_[sel]
        if not len(A_):
            continue
        nW = np.einsum("pij,pfj->pfi", R[B_], model.body_planes[B_, :, :3])
        dW = model.body_planes[B_, :, 3] + np.einsum("pfi,pi->pf", nW, state.pos[B_])
        sd = np.einsum("pi,pfi->pf", state.pos[A_], nW) - dW
        f = np.argmax(sd, axis=1)
        d = sd[np.arange(len(A_)), f] - rad[A_]
        s = d < spec[A_] + spec[B_]
        a, b, f, d = A_[s], B_[s], f[s], d[s]
        n = nW[s, f] if len(a) else np.zeros((0, 3))
        out.append(_rows(g, a, b, state.pos[a] - n * rad[a, None], n, d, b, np.zeros(len(a), np.int64)))
    return out


def _polyhedron_pairs(model: Model, state: State, g: PosedBodies, A_: np.ndarray, B_: np.ndarray
                      ) -> list[ContactRows]:
    """Polyhedron - polyhedron contacts of the pairs ``(A_, B_)`` (Q,): the pair's axis is the face normal
    that separates them best (SAT on face axes); points of each body that lie over the other become
    contacts along it, at their own distance to the other body."""
    R, Wv, vmask, spec, k, patch = g.R, g.Wv, g.vmask, g.spec, g.k, g.patch
    V = Wv.shape[1]
    Q = len(A_)
    qa = np.arange(Q)
    nWB = np.einsum("pij,pfj->pfi", R[B_], model.body_planes[B_, :, :3])   # (Q, F, 3)
    dWB = model.body_planes[B_, :, 3] + np.einsum("pfi,pi->pf", nWB, state.pos[B_])
    nWA = np.einsum("pij,pfj->pfi", R[A_], model.body_planes[A_, :, :3])
    dWA = model.body_planes[A_, :, 3] + np.einsum("pfi,pi->pf", nWA, state.pos[A_])
    mA, mB = vmask[A_], vmask[B_]
    sdAB = np.einsum("pvi,pfi->pvf", Wv[A_], nWB) - dWB[:, None, :]       # (Q, V, F)
    sdBA = np.einsum("pvi,pfi->pvf", Wv[B_], nWA) - dWA[:, None, :]
    sepB = np.where(mA[:, :, None], sdAB, np.inf).min(axis=1)              # (Q, F)
    sepA = np.where(mB[:, :, None], sdBA, np.inf).min(axis=1)
    fB, fA = np.argmax(sepB, axis=1), np.argmax(sepA, axis=1)
    # the pair's axis is the face normal of either body that separates them best (SAT
    # on face axes); points of each body that lie over the other body (their distance to
    # it, ignoring faces facing along the axis, is small) become contacts along that axis
    useB = sepB[qa, fB] >= sepA[qa, fA] - 1e-6
    n = np.where(useB[:, None], nWB[qa, fB], -nWA[qa, fA])               # (Q, 3) B -> A
    reach = (spec[A_] + spec[B_])[:, None]
    lateral = model.opt.margin
    out = []
    for side, (sd, nW, sgn, mask, owner) in enumerate((
            (sdAB, nWB, 1.0, mA, A_), (sdBA, nWA, -1.0, mB, B_))):
        # each point's distance to the other body along the axis (towards it): the line
        # p + s u crosses the other polytope for s in [s_lo, s_hi] (each face plane bounds
        # s from one side); s_lo is where it enters: the gap (> 0) or depth (< 0). Points
        # whose line misses the other body (by more than the margin) are not over it. The
        # support plane of the other body along the axis would give every point over it
        # the depth of its lowest point: wrong lever arms for a body standing on an edge
        cf = -sgn * np.einsum("pfi,pi->pf", nW, n)[:, None, :]              # (Q, 1, F)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = -sd / cf                                                # (Q, V, F)
        s_lo = np.where(cf < -1e-9, ratio, -np.inf).max(axis=2)            # (Q, V)
        s_hi = np.where(cf > 1e-9, ratio, np.inf).min(axis=2)
        par = np.where(np.abs(cf) <= 1e-9, sd, -np.inf).max(axis=2)
        miss = np.maximum(s_lo - s_hi, par)
        d = np.where(mask & (miss < lateral), s_lo, np.inf)
        qi, vi, dk = _pick(d, Wv[owner], k, patch, reach)
        out.append(_rows(g, A_[qi], B_[qi], Wv[owner[qi], vi], n[qi], dk, B_[qi], vi + side * V))
    return out
