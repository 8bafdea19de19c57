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
    nxt = np.roll(f, -1, axis=1)                 # half-edge k of a face runs f[:, k] -> f[:, k+1]
    fwd = f < nxt
    key = np.where(fwd, f, nxt)
    key *= nv
    key += np.where(fwd, nxt, f)
    key = key.reshape(-1)
    del nxt
    # Stable (radix/timsort) argsort: several times faster than quicksort on the spatially coherent
    # face orders of real meshes (scans, marching cubes), and deterministic among equal keys.
    order = np.argsort(key, kind="stable")
    ks = key[order]
    del key
    new = np.empty(len(ks), dtype=bool)
    new[:1] = True
    np.not_equal(ks[1:], ks[:-1], out=new[1:])
    starts = np.flatnonzero(new)
    gid = np.cumsum(new, dtype=np.int64)
    gid -= 1
    inverse = np.empty(len(ks), dtype=np.int64)
    inverse[order] = gid
    del gid
    uniq = ks[starts]
    counts = np.diff(np.append(starts, len(ks)))
    # A two-face edge is inconsistently oriented when both half-edges run the same way; they are
    # neighbours in the sorted order.
    fs = fwd.reshape(-1)[order]
    two = counts == 2
    same = np.zeros(len(uniq), dtype=bool)
    s2 = starts[two]
    same[two] = fs[s2] == fs[s2 + 1]
    lo = uniq // nv
    edges = np.stack([lo, uniq - lo * nv], axis=1)
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
    # Half-edge h (face-major, h = 3 i + k) runs from corner h to corner h + step[k] (the next
    # corner of the face); corners are numbered like half-edges.
    if order is None:
        order = np.argsort(inverse, kind="stable")
    inv_s = inverse[order]
    same = inv_s[1:] == inv_s[:-1]
    a, b = order[:-1][same], order[1:][same]
    del inv_s, same
    step = np.array([1, 1, -2], dtype=np.int64)
    fl = f.reshape(-1)

    def ends(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(corner at the lower vertex, corner at the higher vertex) of half-edges ``h``."""
        h1 = h + step[h % 3]
        up = fl[h] < fl[h1]
        return np.where(up, h, h1), np.where(up, h1, h)

    a_lo, a_hi = ends(a)
    b_lo, b_hi = ends(b)
    rows = np.concatenate([a_lo, a_hi])
    cols = np.concatenate([b_lo, b_hi])
    del a_lo, a_hi, b_lo, b_hi
    g = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(3 * nf, 3 * nf))
    n_lab, labels = connected_components(g, directed=False)
    # Graph edges only join corners of the same vertex, so each fan (component) belongs to exactly
    # one vertex: counting the components per vertex needs no sort.
    fan_vertex = np.empty(n_lab, dtype=np.int64)
    fan_vertex[labels] = f.reshape(-1)
    return np.bincount(fan_vertex, minlength=n_vertices)


def count_duplicate_rows(a: np.ndarray) -> int:
    """Rows of a 2-D array equal to an earlier row (lexsort + neighbour compare; faster than
    ``np.unique(axis=0)``)."""
    if len(a) < 2:
        return 0
    if a.dtype.kind in "iu" and a.ndim == 2 and a.shape[1] == 3 and len(a) and a.min() >= 0:
        n = int(a.max()) + 1
        if n ** 3 < 2 ** 63:                              # one int64 key per row: a plain sort
            k = np.sort((a[:, 0].astype(np.int64) * n + a[:, 1]) * n + a[:, 2])
            return int((k[1:] == k[:-1]).sum())
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
    n, vlab = connected_components(g, directed=False)
    flab = vlab[f[:, 0]]
    # Renumber the labels that faces use to 0..k-1 in label order (isolated vertices are
    # components of their own): a presence table instead of a sort.
    used = np.zeros(n, dtype=bool)
    used[flab] = True
    remap = np.cumsum(used) - 1
    return int(used.sum()), remap[flab].astype(np.int64)


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
    """Statistics and defect counts of a triangle mesh (see :func:`analyse_arrays`)."""
    return analyse_arrays(vertices, faces, self_intersections=self_intersections)[0]


def analyse_arrays(vertices: np.ndarray, faces: np.ndarray, *, self_intersections: bool | None = None,
                   topo: dict[str, np.ndarray] | None = None) -> tuple[dict, dict]:
    """Statistics and defect counts of a triangle mesh.

    Parameters
    ----------
    vertices : (V, 3) float
        May contain NaN/inf rows (counted, and left out of bounds and geometry).
    faces : (F, 3) int
    self_intersections : bool or None
        Count self-intersecting faces; None: only when F <= SELF_INTERSECTION_MAX_FACES.
    topo : dict, optional
        :func:`edge_topology` of ``faces`` when already computed (used only when no face repeats a
        vertex, i.e. when it is the topology of the faces analysed).

    Returns
    -------
    stats : dict (JSON-ready) with counts (``vertices``, ``faces``, ``components``), ``bounds``
    [[min xyz], [max xyz]], ``diagonal``, ``units_guess``, defect counts (``non_finite_vertices``,
    ``unreferenced_vertices``, ``duplicate_vertices``, ``duplicate_faces``, ``degenerate_faces``,
    ``sliver_faces``, ``boundary_edges``, ``holes``, ``largest_hole_edges``, ``non_manifold_edges``,
    ``non_manifold_vertices``, ``inconsistent_orientation_edges``, ``self_intersecting_faces``
    (None when not checked)), flags ``watertight``, ``manifold``, ``oriented`` and ``volume`` (signed,
    None unless watertight and oriented).
    extra : dict of intermediate results, for callers that would otherwise compute them again (repair):
    ``topo`` (:func:`edge_topology` of the non-degenerate faces), ``loops`` (boundary loop sizes,
    largest first), ``n_components`` and ``labels`` ((F',) int64 component per non-degenerate face),
    ``all_faces`` (True when no face has a repeated vertex, so ``labels`` indexes all faces).
    """
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    nv, nf = len(v), len(f)
    finite = np.isfinite(v).all(axis=1)
    out: dict = {"vertices": int(nv), "faces": int(nf), "non_finite_vertices": int((~finite).sum())}
    all_finite = bool(finite.all())
    if finite.any():
        vf = v if all_finite else v[finite]
        lo, hi = vf.min(axis=0), vf.max(axis=0)
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
    out["duplicate_vertices"] = count_duplicate_rows(v if all_finite else v[finite])
    good = finite[f].all(axis=1)
    out["non_finite_faces"] = int((~good).sum())
    out["duplicate_faces"] = count_duplicate_rows(np.sort(f, axis=1))
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    centre = 0.5 * (lo + hi)
    area = np.zeros(nf)
    quality = np.zeros(nf)
    if good.any():
        fg = f if good.all() else f[good]
        # Per coordinate on contiguous 1-D arrays (no (F,3,3) corner array): edge vectors
        # e0 = p1 - p0, e1 = p2 - p1, e2 = p0 - p2, area = |e0 x (p2 - p0)| / 2.
        e0, e1, e2 = [], [], []
        for k in range(3):
            col = v[:, k] - centre[k]
            p0, p1, p2 = col[fg[:, 0]], col[fg[:, 1]], col[fg[:, 2]]
            e0.append(p1 - p0)
            e1.append(p2 - p1)
            e2.append(p0 - p2)
            del p0, p1, p2
        cx = e0[1] * -e2[2] - e0[2] * -e2[1]
        cy = e0[2] * -e2[0] - e0[0] * -e2[2]
        cz = e0[0] * -e2[1] - e0[1] * -e2[0]
        ag = 0.5 * np.sqrt(cx * cx + cy * cy + cz * cz)
        del cx, cy, cz
        ssq = sum(e[0] * e[0] + e[1] * e[1] + e[2] * e[2] for e in (e0, e1, e2))
        area[good] = ag
        with np.errstate(invalid="ignore", divide="ignore"):
            quality[good] = np.where(ssq > 0, 4 * np.sqrt(3) * ag / ssq, 0.0)
    degenerate = repeated | (good & (area <= constants.DEGENERATE_AREA_REL * diag ** 2))
    out["degenerate_faces"] = int(degenerate.sum())
    out["sliver_faces"] = int((good & ~degenerate & (quality < 0.01)).sum())
    out["area"] = float(area.sum())
    # Topology on the non-degenerate faces.
    if repeated.any():
        ft = f[~repeated]
        topo = edge_topology(ft, nv)
    else:
        ft = f
        topo = topo if topo is not None else edge_topology(ft, nv)
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
    ncomp, labels = face_components(ft, nv)
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
    extra = {"topo": topo, "loops": loops, "n_components": int(ncomp), "labels": labels,
             "all_faces": not bool(repeated.any())}
    return out, extra


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
