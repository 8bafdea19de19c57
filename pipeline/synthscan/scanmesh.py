"""The "scanner's mesh": what a scanning app would deliver for the room, not the true geometry.

Made from the same surfaces as the true mesh, then spoiled the way real scan meshes are: far more
triangles than the geometry needs (flat walls at a few centimetres), vertices welded and displaced by
surface noise, colours baked from the photos' lighting (the same light map the photos are rendered
with, sampled through the textures), holes where the scanner saw nothing (random patches, the
undersides of things standing on the floor, the window's glass), and thin parts (chair and table legs,
the thin shelf board) partly missing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.color import linear_to_srgb
from pipeline.synthscan.room import MeshData, Room, interpolate_on_quads, tessellate
from pipeline.synthscan.textures import sample_bilinear

WELD_TOL = 1e-4               # metres: vertices closer than this are one vertex
SURFACE_NOISE = 0.003         # metres, sigma of displacement along the normal
HOLES = 6                     # random holes per room
HOLE_RADIUS = (0.08, 0.25)    # metres, range of hole radii
THIN_MISSING = (0.3, 0.8)     # range of the fraction of each thin part's length that is missing


@dataclass(frozen=True)
class ScanMesh:
    """A scanner-like room mesh."""

    vertices: np.ndarray      # (V, 3) float64, metres, canonical frame
    faces: np.ndarray         # (T, 3) int32
    colors: np.ndarray        # (V, 3) uint8 sRGB, encoded like the photos
    face_part: np.ndarray     # (T,) int32, index into Room.parts
    thin_missing: dict        # thin part name -> fraction of its area removed


def _weld(points: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    key = np.round(points / tol).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return first, inverse.reshape(-1)


def make_scan_mesh(room: Room, light_mesh: MeshData, vertex_radiance: np.ndarray, rng: np.random.Generator,
                   *, cell: float = 0.04) -> ScanMesh:
    """Build the scanner's mesh of ``room``.

    Parameters
    ----------
    room : Room
    light_mesh : the tessellated true mesh that carries the light map
    vertex_radiance : (V, 3) float, exposure-scaled radiance per unit albedo at ``light_mesh`` vertices
    rng : seeded generator
    cell : float, metres, tessellation cell of the scan mesh (over-tessellation)
    """
    emitter = np.array([m.emitter for m in room.materials])
    keep_quads = np.flatnonzero(np.array([room.materials[m].name != "window" for m in room.quad_material]))
    fine = tessellate(room, cell, keep_quads)
    mat = room.quad_material[fine.vertex_quad]

    # Colours: texture albedo x the photos' light map, encoded like the photos.
    light = interpolate_on_quads(room, light_mesh, vertex_radiance, fine.vertices, fine.vertex_quad)
    albedo = np.empty((len(fine.vertices), 3), np.float32)
    for m in room.materials:
        sel = mat == m.id
        if sel.any():
            albedo[sel] = sample_bilinear(room.textures[m.id], fine.uv[sel])
    lin = albedo * light
    lin[emitter[mat]] = 1.0
    colors_f = linear_to_srgb(lin) * 255.0

    # Weld coincident vertices (edges where quads meet), averaging their colours.
    first, inv = _weld(fine.vertices, WELD_TOL)
    verts = fine.vertices[first]
    counts = np.bincount(inv, minlength=len(first)).astype(np.float64)
    cols = np.stack([np.bincount(inv, weights=colors_f[:, c], minlength=len(first)) for c in range(3)], 1)
    cols /= counts[:, None]
    faces = inv[fine.faces]
    face_quad = fine.face_quad
    ok = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    faces, face_quad = faces[ok], face_quad[ok]
    face_part = room.quad_part[face_quad]

    # Holes.
    remove = np.zeros(len(faces), bool)
    cent = verts[faces].mean(axis=1)
    quad_n = np.cross(room.quad_a, room.quad_b)
    quad_n /= np.linalg.norm(quad_n, axis=1, keepdims=True)
    fn = quad_n[face_quad]
    remove |= (fn[:, 2] < -0.9) & (cent[:, 2] < 0.01)          # undersides resting on the floor
    for _ in range(HOLES):
        c = cent[rng.integers(len(cent))]
        r = rng.uniform(*HOLE_RADIUS)
        remove |= np.linalg.norm(cent - c, axis=1) < r

    # Thin parts: a contiguous stretch along the part's longest axis is missing.
    area = 0.5 * np.linalg.norm(np.cross(verts[faces[:, 1]] - verts[faces[:, 0]],
                                         verts[faces[:, 2]] - verts[faces[:, 0]]), axis=1)
    thin_missing: dict[str, float] = {}
    for pi, part in enumerate(room.parts):
        if not part.thin:
            continue
        sel = np.flatnonzero(face_part == pi)
        if len(sel) == 0:
            continue
        pc = cent[sel]
        ext = pc.max(0) - pc.min(0)
        ax = int(np.argmax(ext))
        tt = (pc[:, ax] - pc[:, ax].min()) / max(ext[ax], 1e-9)
        frac = rng.uniform(*THIN_MISSING)
        t0 = rng.uniform(0.0, 1.0 - frac)
        gone = (tt >= t0) & (tt <= t0 + frac)
        remove[sel[gone]] = True
        thin_missing[part.name] = float(area[sel][remove[sel]].sum() / max(area[sel].sum(), 1e-12))

    faces, face_part = faces[~remove], face_part[~remove]

    # Surface noise along area-weighted vertex normals.
    fnorm = np.cross(verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]])
    vn = np.zeros_like(verts)
    for k in range(3):
        np.add.at(vn, faces[:, k], fnorm)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)
    verts = verts + vn * rng.normal(0.0, SURFACE_NOISE, (len(verts), 1))

    # Drop unreferenced vertices.
    used = np.unique(faces.reshape(-1))
    remap = np.full(len(verts), -1, np.int64)
    remap[used] = np.arange(len(used))
    return ScanMesh(
        vertices=verts[used],
        faces=remap[faces].astype(np.int32),
        colors=np.round(cols[used]).astype(np.uint8),
        face_part=face_part.astype(np.int32),
        thin_missing=thin_missing,
    )
