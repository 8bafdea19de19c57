"""Procedural room: geometry, materials and lights, in a canonical frame (metres, z up, floor at z = 0).

The room is a list of rectangles ("quads", each with an origin and two edge vectors whose cross product
is the outward normal). Meshes are made from the quads at any tessellation: the true mesh (for
rendering and ground truth) and the finer "scanner" mesh share the same rectangles, so they describe the
same surfaces. Furniture covers the hard cases of real scans: a table and a chair with thin legs, a shelf
with one thin board, a box on the floor, an open doorway, ceiling area lights and a bright window.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.synthscan.textures import make_texture


@dataclass(frozen=True)
class Material:
    """A diffuse material with a procedural base-colour texture."""

    id: int                   # index into Room.materials
    name: str
    kind: str                 # texture kind: "tiles" | "wood" | "paint" | "cardboard" | "fabric" | "plain"
    base_color: tuple[float, float, float]  # linear RGB mean albedo
    metres_per_repeat: float  # the texture repeats every this many metres along u and v
    roughness: float          # [0, 1] perceptual roughness (recorded for the path tracer; the raster is Lambert)
    emitter: bool             # True for light-emitting surfaces (lamps, window)


@dataclass(frozen=True)
class Light:
    """A one-sided Lambertian rectangular emitter (ceiling panel or window)."""

    name: str
    kind: str                 # "area" (ceiling panel) | "window"
    corners: np.ndarray       # (4, 3) float64, metres, in order around the rectangle (corners[1] - corners[0] and
                              # corners[3] - corners[0] are its edges)
    normal: np.ndarray        # (3,) float64, unit, emitting direction
    radiance: np.ndarray      # (3,) float64, linear RGB radiance, W / (m^2 sr) (relative units)

    @property
    def area(self) -> float:
        """Area in m^2."""
        e1 = self.corners[1] - self.corners[0]
        e2 = self.corners[3] - self.corners[0]
        return float(np.linalg.norm(np.cross(e1, e2)))

    @property
    def power(self) -> np.ndarray:
        """(3,) radiant flux pi * L * A (W, relative units) of a Lambertian emitter."""
        return math.pi * self.radiance * self.area


@dataclass(frozen=True)
class Part:
    """A named piece of geometry (a wall, a table leg); its quads are ``quads[quad_start:quad_stop]``."""

    name: str
    material_id: int
    thin: bool                # thinner than ~4 cm: scanners tend to lose it
    thickness: float          # metres, smallest dimension
    quad_start: int
    quad_stop: int


@dataclass(frozen=True)
class Room:
    """The room in the canonical frame (z up, floor z = 0)."""

    size: np.ndarray          # (3,) float64, interior extent (x, y, z), metres
    quad_origin: np.ndarray   # (Q, 3) float64
    quad_a: np.ndarray        # (Q, 3) float64, first edge (texture u)
    quad_b: np.ndarray        # (Q, 3) float64, second edge (texture v); a x b points outwards
    quad_material: np.ndarray  # (Q,) int32
    quad_part: np.ndarray     # (Q,) int32, index into parts
    parts: tuple[Part, ...]
    materials: tuple[Material, ...]
    textures: tuple[np.ndarray, ...]  # per material, (N, N, 3) uint8 sRGB
    lights: tuple[Light, ...]
    ambient: float            # uniform ambient radiance standing in for inter-reflections (relative units)
    door: np.ndarray          # (4,) float64: x0, x1, height of the doorway in wall y = 0, wall thickness
    walkable: np.ndarray      # (4,) float64: x_min, x_max, y_min, y_max a camera may walk in


@dataclass(frozen=True)
class MeshData:
    """A triangle mesh made from the room's quads."""

    vertices: np.ndarray      # (V, 3) float64, metres
    normals: np.ndarray       # (V, 3) float32, unit (flat per quad)
    uv: np.ndarray            # (V, 2) float32, texture coordinates (repeat, OpenGL v up)
    faces: np.ndarray         # (T, 3) int32, counter-clockwise seen from outside
    face_quad: np.ndarray     # (T,) int32, source quad
    vertex_quad: np.ndarray   # (V,) int32, source quad
    quad_vertex_start: np.ndarray  # (Q,) int64, first vertex of each quad's (na+1) x (nb+1) grid (-1: absent)
    quad_cells: np.ndarray    # (Q, 2) int64, grid cells (na, nb) of each quad (0: absent)


class _Builder:
    def __init__(self) -> None:
        self.o: list[np.ndarray] = []
        self.a: list[np.ndarray] = []
        self.b: list[np.ndarray] = []
        self.m: list[int] = []
        self.p: list[int] = []
        self.parts: list[Part] = []

    def quad(self, o, a, b, mat: int) -> None:
        self.o.append(np.asarray(o, float))
        self.a.append(np.asarray(a, float))
        self.b.append(np.asarray(b, float))
        self.m.append(mat)
        self.p.append(len(self.parts))

    def part(self, name: str, mat: int, quads: list[tuple], thin: bool = False, thickness: float = 0.0) -> None:
        start = len(self.o)
        for o, a, b in quads:
            self.quad(o, a, b, mat)
        self.parts.append(Part(name, mat, thin, float(thickness), start, len(self.o)))

    def box(self, name: str, mat: int, centre, size, yaw: float = 0.0, thin_below: float = 0.04) -> None:
        """Axis-aligned box (rotated by ``yaw`` about z around its centre), outward-facing quads."""
        c = np.asarray(centre, float)
        sx, sy, sz = (float(s) for s in size)
        cy, sy_ = math.cos(yaw), math.sin(yaw)
        R = np.array([[cy, -sy_, 0], [sy_, cy, 0], [0, 0, 1.0]])
        ex, ey, ez = R[:, 0] * sx, R[:, 1] * sy, R[:, 2] * sz
        lo = c - 0.5 * (ex + ey + ez)
        quads = [
            (lo, ey, ex),                     # bottom (-z)
            (lo + ez, ex, ey),                # top (+z)
            (lo, ex, ez),                     # -y side
            (lo + ey, ez, ex),                # +y side
            (lo, ez, ey),                     # -x side
            (lo + ex, ey, ez),                # +x side
        ]
        thickness = min(sx, sy, sz)
        self.part(name, mat, quads, thin=thickness < thin_below, thickness=thickness)


def _materials(rng: np.random.Generator) -> tuple[Material, ...]:
    def jitter(c, s=0.08):
        return tuple(float(np.clip(v * (1 + s * (rng.random() - 0.5) * 2), 0.02, 0.95)) for v in c)

    wall_col = [(0.62, 0.60, 0.55), (0.55, 0.60, 0.62), (0.65, 0.58, 0.48), (0.50, 0.58, 0.50)][int(rng.integers(4))]
    spec = [
        ("floor_tiles", "tiles", jitter((0.50, 0.47, 0.42)), 0.6, 0.6),
        ("wall_paint", "paint", jitter(wall_col), 1.0, 0.9),
        ("ceiling_paint", "paint", (0.80, 0.80, 0.78), 1.0, 0.9),
        ("table_wood", "wood", jitter((0.40, 0.22, 0.10)), 0.8, 0.5),
        ("chair_wood", "wood", jitter((0.30, 0.16, 0.08)), 0.5, 0.5),
        ("shelf_wood", "wood", jitter((0.55, 0.40, 0.25)), 0.6, 0.5),
        ("box_cardboard", "cardboard", jitter((0.45, 0.30, 0.15)), 0.4, 0.8),
        ("chair_fabric", "fabric", jitter((0.12, 0.20, 0.35)), 0.3, 0.9),
        ("corridor_paint", "paint", (0.45, 0.45, 0.45), 1.0, 0.9),
        ("lamp", "plain", (1.0, 1.0, 1.0), 1.0, 1.0),
        ("window", "plain", (1.0, 1.0, 1.0), 1.0, 1.0),
    ]
    return tuple(Material(i, n, k, c, r, rough, n in ("lamp", "window")) for i, (n, k, c, r, rough) in enumerate(spec))


def make_room(rng: np.random.Generator, *, window: bool = True, texture_size: int = 256) -> Room:
    """Build the procedural room; every dimension and colour is drawn from ``rng``.

    The steps draw from ``rng`` in this order (the order fixes the room of a seed): materials and
    textures, the size, :func:`_add_shell`, :func:`_add_table`, :func:`_add_chair`, :func:`_add_shelf`,
    :func:`_add_floor_box`, :func:`_add_lights`.

    Parameters
    ----------
    rng : numpy Generator (from :func:`pipeline.seeding.item_rng`)
    window : bool
        Add a bright window on the wall x = size_x.
    texture_size : int
        Texture resolution in pixels (square).
    """
    mats = _materials(rng)
    M = {m.name: m.id for m in mats}
    textures = tuple(make_texture(m.kind, rng, m.base_color, texture_size) for m in mats)

    X = float(rng.uniform(3.8, 4.4))
    Y = float(rng.uniform(3.2, 3.6))
    Z = float(rng.uniform(2.4, 2.6))
    b = _Builder()
    door = _add_shell(b, M, rng, X, Y, Z)
    table = _add_table(b, M, rng, X, Y)
    _add_chair(b, M, rng, table)
    _add_shelf(b, M, rng, X, Y)
    _add_floor_box(b, M, rng, X)
    lights = _add_lights(b, M, rng, X, Y, Z, window)

    margin = 0.6
    return Room(
        size=np.array([X, Y, Z]),
        quad_origin=np.array(b.o), quad_a=np.array(b.a), quad_b=np.array(b.b),
        quad_material=np.array(b.m, np.int32), quad_part=np.array(b.p, np.int32),
        parts=tuple(b.parts), materials=mats, textures=textures, lights=tuple(lights),
        ambient=0.25, door=door,
        walkable=np.array([margin, X - margin, margin, Y - margin]),
    )


def _add_shell(b: _Builder, M: dict[str, int], rng: np.random.Generator, X: float, Y: float, Z: float
               ) -> np.ndarray:
    """Add the room shell (inward-facing, a doorway in wall y = 0) and the corridor behind the doorway to
    ``b``. Returns the door ``(x0, x1, height, wall thickness)``, metres."""
    ex, ey, ez = np.eye(3)
    # Room shell, inward-facing. Doorway in wall y = 0.
    t = 0.10                                   # wall thickness at the doorway, metres
    dx0 = float(rng.uniform(0.5, 0.9))
    dx1 = dx0 + 0.9
    dh = 2.05
    b.part("floor", M["floor_tiles"], [((0, 0, 0), X * ex, Y * ey)], thickness=0.1)
    b.part("ceiling", M["ceiling_paint"], [((0, 0, Z), Y * ey, X * ex)], thickness=0.1)
    b.part("wall_y0", M["wall_paint"], [
        ((0, 0, 0), Z * ez, dx0 * ex),
        ((dx1, 0, 0), Z * ez, (X - dx1) * ex),
        ((dx0, 0, dh), (Z - dh) * ez, (dx1 - dx0) * ex),
    ], thickness=t)
    b.part("wall_y1", M["wall_paint"], [((0, Y, 0), X * ex, Z * ez)], thickness=0.1)
    b.part("wall_x0", M["wall_paint"], [((0, 0, 0), Y * ey, Z * ez)], thickness=0.1)
    b.part("wall_x1", M["wall_paint"], [((X, 0, 0), Z * ez, Y * ey)], thickness=0.1)
    # Doorway reveal (jambs and lintel), facing into the opening.
    b.part("doorway", M["wall_paint"], [
        ((dx0, -t, 0), t * ey, dh * ez),          # jamb at x = dx0, normal +x
        ((dx1, -t, 0), dh * ez, t * ey),          # jamb at x = dx1, normal -x
        ((dx0, -t, dh), t * ey, (dx1 - dx0) * ex),  # lintel underside, normal -z
        ((dx0, -t, 0), (dx1 - dx0) * ex, t * ey),   # threshold floor, normal +z
    ], thickness=t)
    # Corridor behind the doorway (dim, lit only by ambient light).
    cx0, cx1, cy0, cy1 = dx0 - 0.6, dx1 + 0.6, -t - 1.2, -t
    b.part("corridor", M["corridor_paint"], [
        ((cx0, cy0, 0), (cx1 - cx0) * ex, (cy1 - cy0) * ey),            # floor
        ((cx0, cy0, dh + 0.3), (cy1 - cy0) * ey, (cx1 - cx0) * ex),     # ceiling
        ((cx0, cy0, 0), (dh + 0.3) * ez, (cx1 - cx0) * ex),             # far wall y = cy0, normal +y
        ((cx0, cy0, 0), (cy1 - cy0) * ey, (dh + 0.3) * ez),             # x = cx0, normal +x
        ((cx1, cy0, 0), (dh + 0.3) * ez, (cy1 - cy0) * ey),             # x = cx1, normal -x
        ((cx0, cy1, 0), (dx0 - cx0) * ex, (dh + 0.3) * ez),             # room-side wall, left of door
        ((dx1, cy1, 0), (cx1 - dx1) * ex, (dh + 0.3) * ez),             # right of door
        ((dx0, cy1, dh), (dx1 - dx0) * ex, 0.3 * ez),                   # above door
    ], thickness=0.1)
    return np.array([dx0, dx1, dh, t])


@dataclass(frozen=True)
class _Table:
    """Where :func:`_add_table` put the table (the chair stands beside it)."""

    x: float            # m, centre
    y: float
    yaw: float          # rad about z
    depth: float        # m
    Rz: np.ndarray      # (2, 2) float64, rotation by yaw


def _add_table(b: _Builder, M: dict[str, int], rng: np.random.Generator, X: float, Y: float) -> _Table:
    """Add a table with thin legs near the middle of the room to ``b``."""
    tx, ty = X * float(rng.uniform(0.45, 0.6)), Y * float(rng.uniform(0.45, 0.6))
    tyaw = float(rng.uniform(-0.3, 0.3))
    tw, td, th = 1.2, 0.7, 0.74
    Rz = np.array([[math.cos(tyaw), -math.sin(tyaw)], [math.sin(tyaw), math.cos(tyaw)]])
    b.box("table_top", M["table_wood"], (tx, ty, th - 0.02), (tw, td, 0.04), tyaw)
    leg = 0.035
    for i, (sx, sy) in enumerate([(-1, -1), (1, -1), (1, 1), (-1, 1)]):
        off = Rz @ np.array([sx * (tw / 2 - 0.06), sy * (td / 2 - 0.06)])
        b.box(f"table_leg_{i}", M["table_wood"], (tx + off[0], ty + off[1], (th - 0.04) / 2), (leg, leg, th - 0.04), tyaw)
    return _Table(tx, ty, tyaw, td, Rz)


def _add_chair(b: _Builder, M: dict[str, int], rng: np.random.Generator, table: _Table) -> None:
    """Add a chair with thin legs beside ``table`` to ``b``."""
    tx, ty, tyaw, td, Rz = table.x, table.y, table.yaw, table.depth, table.Rz
    cyaw = tyaw + float(rng.uniform(-0.4, 0.4))
    side = 1 if rng.random() < 0.5 else -1
    coff = Rz @ np.array([0.0, side * (td / 2 + 0.35)])
    chx, chy = tx + coff[0], ty + coff[1]
    Rc = np.array([[math.cos(cyaw), -math.sin(cyaw)], [math.sin(cyaw), math.cos(cyaw)]])
    sh, sw = 0.45, 0.42
    b.box("chair_seat", M["chair_fabric"], (chx, chy, sh - 0.015), (sw, sw, 0.03), cyaw)
    cl = 0.025
    for i, (sx, sy) in enumerate([(-1, -1), (1, -1), (1, 1), (-1, 1)]):
        off = Rc @ np.array([sx * (sw / 2 - 0.03), sy * (sw / 2 - 0.03)])
        b.box(f"chair_leg_{i}", M["chair_wood"], (chx + off[0], chy + off[1], (sh - 0.03) / 2), (cl, cl, sh - 0.03), cyaw)
    for i, sx in enumerate((-1, 1)):
        off = Rc @ np.array([sx * (sw / 2 - 0.03), side * (sw / 2 - 0.0125)])
        b.box(f"chair_post_{i}", M["chair_wood"], (chx + off[0], chy + off[1], sh + 0.22), (cl, cl, 0.44), cyaw)
    off = Rc @ np.array([0.0, side * (sw / 2 - 0.0125)])
    b.box("chair_back", M["chair_wood"], (chx + off[0], chy + off[1], sh + 0.34), (sw - 0.06, 0.018, 0.16), cyaw)


def _add_shelf(b: _Builder, M: dict[str, int], rng: np.random.Generator, X: float, Y: float) -> None:
    """Add a shelf against wall y = Y to ``b``: two sides and four boards, one of them thin."""
    shw, shd, shh = 0.8, 0.3, 1.6
    sx0 = X * float(rng.uniform(0.15, 0.55))
    scy = Y - shd / 2 - 0.01
    b.box("shelf_side_0", M["shelf_wood"], (sx0 + 0.01, scy, shh / 2), (0.02, shd, shh))
    b.box("shelf_side_1", M["shelf_wood"], (sx0 + shw - 0.01, scy, shh / 2), (0.02, shd, shh))
    thin_board = int(rng.integers(1, 3))
    for k, z in enumerate((0.05, 0.55, 1.05, shh - 0.01)):
        thick = 0.008 if k == thin_board else 0.02
        b.box(f"shelf_board_{k}", M["shelf_wood"], (sx0 + shw / 2, scy, z), (shw - 0.04, shd - 0.01, thick))


def _add_floor_box(b: _Builder, M: dict[str, int], rng: np.random.Generator, X: float) -> None:
    """Add a cardboard box on the floor to ``b``, in a corner region away from the door."""
    bw, bd, bh = float(rng.uniform(0.35, 0.5)), float(rng.uniform(0.25, 0.35)), float(rng.uniform(0.25, 0.35))
    bx = X - 0.5 - float(rng.uniform(0.0, 0.3))
    by = 0.5 + float(rng.uniform(0.0, 0.4))
    b.box("box", M["box_cardboard"], (bx, by, bh / 2), (bw, bd, bh), float(rng.uniform(-0.6, 0.6)))


def _add_lights(b: _Builder, M: dict[str, int], rng: np.random.Generator, X: float, Y: float, Z: float,
                window: bool) -> list[Light]:
    """Add the lights to ``b``: two ceiling panels (emitting down) and, with ``window``, a window on wall
    x = X (emitting -x). Returns them as :class:`Light`."""
    lights: list[Light] = []
    n_lamps = 2
    L_lamp = float(rng.uniform(9.0, 12.0))
    for k in range(n_lamps):
        lx = X * (k + 1) / (n_lamps + 1)
        ly = Y * float(rng.uniform(0.4, 0.6))
        hs = 0.3
        z = Z - 0.005
        corners = np.array([[lx - hs, ly - hs, z], [lx - hs, ly + hs, z], [lx + hs, ly + hs, z], [lx + hs, ly - hs, z]])
        b.part(f"lamp_{k}", M["lamp"], [(corners[0], corners[1] - corners[0], corners[3] - corners[0])], thickness=0.0)
        lights.append(Light(f"lamp_{k}", "area", corners, np.array([0.0, 0.0, -1.0]),
                            np.array([1.0, 0.95, 0.85]) * L_lamp))
    if window:
        wy0 = Y * float(rng.uniform(0.25, 0.4))
        wy1 = wy0 + 1.1
        wz0, wz1 = 0.9, 2.1
        xw = X - 0.003
        corners = np.array([[xw, wy0, wz0], [xw, wy0, wz1], [xw, wy1, wz1], [xw, wy1, wz0]])
        b.part("window", M["window"], [(corners[0], corners[1] - corners[0], corners[3] - corners[0])], thickness=0.0)
        lights.append(Light("window", "window", corners, np.array([-1.0, 0.0, 0.0]),
                            np.array([0.85, 0.92, 1.0]) * float(rng.uniform(14.0, 20.0))))
    return lights


def tessellate(room: Room, cell: float, quads: np.ndarray | None = None) -> MeshData:
    """Mesh of the room's quads, each split into a grid of cells of at most ``cell`` metres.

    Vertices are not shared between quads (flat normals, sharp edges). UVs are metric, divided by the
    material's ``metres_per_repeat``.

    Parameters
    ----------
    room : Room
    cell : float, metres, > 0
    quads : (Q',) int, optional subset of quad indices (default: all)
    """
    idx = np.arange(len(room.quad_origin)) if quads is None else np.asarray(quads)
    verts, norms, uvs, faces, fq, vq = [], [], [], [], [], []
    base = 0
    q_start = np.full(len(room.quad_origin), -1, np.int64)
    q_cells = np.zeros((len(room.quad_origin), 2), np.int64)
    mpr = np.array([m.metres_per_repeat for m in room.materials])
    for q in idx:
        o, a, b = room.quad_origin[q], room.quad_a[q], room.quad_b[q]
        la, lb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
        na, nb = max(1, math.ceil(la / cell - 1e-9)), max(1, math.ceil(lb / cell - 1e-9))
        s = np.linspace(0.0, 1.0, na + 1)
        t = np.linspace(0.0, 1.0, nb + 1)
        S, T = np.meshgrid(s, t, indexing="ij")
        P = o + S.reshape(-1, 1) * a + T.reshape(-1, 1) * b
        n = np.cross(a, b)
        n = n / np.linalg.norm(n)
        r = mpr[room.quad_material[q]]
        # Metric UVs anchored at world coordinates so abutting quads line up.
        ua, ub = a / la, b / lb
        uv = np.stack([(P @ ua), (P @ ub)], axis=1) / r
        ii, jj = np.meshgrid(np.arange(na), np.arange(nb), indexing="ij")
        v00 = (ii * (nb + 1) + jj).reshape(-1)
        v10, v01, v11 = v00 + (nb + 1), v00 + 1, v00 + nb + 2
        f = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)], 0) + base
        q_start[q] = base
        q_cells[q] = (na, nb)
        verts.append(P)
        norms.append(np.broadcast_to(n, P.shape))
        uvs.append(uv)
        faces.append(f)
        fq.append(np.full(len(f), q, np.int32))
        vq.append(np.full(len(P), q, np.int32))
        base += len(P)
    return MeshData(
        vertices=np.concatenate(verts).astype(np.float64),
        normals=np.concatenate(norms).astype(np.float32),
        uv=np.concatenate(uvs).astype(np.float32),
        faces=np.concatenate(faces).astype(np.int32),
        face_quad=np.concatenate(fq),
        vertex_quad=np.concatenate(vq),
        quad_vertex_start=q_start,
        quad_cells=q_cells,
    )


def interpolate_on_quads(room: Room, mesh: MeshData, values: np.ndarray, points: np.ndarray,
                         point_quad: np.ndarray) -> np.ndarray:
    """Bilinearly interpolate per-vertex ``values`` of ``mesh`` at ``points`` lying on known quads.

    Parameters
    ----------
    room : Room
    mesh : MeshData made by :func:`tessellate` (every quad in ``point_quad`` must be in it)
    values : (V, C) per-vertex values of ``mesh``
    points : (N, 3) float, metres, on the quads
    point_quad : (N,) int, the quad of each point

    Returns
    -------
    (N, C) values.dtype-compatible float array
    """
    o, a, b = room.quad_origin[point_quad], room.quad_a[point_quad], room.quad_b[point_quad]
    d = points - o
    s = np.clip(np.einsum("nd,nd->n", d, a) / np.einsum("nd,nd->n", a, a), 0.0, 1.0)
    t = np.clip(np.einsum("nd,nd->n", d, b) / np.einsum("nd,nd->n", b, b), 0.0, 1.0)
    na, nb = mesh.quad_cells[point_quad, 0], mesh.quad_cells[point_quad, 1]
    x, y = s * na, t * nb
    i0 = np.minimum(np.floor(x).astype(np.int64), na - 1)
    j0 = np.minimum(np.floor(y).astype(np.int64), nb - 1)
    fx, fy = (x - i0)[:, None], (y - j0)[:, None]
    start = mesh.quad_vertex_start[point_quad]
    v00 = start + i0 * (nb + 1) + j0
    v10, v01, v11 = v00 + (nb + 1), v00 + 1, v00 + nb + 2
    return ((values[v00] * (1 - fx) + values[v10] * fx) * (1 - fy)
            + (values[v01] * (1 - fx) + values[v11] * fx) * fy)
