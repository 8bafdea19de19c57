"""Mesh statistics: counts, bounds, units guess, components, holes, non-manifold elements, defects.

:func:`inspect_arrays` works on plain arrays (NumPy/SciPy only, except the optional
self-intersection count, which uses PyMeshLab); :func:`inspect` reads a file.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from meshprep import constants
from meshprep.mass import signed_volume

log = logging.getLogger(__name__)


def guess_units(diagonal: float) -> str:
    """Guess the length unit from the bounding-box diagonal: 'metres', 'millimetres' or 'unknown'.

    Objects and rooms are 1 cm .. 30 m across; the same things in millimetres are 10 .. 30000.
    A diagonal in the overlap (10 .. 30) is read as metres (a room).
    """
    if not np.isfinite(diagonal) or diagonal <= 0:
        return "unknown"
    if 0.005 <= diagonal <= 30.0:
        return "metres"
    if 30.0 < diagonal <= 30000.0:
        return "millimetres"
    return "unknown"


def edge_topology(faces: np.ndarray, n_vertices: int) -> dict[str, np.ndarray]:
    """Undirected edges of a triangle mesh with their face counts.

    Parameters
    ----------
    faces : (F, 3) int
    n_vertices : int

    Returns
    -------
    dict with ``edges`` (E, 2) int64 (sorted pairs), ``counts`` (E,) int64 (faces per edge),
    ``inverse`` (3F,) int64 (edge index of each half-edge, face-major), ``same_direction`` (E,) bool
    (a two-face edge whose half-edges run the same way: inconsistent orientation), ``order`` (3F,)
    the half-edges sorted by edge.
    """
    f = np.asarray(faces, dtype=np.int64)
    nv = np.int64(max(n_vertices, 1))
    he = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    key = np.minimum(he[:, 0], he[:, 1]) * nv + np.maximum(he[:, 0], he[:, 1])
    order = np.argsort(key)
    ks = key[order]
    new = np.ones(len(ks), dtype=bool)
    new[1:] = ks[1:] != ks[:-1]
    gid = np.cumsum(new) - 1
    inverse = np.empty(len(ks), dtype=np.int64)
    inverse[order] = gid
    uniq = ks[new]
    counts = np.diff(np.append(np.flatnonzero(new), len(ks)))
    forward = (he[:, 0] < he[:, 1]).astype(np.int64)
    n_forward = np.bincount(inverse, weights=forward, minlength=len(uniq))
    same = (counts == 2) & (n_forward != 1)
    edges = np.stack([uniq // nv, uniq % nv], axis=1)
    return {"edges": edges, "counts": counts, "inverse": inverse, "same_direction": same,
            "order": order}


def count_fans(faces: np.ndarray, n_vertices: int, inverse: np.ndarray,
               order: np.ndarray | None = None) -> np.ndarray:
    """Number of edge-connected face fans around each vertex (V,) int64 (0 for unreferenced).

    A vertex is manifold when its faces form one fan; a bow-tie vertex has two or more.
    ``inverse`` is :func:`edge_topology`'s half-edge to edge map (``order``, its sort of the
    half-edges by edge, saves a sort when given).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, dtype=np.int64)
    nf = len(f)
    if nf == 0:
        return np.zeros(n_vertices, dtype=np.int64)
    corner = np.arange(3 * nf).reshape(nf, 3)
    # Half-edge k of face i runs from corner k to corner (k+1)%3.
    c0 = corner.reshape(-1)
    c1 = corner[:, [1, 2, 0]].reshape(-1)
    v0, v1 = f.reshape(-1), f[:, [1, 2, 0]].reshape(-1)
    c_lo = np.where(v0 < v1, c0, c1)
    c_hi = np.where(v0 < v1, c1, c0)
    if order is None:
        order = np.argsort(inverse)
    inv_s = inverse[order]
    same = inv_s[1:] == inv_s[:-1]
    a, b = order[:-1][same], order[1:][same]
    rows = np.concatenate([c_lo[a], c_hi[a]])
    cols = np.concatenate([c_lo[b], c_hi[b]])
    g = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(3 * nf, 3 * nf))
    _, labels = connected_components(g, directed=False)
    n_lab = np.int64(labels.max() + 1)
    keys = np.unique(f.reshape(-1) * n_lab + labels)      # one key per (vertex, fan)
    return np.bincount(keys // n_lab, minlength=n_vertices)


def count_duplicate_rows(a: np.ndarray) -> int:
    """Rows of a 2-D array equal to an earlier row (lexsort + neighbour compare; faster than
    ``np.unique(axis=0)``)."""
    if len(a) < 2:
        return 0
    order = np.lexsort(a.T[::-1])
    s = a[order]
    return int((s[1:] == s[:-1]).all(axis=1).sum())


def face_components(faces: np.ndarray, n_vertices: int) -> tuple[int, np.ndarray]:
    """Vertex-connected components: (count, (F,) int64 label per face)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return 0, np.zeros(0, dtype=np.int64)
    rows = np.concatenate([f[:, 0], f[:, 1]])
    cols = np.concatenate([f[:, 1], f[:, 2]])
    g = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n_vertices, n_vertices))
    _, vlab = connected_components(g, directed=False)
    flab = vlab[f[:, 0]]
    uniq, flab = np.unique(flab, return_inverse=True)
    return len(uniq), flab.astype(np.int64)


def boundary_loops(edges: np.ndarray, n_vertices: int) -> np.ndarray:
    """Edge count of each boundary loop (hole or open border), largest first; (H,) int64."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if len(edges) == 0:
        return np.zeros(0, dtype=np.int64)
    g = coo_matrix((np.ones(len(edges), dtype=np.int8), (edges[:, 0], edges[:, 1])),
                   shape=(n_vertices, n_vertices))
    _, lab = connected_components(g, directed=False)
    sizes = np.bincount(lab[edges[:, 0]])
    return np.sort(sizes[sizes > 0])[::-1].astype(np.int64)


def count_self_intersections(vertices: np.ndarray, faces: np.ndarray) -> int:
    """Faces that intersect another face of the mesh (PyMeshLab's test)."""
    from meshprep.io import meshset_from_arrays

    ms = meshset_from_arrays(vertices, faces)
    ms.compute_selection_by_self_intersections_per_face()
    return int(ms.current_mesh().selected_face_number())


def inspect_arrays(vertices: np.ndarray, faces: np.ndarray, *,
                   self_intersections: bool | None = None) -> dict:
    """Statistics and defect counts of a triangle mesh.

    Parameters
    ----------
    vertices : (V, 3) float
        May contain NaN/inf rows (counted, and left out of bounds and geometry).
    faces : (F, 3) int
    self_intersections : bool or None
        Count self-intersecting faces; None: only when F <= SELF_INTERSECTION_MAX_FACES.

    Returns
    -------
    dict (JSON-ready) with counts (``vertices``, ``faces``, ``components``), ``bounds``
    [[min xyz], [max xyz]], ``diagonal``, ``units_guess``, defect counts (``non_finite_vertices``,
    ``unreferenced_vertices``, ``duplicate_vertices``, ``duplicate_faces``, ``degenerate_faces``,
    ``sliver_faces``, ``boundary_edges``, ``holes``, ``largest_hole_edges``, ``non_manifold_edges``,
    ``non_manifold_vertices``, ``inconsistent_orientation_edges``, ``self_intersecting_faces``
    (None when not checked)), flags ``watertight``, ``manifold``, ``oriented`` and ``volume`` (signed,
    None unless watertight and oriented).
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    nv, nf = len(v), len(f)
    finite = np.isfinite(v).all(axis=1)
    out: dict = {"vertices": int(nv), "faces": int(nf), "non_finite_vertices": int((~finite).sum())}
    if finite.any():
        lo, hi = v[finite].min(axis=0), v[finite].max(axis=0)
        diag = float(np.linalg.norm(hi - lo))
        out["bounds"] = [lo.tolist(), hi.tolist()]
    else:
        lo = hi = np.zeros(3)
        diag = 0.0
        out["bounds"] = None
    out["diagonal"] = diag
    out["units_guess"] = guess_units(diag)
    referenced = np.zeros(nv, dtype=bool)
    referenced[f.reshape(-1)] = True
    out["unreferenced_vertices"] = int((~referenced).sum())
    out["duplicate_vertices"] = count_duplicate_rows(v[finite])
    out["non_finite_faces"] = int((~finite[f]).any(axis=1).sum()) if nf else 0
    out["duplicate_faces"] = count_duplicate_rows(np.sort(f, axis=1))
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    good = finite[f].all(axis=1)
    centre = 0.5 * (lo + hi)
    area = np.zeros(nf)
    quality = np.zeros(nf)
    if good.any():
        p = v[f[good]] - centre
        e0, e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 1], p[:, 0] - p[:, 2]
        area[good] = 0.5 * np.linalg.norm(np.cross(e0, -e2), axis=1)
        ssq = (e0 ** 2).sum(1) + (e1 ** 2).sum(1) + (e2 ** 2).sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            quality[good] = np.where(ssq > 0, 4 * np.sqrt(3) * area[good] / ssq, 0.0)
    degenerate = repeated | (good & (area <= constants.DEGENERATE_AREA_REL * diag ** 2))
    out["degenerate_faces"] = int(degenerate.sum())
    out["sliver_faces"] = int((good & ~degenerate & (quality < 0.01)).sum())
    out["area"] = float(area.sum())
    # Topology on the non-degenerate faces.
    ft = f[~repeated]
    topo = edge_topology(ft, nv)
    counts = topo["counts"]
    bnd = topo["edges"][counts == 1]
    loops = boundary_loops(bnd, nv)
    out["edges"] = int(len(counts))
    out["boundary_edges"] = int(len(bnd))
    out["holes"] = int(len(loops))
    out["largest_hole_edges"] = int(loops[0]) if len(loops) else 0
    out["non_manifold_edges"] = int((counts > 2).sum())
    fans = count_fans(ft, nv, topo["inverse"], topo["order"])
    out["non_manifold_vertices"] = int((fans > 1).sum())
    out["inconsistent_orientation_edges"] = int(topo["same_direction"].sum())
    ncomp, _ = face_components(ft, nv)
    out["components"] = int(ncomp)
    if self_intersections is None:
        self_intersections = 0 < nf <= constants.SELF_INTERSECTION_MAX_FACES
    if self_intersections and nf and finite.all():
        out["self_intersecting_faces"] = count_self_intersections(v, f)
    else:
        out["self_intersecting_faces"] = None
    out["manifold"] = bool(nf > 0 and out["non_manifold_edges"] == 0
                           and out["non_manifold_vertices"] == 0)
    out["watertight"] = bool(out["manifold"] and out["boundary_edges"] == 0)
    out["oriented"] = bool(nf > 0 and out["inconsistent_orientation_edges"] == 0
                           and out["non_manifold_edges"] == 0)
    closed = out["watertight"] and out["oriented"] and out["non_finite_faces"] == 0
    out["volume"] = signed_volume(v, f[~repeated]) if closed else None
    return out


def inspect(path: str | Path, *, self_intersections: bool | None = None) -> dict:
    """Read a mesh file and return :func:`inspect_arrays`'s statistics plus ``file`` and ``seconds``.

    Also reports whether the file carries vertex colours, UVs and textures.

    Raises
    ------
    meshprep.errors.InputError
        When the file cannot be read.
    """
    from meshprep.io import arrays_of, load_meshset

    t0 = time.perf_counter()
    ms = load_meshset(path)
    m = ms.current_mesh()
    v, f = arrays_of(ms)
    rep = inspect_arrays(v, f, self_intersections=self_intersections)
    rep["file"] = str(path)
    rep["vertex_colors"] = bool(m.has_vertex_color())
    rep["uvs"] = bool(m.has_wedge_tex_coord() or m.has_vertex_tex_coord())
    rep["textures"] = int(m.texture_number())
    rep["seconds"] = round(time.perf_counter() - t0, 3)
    return rep
