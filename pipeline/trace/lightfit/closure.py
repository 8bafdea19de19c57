"""Step 1, the closing of the room: the scan's mesh, a box around it and the known lights, as one scene.

Rays that leave the mesh through a hole, or past the top of the scanned walls, meet a cell of the box, so
light no photo saw gets a place in the room, not only a direction. The box stands behind the cameras (whoever
held one stood in front of a wall no photo saw) and, for a scan that did not reach the ceiling, where a
ceiling would be. A box cell the mesh hides from every camera is behind a wall, not part of the room.
A scan is a shell seen from one side: a table top is one sheet, and its unseen back is no copy of its top.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from pipeline.geometry import up_frame

log = logging.getLogger(__name__)

MARGIN = 0.02                 # metres between the mesh's extent and the closing box
LOW_FILL_M = 0.8              # box cells lower than this above the scan's lowest point are filled, not fitted
ASSUMED_CEILING_M = 2.5       # a scan shorter than this (floor to top) is closed at this height above its lowest point
BEHIND_CAMERA_M = 0.5         # the unseen wall behind a camera is at least this far behind it (horizontally)


@dataclass(frozen=True)
class Room:
    """The room closed by a box, with the known lights: the scene every ray of the fit is traced in."""

    V: np.ndarray              # (nv, 3) float64 metres, the scan's mesh vertices
    F: np.ndarray              # (nt, 3) int64, its triangles
    cameras: list              # the photos' pipeline.camera.Camera, in order
    known_quads: list          # (4, 3) float64 metres, corners of each known light (trace.lights_file)
    known_normals: list        # (3,) float64, the side each known light emits on
    known_radiance: np.ndarray  # (k, 3) float64 linear radiance of each known light
    up: np.ndarray             # (3,) float64 unit up
    h_low: float               # metres along up of the lowest point the box encloses
    ceiling_assumed: bool      # the scan did not reach ASSUMED_CEILING_M: the box's top is put there
    box_v: np.ndarray          # (4C, 3) float64, four corners per box cell
    box_f: np.ndarray          # (2C, 3) int64, two triangles per cell, facing into the box
    box_centre: np.ndarray     # (C, 3) float64 cell centres
    box_normal: np.ndarray     # (C, 3) float64 inward unit normals
    floor_cell: np.ndarray     # (C,) bool: the box's bottom and the low band of its sides (never a light)
    ceiling_cell: np.ndarray   # (C,) bool: the box's top
    all_v: np.ndarray          # (nv + 4C + 4k, 3) float32: mesh, box, known lights' corners
    all_f: np.ndarray          # (nt + 2C + 2k, 3) int32: mesh, box, known lights' triangles
    isect: object              # pipeline.trace.intersect.EmbreeIntersector of all_v, all_f
    eps: float                 # metres, ray offset (1e-3 of the scene's extent)
    corners: np.ndarray        # (T, 3, 3) float64, every triangle's corners
    tri_normal: np.ndarray     # (T, 3) float64 unit normals
    tri_area: np.ndarray       # (T,) float64 m^2

    @property
    def nv(self) -> int:
        return len(self.V)

    @property
    def nt(self) -> int:
        return len(self.F)

    @property
    def nbt(self) -> int:
        """Triangles before the known lights' (mesh and box)."""
        return self.nt + len(self.box_f)

    @property
    def cams(self) -> list:
        """(3,) camera centres."""
        return [c.center for c in self.cameras]


def close_room(vertices: np.ndarray, faces: np.ndarray, frames: list, known_lights, up: np.ndarray,
               cell: float) -> Room:
    """The :class:`Room` of mesh ``vertices``, ``faces``, photographed as ``frames`` (photo, K, T_c2w), with the
    ``known_lights`` (corners, radiance), closed by a box of cells of about ``cell`` metres aligned with ``up``."""
    from pipeline.camera import Camera
    from pipeline.trace.intersect import EmbreeIntersector

    V = np.asarray(vertices, np.float64).reshape(-1, 3)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    nv, nt = len(V), len(F)
    cameras = [Camera(K=np.asarray(Kc, np.float64), T_c2w=np.asarray(T, np.float64), width=np.shape(ph)[1],
                      height=np.shape(ph)[0]) for ph, Kc, T in frames]
    kq = [np.asarray(c, np.float64).reshape(4, 3) for c, _ in known_lights]
    # a known light emits on the side its corners turn counter-clockwise around (as the trace samples it)
    kq_n = [unit_normal(q) for q in kq]
    upv = np.asarray(up, np.float64) / np.linalg.norm(up)
    pts_box = box_extent(V, cameras, kq, upv) if nv or cameras else np.zeros((1, 3))
    hgt = pts_box @ upv
    h_low = float(hgt.min())
    ceiling_assumed = float(hgt.max()) - h_low < ASSUMED_CEILING_M
    if ceiling_assumed:   # a scan that did not reach the ceiling: put the box's top where a ceiling would be
        pts_box = np.concatenate([pts_box, (pts_box[np.argmin(hgt)] + ASSUMED_CEILING_M * upv)[None]])
    BV, BF, bcen, bnrm = closing_box(pts_box, up, cell)
    hb = bcen @ upv
    # the box's normals are +-up or level (closing_box builds it on the up frame)
    floor_cell = ((bnrm @ upv) > 0.5) | (hb < h_low + LOW_FILL_M)
    ceiling_cell = (bnrm @ upv) < -0.5
    KV = np.concatenate(kq) if kq else np.zeros((0, 3))
    KF = np.array([[4 * i, 4 * i + 1, 4 * i + 2] for i in range(len(kq))] +
                  [[4 * i, 4 * i + 2, 4 * i + 3] for i in range(len(kq))], np.int64).reshape(-1, 3)
    k_rad = np.asarray([r for _, r in known_lights], np.float64).reshape(-1, 3)
    AV = np.concatenate([V, BV, KV]).astype(np.float32)
    AF = np.concatenate([F, BF + nv, KF + nv + len(BV)]).astype(np.int32)
    isect = EmbreeIntersector(AV, AF)
    eps = 1e-3 * max(float(np.ptp(AV, axis=0).max()), 1e-3)
    p_ = AV[AF].astype(np.float64)
    tn = np.cross(p_[:, 1] - p_[:, 0], p_[:, 2] - p_[:, 0])
    tarea = 0.5 * np.linalg.norm(tn, axis=1)
    tn /= np.maximum(2 * tarea, 1e-30)[:, None]
    return Room(V=V, F=F, cameras=cameras, known_quads=kq, known_normals=kq_n, known_radiance=k_rad, up=upv,
                h_low=h_low, ceiling_assumed=ceiling_assumed, box_v=BV, box_f=BF, box_centre=bcen, box_normal=bnrm,
                floor_cell=floor_cell, ceiling_cell=ceiling_cell, all_v=AV, all_f=AF, isect=isect, eps=eps,
                corners=p_, tri_normal=tn, tri_area=tarea)


def facing_away(room: Room, name: str) -> list[int]:
    """The known lights that turn their back on every camera, said in one warning: a known light emits on one
    side only (as the trace stage samples it), and one facing away from every photo is most likely wound the
    wrong way round. Said, not changed."""
    cams = room.cams
    backwards = [k for k, (q, qn_) in enumerate(zip(room.known_quads, room.known_normals)) if cams and all(
        float(qn_ @ (c - q.mean(axis=0))) < 0 for c in cams)]
    if backwards:
        log.warning("light fit of %s: trace.lights_file emitter(s) %s face away from every camera (they emit on the "
                    "side their corners turn counter-clockwise around); if they should light the room, reverse "
                    "their corners' order", name, backwards)
    return backwards


def closing_box(points: np.ndarray, up: np.ndarray, cell: float, margin: float = MARGIN
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An inward-facing box around ``points`` (aligned with ``up``), cut into cells of about ``cell`` m.

    Returns
    -------
    vertices : (4C, 3) float64, four of its own per cell (so a cell's radiance is constant)
    faces : (2C, 3) int64, two triangles per cell, wound so their normal points into the box
    centres : (C, 3) float64 cell centres
    normals : (C, 3) float64 inward unit normals
    """
    e1, e2, u = up_frame(up)
    B = np.stack([e1, e2, u])                     # rows: box axes in world
    c = np.asarray(points, np.float64) @ B.T
    lo, hi = c.min(axis=0) - margin, c.max(axis=0) + margin
    verts, faces, cen, nrm = [], [], [], []
    for axis in range(3):
        a1, a2 = [k for k in range(3) if k != axis]
        for side, val in ((+1, lo[axis]), (-1, hi[axis])):   # inward normal: + at lo, - at hi
            n1 = max(1, int(np.ceil((hi[a1] - lo[a1]) / cell)))
            n2 = max(1, int(np.ceil((hi[a2] - lo[a2]) / cell)))
            g1 = np.linspace(lo[a1], hi[a1], n1 + 1)
            g2 = np.linspace(lo[a2], hi[a2], n2 + 1)
            for i in range(n1):
                for j in range(n2):
                    q = np.zeros((4, 3))
                    q[:, axis] = val
                    q[:, a1] = [g1[i], g1[i + 1], g1[i + 1], g1[i]]
                    q[:, a2] = [g2[j], g2[j], g2[j + 1], g2[j + 1]]
                    base = 4 * len(cen)
                    nn = np.zeros(3)
                    nn[axis] = side
                    f = np.array([[base, base + 1, base + 2], [base, base + 2, base + 3]])
                    tn = np.cross(q[1] - q[0], q[2] - q[0])
                    if tn @ nn < 0:
                        f = f[:, ::-1]
                    verts.append(q)
                    faces.append(f)
                    cen.append(q.mean(axis=0))
                    nrm.append(nn)
    V = np.concatenate(verts) @ B                  # back to world
    return V, np.concatenate(faces), np.asarray(cen) @ B, np.asarray(nrm) @ B


def box_extent(vertices: np.ndarray, cameras, known_quads, up: np.ndarray) -> np.ndarray:
    """The points the closing box must enclose: the mesh, the cameras, the known lights' corners, and a
    point :data:`BEHIND_CAMERA_M` behind each camera (against its optical axis, projected level).

    Whoever held a camera stood in front of the wall behind it, which no photo saw: a box closing the room
    at the cameras themselves would stand nearer the lamps than any real wall there, and light the objects
    with light the room does not have. A scanned wall farther away still sets the box (it encloses the mesh).

    ``up`` is a unit vector; a camera looking straight up or down adds no point behind it.
    """
    pts = [np.asarray(vertices, np.float64).reshape(-1, 3)]
    for cam in cameras:
        axis = cam.T_c2w[:3, 2]
        level = axis - (axis @ up) * up
        n = float(np.linalg.norm(level))
        pts.append(cam.center[None])
        if n > 1e-6:
            pts.append((cam.center - BEHIND_CAMERA_M * level / n)[None])
    return np.concatenate(pts + [np.asarray(q, np.float64).reshape(-1, 3) for q in known_quads])


def behind_the_mesh(isect, cells: np.ndarray, cams: list, eps: float, grid: int = 3) -> np.ndarray:
    """(C,) bool: the closing box's cells ``cells (C, 4, 3)`` (corners in order) the room's mesh hides from
    every camera centre ``cams``: from each of ``grid`` x ``grid`` points spread over the cell, the segment
    to every camera meets the mesh (``isect`` holds it with the box, which the segments do not cross). A
    cell seen in part, through a hole or past a wall's end, is not hidden. False for all without cameras."""
    cells = np.asarray(cells, np.float64).reshape(-1, 4, 3)
    t = (np.arange(grid) + 0.5) / grid
    a, b = (x.ravel() for x in np.meshgrid(t, t))
    o, u, v = cells[:, 0], cells[:, 1] - cells[:, 0], cells[:, 3] - cells[:, 0]
    pts = (o[:, None] + a[None, :, None] * u[:, None] + b[None, :, None] * v[:, None]).reshape(-1, 3)
    hidden = np.full(len(pts), bool(cams))
    for c in cams:
        if not hidden.any():
            break
        idx = np.flatnonzero(hidden)
        d = np.asarray(c, np.float64)[None] - pts[idx]
        dist = np.linalg.norm(d, axis=1)
        d /= np.maximum(dist, 1e-12)[:, None]
        hidden[idx] = isect.occluded(pts[idx] + eps * d, d, np.maximum(dist - 2 * eps, 0))
    return hidden.reshape(len(cells), grid * grid).all(axis=1)


def unseen_side(prim: np.ndarray, d: np.ndarray, tn: np.ndarray, nt: int, seen_side: int) -> np.ndarray:
    """(R,) bool: the rays of directions ``d`` met mesh triangle ``prim`` (one of the first ``nt``; normals
    ``tn``) on the side no camera saw (``seen_side``: +1 the cameras see the front, -1 the back, 0 both)."""
    out = np.zeros(prim.shape, bool)
    if seen_side == 0:
        return out
    m = np.flatnonzero(prim < nt)
    out[m] = seen_side * np.sum(d[m] * tn[prim[m]], axis=1) > 0
    return out


def nearest_facing(P: np.ndarray, N: np.ndarray, Q: np.ndarray, QN: np.ndarray, reach: float, k: int = 8,
                   either_way: bool = False) -> np.ndarray:
    """(len(Q),) index of the nearest of each query ``Q``'s ``k`` nearest points ``P`` within ``reach``
    metres whose normal ``N`` is within 60 degrees of the query's ``QN`` (``either_way``: of it or its
    opposite), -1 where none is."""
    from scipy.spatial import cKDTree

    out = np.full(len(Q), -1, np.int64)
    if len(Q) == 0 or len(P) == 0:
        return out
    k = min(k, len(P))
    dist, nb = cKDTree(P).query(Q, k=k, distance_upper_bound=reach)
    dist, nb = dist.reshape(len(Q), k), np.minimum(nb.reshape(len(Q), k), len(P) - 1)
    cos = np.einsum("qkj,qj->qk", N[nb], QN)
    ok = np.isfinite(dist) & ((np.abs(cos) if either_way else cos) > 0.5)
    first = np.argmax(ok, axis=1)                                  # the nearest that qualifies
    has = ok[np.arange(len(Q)), first]
    out[has] = nb[has, first[has]]
    return out


def sheet_backs(P: np.ndarray, N: np.ndarray, patch: np.ndarray, npatch: int, owner: np.ndarray,
                hit_pos: np.ndarray, seen_normal: np.ndarray, reach: float, weight: float, near: int = 8):
    """(len(P), npatch + 1) sparse: the irradiance each point ``P`` (normals ``N``) receives from the unseen
    sides of sheets, per unit albedo of each patch (the last column: per unit of the room's level) and unit
    radiance of what those sides face. ``owner (R,)`` / ``hit_pos (R, 3)`` / ``seen_normal (R, 3)``: the
    gather rays that met an unseen side (the point they left, where they met it, the normal of the side the
    cameras saw there), each worth ``weight`` (pi / rays per point). A hit takes the patch of the nearest of
    its ``near`` nearest points within ``reach`` metres that faces the way the seen side does (the sheet's
    photographed top, not the wall beside it: a scan's table top is one sheet), the level where none does.

    Why: the underside of a table top is lit by the floor below and reflects it with the table's albedo; with
    nothing there the floor under a table is short of known light, and the fit explains its shadow with a
    higher albedo and too little light."""
    import scipy.sparse

    n = len(P)
    if owner.size == 0 or n == 0:
        return scipy.sparse.csr_matrix((n, npatch + 1))
    idx = nearest_facing(P, N, hit_pos, seen_normal, reach, near)
    col = np.where(idx >= 0, patch[idx], npatch)
    return scipy.sparse.csr_matrix((np.full(owner.size, float(weight)), (owner, col)), shape=(n, npatch + 1))


def unit_normal(quad: np.ndarray) -> np.ndarray:
    """(3,) unit normal of rectangle ``quad (4, 3)``: the side its corners turn counter-clockwise around."""
    q = np.asarray(quad, np.float64)
    n = np.cross(q[1] - q[0], q[2] - q[0])
    return n / max(float(np.linalg.norm(n)), 1e-30)


def near_quads(points: np.ndarray, quads: np.ndarray, reach: float) -> np.ndarray:
    """(n,) bool: ``points (n, 3)`` within ``reach`` metres of any parallelogram ``quads (C, 4, 3)`` (corners in
    order)."""
    P = np.asarray(points, np.float64).reshape(-1, 3)
    near = np.zeros(len(P), bool)
    for q in np.asarray(quads, np.float64).reshape(-1, 4, 3):
        a, b = q[1] - q[0], q[3] - q[0]
        d = P - q[0]
        u = np.clip(d @ a / max(float(a @ a), 1e-30), 0.0, 1.0)
        v = np.clip(d @ b / max(float(b @ b), 1e-30), 0.0, 1.0)
        near |= np.linalg.norm(d - u[:, None] * a - v[:, None] * b, axis=1) <= reach
    return near


def quad_area(quads: np.ndarray) -> np.ndarray:
    """(C,) areas of parallelograms ``quads (C, 4, 3)`` (corners in order)."""
    q = np.asarray(quads, np.float64).reshape(-1, 4, 3)
    return np.linalg.norm(np.cross(q[:, 1] - q[:, 0], q[:, 3] - q[:, 0]), axis=1)


def read_lights_file(file: str, radiance_scale: float = 1.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """The emitters of ``trace.lights_file``: ``[(corners (4, 3), radiance (3,) x radiance_scale)]``.

    Raises InputError naming the file and the entry for anything that is not a list of
    ``{"corners": 4 x 3 numbers, "radiance": 3 numbers >= 0}`` with a non-degenerate rectangle.
    """
    import json
    from pathlib import Path

    from pipeline.errors import InputError

    p = Path(file)
    try:
        doc = json.loads(p.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{p}: cannot read trace.lights_file ({e}); give a JSON list of "
                         f"{{\"corners\": [[x, y, z] x 4], \"radiance\": [r, g, b]}}") from None
    if not isinstance(doc, list):
        raise InputError(f"{p}: trace.lights_file must be a JSON list of emitters, got {type(doc).__name__}")
    out = []
    for k, e in enumerate(doc):
        try:
            c = np.asarray(e["corners"], np.float64)
            r = np.asarray(e["radiance"], np.float64)
        except (TypeError, KeyError, ValueError):
            raise InputError(f"{p}: emitter {k} needs \"corners\" (4 x [x, y, z] metres) and \"radiance\" "
                             f"([r, g, b])") from None
        if c.shape != (4, 3) or r.shape != (3,) or not (np.all(np.isfinite(c)) and np.all(np.isfinite(r))):
            raise InputError(f"{p}: emitter {k}: corners {c.shape} / radiance {r.shape} must be 4 x 3 and 3 "
                             f"finite numbers")
        if np.any(r < 0) or quad_area(c)[0] < 1e-8:
            raise InputError(f"{p}: emitter {k}: radiance {r.tolist()} must be >= 0 and the rectangle must "
                             f"have an area")
        out.append((c, r * radiance_scale))
    return out
