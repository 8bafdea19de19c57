"""Closed solids for physics: manifold3d solid, exact mass properties, convex hull and decomposition.

The solid is the union (manifold3d) of the repaired mesh's closed components, so overlapping parts
are merged instead of counted twice. The convex decomposition is only made when the hull deviates
from the shape: the mean gap between hull and shape (hull volume minus volume, over hull area: a
length) above ``CONCAVITY_TOL_REL`` x diagonal. Pieces come from recursive plane cuts (manifold3d
``split_by_plane``), each cut chosen among the three axis planes through the piece's centre as the one
whose halves' hulls are smallest, worst piece first, until every piece's gap is within tolerance or
``MAX_CONVEX_PARTS`` is reached.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from meshprep import constants
from meshprep.errors import InputError, RepairError

if TYPE_CHECKING:  # pragma: no cover
    import manifold3d

log = logging.getLogger(__name__)


def to_manifold(vertices: np.ndarray, faces: np.ndarray, *, where: str = "mesh") -> "manifold3d.Manifold":
    """A manifold3d solid from a closed, oriented triangle mesh (float64 positions).

    Each vertex-connected component is converted on its own and the components are united, so
    overlapping closed parts become one solid.

    Raises
    ------
    RepairError
        When a component is not a closed oriented 2-manifold (repair it first).
    """
    import manifold3d as m3

    from meshprep.inspect import face_components

    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    n, lab = face_components(f, len(v))
    parts = []
    for k in range(n):
        fk = f[lab == k]
        used, inv = np.unique(fk, return_inverse=True)
        mesh = m3.Mesh64(vert_properties=np.ascontiguousarray(v[used]),
                         tri_verts=np.ascontiguousarray(inv.reshape(-1, 3), dtype=np.uint64))
        man = m3.Manifold(mesh)
        if man.status() != m3.Error.NoError:
            raise RepairError(f"{where}: component {k} ({len(fk)} faces) is not a closed oriented "
                              f"2-manifold ({man.status().name}); run `meshprep repair --kind object` first")
        if man.volume() < 0:
            raise RepairError(f"{where}: component {k} encloses a negative volume (inside out); "
                              f"run `meshprep repair --kind object` first")
        parts.append(man)
    if not parts:
        raise RepairError(f"{where}: no faces; nothing to make a solid of")
    return m3.Manifold.batch_boolean(parts, m3.OpType.Add) if len(parts) > 1 else parts[0]


def manifold_arrays(man: "manifold3d.Manifold") -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V,3) float64, faces (F,3) int32) of a manifold3d solid."""
    mesh = man.to_mesh64()
    v = np.asarray(mesh.vert_properties, dtype=np.float64)[:, :3]
    f = np.asarray(mesh.tri_verts, dtype=np.int64).astype(np.int32)
    return np.ascontiguousarray(v), f.reshape(-1, 3)


def convex_hull(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Convex hull of points as a closed, outward mesh: (vertices (H,3) float64, faces (G,3) int32)."""
    import manifold3d as m3

    pts = np.ascontiguousarray(vertices, dtype=np.float64)
    c = 0.5 * (pts.min(0) + pts.max(0))
    hv, hf = manifold_arrays(m3.Manifold.hull_points(pts - c))
    return hv + c, hf


def concavity(man: "manifold3d.Manifold") -> float:
    """Mean gap between a solid and its hull: (hull volume - volume) / hull area (length units)."""
    h = man.hull()
    area = h.surface_area()
    return float(max(h.volume() - man.volume(), 0.0) / area) if area > 0 else 0.0


def convex_decomposition(man: "manifold3d.Manifold", *, tolerance: float,
                         max_parts: int = constants.MAX_CONVEX_PARTS) -> list["manifold3d.Manifold"]:
    """Pieces (manifold3d solids) whose hulls each stay within ``tolerance`` of the piece.

    Returns ``[man]`` when the solid is already within tolerance of its hull.
    """
    pieces = [(concavity(man), man)]
    while len(pieces) < max_parts:
        pieces.sort(key=lambda t: -t[0])
        worst_c, worst = pieces[0]
        if worst_c <= tolerance:
            break
        bb = np.asarray(worst.bounding_box(), dtype=np.float64).reshape(2, 3)
        centre = bb.mean(axis=0)
        best = None
        for axis in np.argsort(-(bb[1] - bb[0])):
            normal = np.zeros(3)
            normal[axis] = 1.0
            a, b = worst.split_by_plane(normal.tolist(), float(centre[axis]))
            if a.is_empty() or b.is_empty():
                continue
            cost = a.hull().volume() + b.hull().volume()
            if best is None or cost < best[0]:
                best = (cost, a, b)
        if best is None:
            pieces[0] = (0.0, worst)  # cannot be cut further; accept it
            continue
        new = [p for half in best[1:] for p in half.decompose() if not p.is_empty() and p.volume() > 0]
        pieces = pieces[1:] + [(concavity(p), p) for p in new]
    return [p for _, p in pieces]


def solid_arrays(vertices: np.ndarray, faces: np.ndarray, *, density: float = 1000.0,
                 concavity_tol_rel: float = constants.CONCAVITY_TOL_REL,
                 max_parts: int = constants.MAX_CONVEX_PARTS, where: str = "mesh") -> dict:
    """Closed solid, mass properties, hull and (when needed) convex parts of a closed mesh.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
        A closed, outward-oriented mesh (the output of ``repair(kind='object')``).
    density : float
        kg/m^3 when the mesh is in metres.
    concavity_tol_rel : float
        Decompose only when the hull's mean gap exceeds this fraction of the bounding-box diagonal.

    Returns
    -------
    dict with ``vertices``/``faces`` (the solid), ``volume``, ``mass``, ``com`` (3,), ``inertia``
    (3,3) about the com, ``hull_vertices``/``hull_faces``, ``hull_concavity`` (length),
    ``parts`` (list of (vertices, faces); empty when the hull is close enough),
    ``manifold_volume`` (manifold3d's own figure, a cross-check).
    """
    from meshprep.mass import mass_properties

    man = to_manifold(vertices, faces, where=where)
    v, f = manifold_arrays(man)
    mp = mass_properties(v, f, density=density)
    hv, hf = convex_hull(v)
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    conc = concavity(man)
    parts: list[tuple[np.ndarray, np.ndarray]] = []
    if conc > concavity_tol_rel * diag:
        pieces = convex_decomposition(man, tolerance=concavity_tol_rel * diag, max_parts=max_parts)
        parts = [manifold_arrays(p.hull()) for p in pieces]
    return {"vertices": v, "faces": f, "volume": mp.volume, "mass": mp.mass, "com": mp.com,
            "inertia": mp.inertia, "density": float(density), "hull_vertices": hv, "hull_faces": hf,
            "hull_concavity": conc, "parts": parts, "manifold_volume": float(man.volume()),
            "diagonal": diag}


def load_object_arrays(in_path: str | Path, *, scale: float = 1.0, repair_first: bool = True
                       ) -> tuple[np.ndarray, np.ndarray, dict | None]:
    """Read an object mesh, scale it, and repair it as an object in memory.

    Returns (vertices (V,3) float64, faces (F,3) int32, repair info or None).
    """
    from meshprep.io import arrays_of, load_meshset
    from meshprep.repair import check_repaired, repair_meshset

    if not (scale > 0 and np.isfinite(scale)):
        raise InputError(f"--scale {scale} must be a positive number (0.001 turns millimetres into metres)")
    ms = load_meshset(in_path)
    info = None
    if repair_first:
        info = repair_meshset(ms, kind="object")
        from meshprep.inspect import inspect_arrays

        ms.current_mesh().compact()
        check_repaired(inspect_arrays(*arrays_of(ms), self_intersections=False), "object", str(in_path))
    ms.current_mesh().compact()
    v, f = arrays_of(ms)
    return v * scale, f, info


def solid(in_path: str | Path, out_path: str | Path, *, density: float = 1000.0, scale: float = 1.0,
          report: str | Path | None = None,
          concavity_tol_rel: float = constants.CONCAVITY_TOL_REL) -> dict:
    """Make a closed manifold solid of an object mesh; write it and a JSON report of its properties.

    The input is repaired as an object first (in memory). The report holds ``volume``, ``mass``,
    ``com``, ``inertia`` (about the com), hull size and the number of convex parts needed.

    Parameters
    ----------
    density : float
        kg/m^3 (with the mesh in metres after ``scale``).
    scale : float
        Factor applied to coordinates first (0.001 for millimetre models such as BOP's).
    """
    from meshprep.io import check_writable, meshset_from_arrays, save_meshset, write_json

    t0 = time.perf_counter()
    if not (density > 0 and np.isfinite(density)):
        raise InputError(f"--density {density} must be a positive number (kg/m^3, water is 1000)")
    out_path = check_writable(out_path)
    v, f, info = load_object_arrays(in_path, scale=scale)
    s = solid_arrays(v, f, density=density, concavity_tol_rel=concavity_tol_rel, where=str(in_path))
    save_meshset(meshset_from_arrays(s["vertices"], s["faces"]), out_path)
    rep = {"command": "solid", "input": str(in_path), "output": str(out_path), "scale": scale,
           "repair": info, "faces": int(len(s["faces"])), "vertices": int(len(s["vertices"])),
           "volume": s["volume"], "manifold_volume": s["manifold_volume"], "mass": s["mass"],
           "density": density, "com": s["com"], "inertia": s["inertia"],
           "hull_faces": int(len(s["hull_faces"])), "hull_concavity": s["hull_concavity"],
           "hull_concavity_rel": s["hull_concavity"] / max(s["diagonal"], 1e-300),
           "convex_parts": len(s["parts"]), "ok": True,
           "seconds": round(time.perf_counter() - t0, 3)}
    write_json(Path(report) if report else out_path.with_name(out_path.name + ".report.json"), rep)
    return rep
