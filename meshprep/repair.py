"""Mesh repair: clean, drop junk, fix non-manifold elements, close holes, orient faces.

The passes run with PyMeshLab on a MeshSet, so vertex colours, UVs and textures survive. They repeat
until a pass changes nothing, which makes :func:`repair` idempotent: repairing its output changes
nothing.

Two kinds of input are told apart (``kind``):

- ``object``: must end watertight, manifold and oriented outwards (positive volume); every hole is
  closed. Anything else is a :class:`~meshprep.errors.RepairError`.
- ``scan``: an open surface (a room); only small holes are closed, the result must be manifold and
  consistently oriented; with camera positions, each component faces the cameras.
- ``auto``: ``scan`` when cameras are given or when the holes are large for the surface
  (:func:`decide_kind`), else ``object``.
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
    import pymeshlab

log = logging.getLogger(__name__)

KINDS = ("auto", "object", "scan")

# auto kind: when discs spanning the boundary loops would add more than this fraction of the surface
# area, the mesh is an open scan (a flat square sheet: 1.27; a sphere missing a 60-degree cap: 0.19).
SCAN_HOLE_AREA_RATIO = 0.25


def _counts(ms: "pymeshlab.MeshSet") -> tuple[int, int]:
    m = ms.current_mesh()
    return int(m.vertex_number()), int(m.face_number())


def _arrays(ms: "pymeshlab.MeshSet") -> tuple[np.ndarray, np.ndarray]:
    from meshprep.io import arrays_of

    ms.current_mesh().compact()
    return arrays_of(ms)


def _select_faces(ms: "pymeshlab.MeshSet", mask: np.ndarray) -> None:
    """Select exactly the faces where ``mask`` (F,) is true (via a temporary face attribute)."""
    m = ms.current_mesh()
    m.compact()
    values = mask.astype(np.float64)
    # PyMeshLab cannot delete custom attributes (they are not written to files): use a fresh name.
    for i in range(1 << 16):
        name = f"meshprep_sel{i}"
        try:
            m.add_face_custom_scalar_attribute(values, name)
            break
        except Exception as e:  # "already has a custom attribute with the name"
            if type(e).__name__ != "PyMeshLabException":
                raise
    ms.compute_selection_by_condition_per_face(condselect=f"{name} > 0.5")


def _apply(ms: "pymeshlab.MeshSet", log_: list[dict], step: str, fn, /, **kw) -> None:
    """Run a PyMeshLab filter and record what it changed."""
    v0, f0 = _counts(ms)
    fn(**kw)
    v1, f1 = _counts(ms)
    if (v0, f0) != (v1, f1):
        log_.append({"step": step, "vertices": v1 - v0, "faces": f1 - f0})


def _remove_non_finite(ms: "pymeshlab.MeshSet", log_: list[dict]) -> None:
    v, _ = _arrays(ms)
    if np.isfinite(v).all():
        return
    cond = "(x!=x)||(y!=y)||(z!=z)||(abs(x)>1e300)||(abs(y)>1e300)||(abs(z)>1e300)"
    ms.compute_selection_by_condition_per_vertex(condselect=cond)
    ms.compute_selection_transfer_vertex_to_face(inclusive=False)
    _apply(ms, log_, "remove non-finite vertices", ms.meshing_remove_selected_vertices_and_faces)


def _junk_components(v: np.ndarray, f: np.ndarray, n: int, lab: np.ndarray, junk_diag_rel: float,
                     junk_faces: int) -> np.ndarray:
    """(n,) bool: components that are small by diameter or face count (never the largest one)."""
    if n <= 1:
        return np.zeros(n, dtype=bool)
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    sizes = np.bincount(lab, minlength=n)
    order = np.argsort(lab, kind="stable")
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    corners = v[f[order]]                                  # (F, 3 corners, 3 xyz), by component
    lo = np.minimum.reduceat(corners.min(axis=1), starts, axis=0)
    hi = np.maximum.reduceat(corners.max(axis=1), starts, axis=0)
    del corners
    cdiag = np.linalg.norm(hi - lo, axis=1)
    # Few faces alone is junk only when tiny next to the whole (a 2-triangle mesh keeps both).
    junk = (cdiag < junk_diag_rel * diag) | ((sizes < junk_faces) & (sizes < 0.01 * len(f)))
    junk[np.argmax(sizes)] = False
    return junk


def _remove_junk(ms: "pymeshlab.MeshSet", log_: list[dict], junk_diag_rel: float, junk_faces: int,
                 comps: tuple[int, np.ndarray] | None = None) -> None:
    """Drop components that are small by diameter or face count (never the largest one).

    ``comps`` (count, (F,) face labels) of the current mesh, when already known.
    """
    from meshprep.inspect import face_components

    v, f = _arrays(ms)
    n, lab = comps if comps is not None else face_components(f, len(v))
    junk = _junk_components(v, f, n, lab, junk_diag_rel, junk_faces)
    if not junk.any():
        return
    _select_faces(ms, junk[lab])
    _apply(ms, log_, f"remove {int(junk.sum())} junk components", ms.meshing_remove_selected_faces)
    ms.meshing_remove_unreferenced_vertices()


def _orient(ms: "pymeshlab.MeshSet", log_: list[dict], kind: str, cameras: np.ndarray | None,
            comps: tuple[int, np.ndarray] | None = None) -> bool:
    """Flip whole components: objects to positive volume, scans towards the cameras.

    ``comps`` (count, (F,) face labels) of the current mesh, when already known. Returns whether
    faces were flipped.
    """
    from meshprep.inspect import face_components

    if kind != "object" and (cameras is None or not len(cameras)):
        return False
    v, f = _arrays(ms)
    if len(f) == 0:
        return False
    n, lab = comps if comps is not None else face_components(f, len(v))
    c = 0.5 * (v.min(0) + v.max(0))
    a, b, d = v[f[:, 0]] - c, v[f[:, 1]] - c, v[f[:, 2]] - c
    if kind == "object":
        score = np.bincount(lab, weights=np.einsum("ij,ij->i", a, np.cross(b, d)), minlength=n)
        what = "orient components outwards"
    elif cameras is not None and len(cameras):
        score = camera_votes(v, f, lab, n, cameras)
        what = "orient components towards the cameras"
    else:  # pragma: no cover (returned above)
        return False
    flip = score < 0
    if not flip.any():
        return False
    _select_faces(ms, flip[lab])
    ms.meshing_invert_face_orientation(forceflip=True, onlyselected=True)
    ms.set_selection_none()
    log_.append({"step": what, "faces_flipped": int(flip[lab].sum()), "components_flipped": int(flip.sum())})
    return True


def _drop_non_orientable(ms: "pymeshlab.MeshSet", log_: list[dict], topo: dict | None = None) -> bool:
    """Remove the faces on edges still inconsistently oriented after coherent re-orientation.

    Such edges remain only on non-orientable strips (Moebius-like TSDF artefacts); removing the faces
    opens a small hole that the next pass closes.
    """
    from meshprep.inspect import edge_topology

    if topo is None:
        v, f = _arrays(ms)
        topo = edge_topology(f, len(v))
    bad = topo["same_direction"]
    if not bad.any():
        return False
    mask = bad[topo["inverse"]].reshape(-1, 3).any(axis=1)
    _select_faces(ms, mask)
    _apply(ms, log_, "remove faces on non-orientable edges", ms.meshing_remove_selected_faces)
    ms.meshing_remove_unreferenced_vertices()
    return True


# inspect counts that a repair pass would change; when all are zero, no hole of the size closed is
# left, no component is junk and every component is oriented (the pass ends by orienting), the next
# pass is provably a no-op and is skipped.
_PASS_DEFECTS = ("non_finite_vertices", "duplicate_vertices", "duplicate_faces", "degenerate_faces",
                 "unreferenced_vertices", "non_manifold_edges", "non_manifold_vertices",
                 "inconsistent_orientation_edges")


def _settled(stats: dict, extra: dict, v: np.ndarray, f: np.ndarray, holes: int, junk_diag_rel: float,
             junk_faces: int) -> bool:
    """Whether another repair pass would change nothing (from :func:`analyse_arrays` results)."""
    if stats["faces"] == 0 or not extra["all_faces"] or any(stats[k] for k in _PASS_DEFECTS):
        return False
    loops = extra["loops"]
    if holes >= 3 and len(loops) and int(loops.min()) <= holes:
        return False
    return not _junk_components(v, f, extra["n_components"], extra["labels"], junk_diag_rel,
                                junk_faces).any()


def camera_votes(vertices: np.ndarray, faces: np.ndarray, labels: np.ndarray, n: int,
                 cameras: np.ndarray) -> np.ndarray:
    """Per component (n,) area-weighted vote: > 0 when its faces' fronts face their nearest camera."""
    from scipy.spatial import cKDTree

    c = 0.5 * (vertices.min(0) + vertices.max(0))
    a, b, d = (vertices[faces[:, k]] - c for k in range(3))
    cr = np.cross(b - a, d - a)
    cen = (a + b + d) / 3.0
    cams = np.asarray(cameras, dtype=np.float64) - c
    _, idx = cKDTree(cams).query(cen)
    vote = np.sign(np.einsum("ij,ij->i", cr, cams[idx] - cen)) * np.linalg.norm(cr, axis=1)
    return np.bincount(labels, weights=vote, minlength=n)


def orient_towards_cameras(vertices: np.ndarray, faces: np.ndarray, cameras: np.ndarray) -> np.ndarray:
    """Faces (F,3) int32 with each vertex-connected component flipped to face the cameras.

    Assumes each component is already coherently oriented (as after :func:`repair_meshset`).
    """
    from meshprep.inspect import face_components

    f = np.asarray(faces, dtype=np.int32)
    n, lab = face_components(f, len(vertices))
    flip = camera_votes(np.asarray(vertices, dtype=np.float64), f, lab, n, cameras) < 0
    out = f.copy()
    out[flip[lab]] = out[flip[lab]][:, ::-1]
    return out


def decide_kind(vertices: np.ndarray, faces: np.ndarray, cameras: np.ndarray | None) -> tuple[str, str]:
    """The ``auto`` rule: ('scan' | 'object', reason).

    Each boundary loop of length L would be closed by a patch of about a disc's area L^2 / (4 pi).
    When these patches add up to more than ``SCAN_HOLE_AREA_RATIO`` of the surface, the holes are
    not defects but the border of an open surface (a sheet, a room): a scan. A closed shell with a
    few holes (a cup scanned without its bottom) is an object.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from meshprep.inspect import edge_topology

    if cameras is not None:
        return "scan", "camera positions were given"
    if len(faces) == 0:
        return "object", "empty mesh"
    v = vertices - vertices.min(0)
    topo = edge_topology(faces, len(v))
    bnd = topo["edges"][topo["counts"] == 1]
    area = 0.5 * float(np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]],
                                                v[faces[:, 2]] - v[faces[:, 0]]), axis=1).sum())
    if len(bnd) == 0:
        return "object", "closed surface (no boundary)"
    g = coo_matrix((np.ones(len(bnd)), (bnd[:, 0], bnd[:, 1])), shape=(len(v), len(v)))
    _, lab = connected_components(g, directed=False)
    lengths = np.bincount(lab[bnd[:, 0]], weights=np.linalg.norm(v[bnd[:, 0]] - v[bnd[:, 1]], axis=1))
    ratio = float((lengths ** 2).sum() / (4 * np.pi) / max(area, 1e-300))
    if ratio > SCAN_HOLE_AREA_RATIO:
        return "scan", (f"holes would need patches of {ratio:.2f} x the surface area "
                        f"(> {SCAN_HOLE_AREA_RATIO}): an open surface")
    return "object", f"holes would need patches of {ratio:.3f} x the surface area (<= {SCAN_HOLE_AREA_RATIO})"


def repair_meshset(ms: "pymeshlab.MeshSet", *, kind: str = "auto", cameras: np.ndarray | None = None,
                   max_hole_edges: int | None = None,
                   junk_diag_rel: float = constants.JUNK_COMPONENT_DIAG_REL,
                   junk_faces: int = constants.JUNK_COMPONENT_FACES) -> dict:
    """Repair the current mesh of ``ms`` in place.

    Parameters
    ----------
    ms : pymeshlab.MeshSet
        Holds the mesh; modified in place (colours, UVs and textures are kept).
    kind : {'auto', 'object', 'scan'}
    cameras : (N, 3) float64, optional
        Camera centres in mesh units (scans: faces are turned towards them).
    max_hole_edges : int, optional
        Largest hole closed; defaults to OBJECT_MAX_HOLE_EDGES or SCAN_MAX_HOLE_EDGES.
    junk_diag_rel, junk_faces
        Components below this diagonal fraction or face count are removed (never the largest).

    Returns
    -------
    dict with ``kind``, ``kind_reason``, ``passes`` and ``changes`` (a list of steps with the change
    in vertex/face counts).
    """
    return _repair_meshset(ms, kind=kind, cameras=cameras, max_hole_edges=max_hole_edges,
                           junk_diag_rel=junk_diag_rel, junk_faces=junk_faces)[0]


def _repair_meshset(ms: "pymeshlab.MeshSet", *, kind: str, cameras: np.ndarray | None,
                    max_hole_edges: int | None, junk_diag_rel: float,
                    junk_faces: int) -> tuple[dict, dict]:
    """:func:`repair_meshset`, also returning the :func:`~meshprep.inspect.inspect_arrays` statistics
    of the result (without the self-intersection count).

    Each pass ends with one topology analysis of its result; it serves the non-orientable-edge
    check, the orientation (components), the test whether another pass could change anything
    (:func:`_settled`; a settled mesh ends the loop without a confirming pass), the next pass's junk
    check when its cleaning filters changed nothing, and the final statistics.
    """
    from meshprep.inspect import analyse_arrays, boundary_loops, edge_topology

    if kind not in KINDS:
        raise InputError(f"kind {kind!r} is not one of {', '.join(KINDS)}")
    changes: list[dict] = []
    _remove_non_finite(ms, changes)
    reason = "given"
    passes = 0
    stats: dict | None = None
    extra: dict | None = None
    before = _arrays(ms)
    for passes in range(1, constants.REPAIR_MAX_PASSES + 1):
        n_logged = len(changes)
        _apply(ms, changes, "remove duplicate vertices", ms.meshing_remove_duplicate_vertices)
        _apply(ms, changes, "remove duplicate faces", ms.meshing_remove_duplicate_faces)
        _apply(ms, changes, "remove zero-area faces", ms.meshing_remove_null_faces)
        _apply(ms, changes, "remove unreferenced vertices", ms.meshing_remove_unreferenced_vertices)
        if ms.current_mesh().face_number() == 0:
            stats = None
            break
        # These filters only delete: unchanged counts mean an unchanged mesh, so the last pass's
        # components still hold.
        comps = None
        if (extra is not None and extra["all_faces"] and len(changes) == n_logged
                and _counts(ms) == (len(before[0]), len(before[1]))):
            comps = (extra["n_components"], extra["labels"])
        _remove_junk(ms, changes, junk_diag_rel, junk_faces, comps)
        _apply(ms, changes, "repair non-manifold edges (remove faces)",
               ms.meshing_repair_non_manifold_edges, method=0)
        # Split copies are moved slightly apart, so that the duplicate-vertex pass does not merge them
        # back into the same bow-tie.
        _apply(ms, changes, "repair non-manifold vertices (split)", ms.meshing_repair_non_manifold_vertices,
               vertdispratio=constants.SPLIT_VERTEX_DISPLACEMENT)
        _apply(ms, changes, "remove unreferenced vertices", ms.meshing_remove_unreferenced_vertices)
        if kind == "auto" or passes == 1 and reason == "given":
            if kind == "auto":
                v, f = _arrays(ms)
                kind, reason = decide_kind(v, f, cameras)
        if ms.current_mesh().face_number() == 0:
            stats = None
            break
        holes = max_hole_edges if max_hole_edges is not None else (
            constants.OBJECT_MAX_HOLE_EDGES if kind == "object" else constants.SCAN_MAX_HOLE_EDGES)
        if holes >= 3:
            try:
                _apply(ms, changes, f"close holes up to {holes} edges", ms.meshing_close_holes,
                       maxholesize=int(holes), selfintersection=kind != "object", newfaceselected=False)
            except Exception as e:  # PyMeshLab refuses non-manifold input; the next pass retries
                if type(e).__name__ != "PyMeshLabException":
                    raise
                changes.append({"step": "close holes skipped", "reason": " ".join(str(e).split())})
            # Holes along collinear edges are filled with zero-area faces: drop them again, the hole
            # stays (a fixed point, so the next pass changes nothing).
            _apply(ms, changes, "remove zero-area hole faces", ms.meshing_remove_null_faces)
        f_before = _arrays(ms)[1]
        try:
            ms.meshing_re_orient_faces_coherently()
        except Exception as e:
            if type(e).__name__ != "PyMeshLabException":
                raise
        v, f = _arrays(ms)
        if f_before.shape == f.shape and not np.array_equal(f_before, f):
            n_flip = int((f_before != f).any(axis=1).sum())
            changes.append({"step": "orient faces coherently", "faces_flipped": n_flip})
        del f_before
        topo = edge_topology(f, len(v))
        if _drop_non_orientable(ms, changes, topo):
            v, f = _arrays(ms)
            topo = edge_topology(f, len(v))
        # Full analysis only when the pass may have settled (no non-manifold edge, no hole small
        # enough to close): otherwise another pass follows anyway.
        bnd = topo["edges"][topo["counts"] == 1]
        loops = boundary_loops(bnd, len(v)) if holes >= 3 else np.zeros(0, dtype=np.int64)
        may_settle = not (topo["counts"] > 2).any() and not (len(loops) and int(loops.min()) <= holes)
        stats = extra = None
        if may_settle:
            stats, extra = analyse_arrays(v, f, self_intersections=False, topo=topo)
        del topo, bnd
        comps = (extra["n_components"], extra["labels"]) if extra and extra["all_faces"] else None
        if _orient(ms, changes, kind, cameras, comps):
            v, f = _arrays(ms)            # whole components flipped: re-analyse (rare)
            stats = extra = None
            if may_settle:
                stats, extra = analyse_arrays(v, f, self_intersections=False)
        unchanged = (before[0].shape == v.shape and before[1].shape == f.shape
                     and np.array_equal(before[0], v) and np.array_equal(before[1], f))
        before = (v, f)
        if unchanged:
            del changes[n_logged:]  # steps that undid each other (fill, then drop, a degenerate hole)
            break
        if stats is not None and _settled(stats, extra, v, f, holes, junk_diag_rel, junk_faces):
            break
    ms.set_selection_none()
    if stats is None:
        stats = analyse_arrays(*_arrays(ms), self_intersections=False)[0]
    return {"kind": kind, "kind_reason": reason, "passes": passes, "changes": changes}, stats


def check_repaired(stats: dict, kind: str, where: str) -> None:
    """Raise RepairError naming what is still wrong for ``kind`` (stats from inspect_arrays)."""
    problems = []
    if stats["faces"] == 0:
        raise RepairError(f"{where}: nothing is left after removing invalid elements (no valid "
                          f"triangles); the input holds no usable surface")
    if stats["non_manifold_edges"]:
        problems.append(f"{stats['non_manifold_edges']} non-manifold edges")
    if stats["non_manifold_vertices"]:
        problems.append(f"{stats['non_manifold_vertices']} non-manifold vertices")
    if stats["inconsistent_orientation_edges"]:
        problems.append(f"{stats['inconsistent_orientation_edges']} edges with inconsistent orientation")
    if kind == "object":
        if stats["boundary_edges"]:
            problems.append(f"{stats['holes']} holes left (largest {stats['largest_hole_edges']} edges)")
        if stats["volume"] is not None and stats["volume"] <= 0:
            problems.append(f"enclosed volume is {stats['volume']:.3g} (not positive)")
    if problems:
        raise RepairError(f"{where}: could not repair as {kind}: " + "; ".join(problems)
                          + (" (for an open surface use --kind scan)" if kind == "object" else ""))


def repair(in_path: str | Path, out_path: str | Path, *, kind: str = "auto",
           cameras: np.ndarray | str | Path | None = None, report: str | Path | None = None,
           max_hole_edges: int | None = None,
           junk_diag_rel: float = constants.JUNK_COMPONENT_DIAG_REL,
           junk_faces: int = constants.JUNK_COMPONENT_FACES, self_intersections: bool | None = None) -> dict:
    """Repair a mesh file and write the result and a JSON report.

    Parameters
    ----------
    in_path, out_path : path
        Input mesh (any format :mod:`meshprep.io` reads); output ``.ply``/``.obj``/``.off``/``.stl``.
    kind : {'auto', 'object', 'scan'}
        See the module docstring.
    cameras : (N, 3) array or path, optional
        Camera positions (or a file for :func:`meshprep.io.load_cameras`), for scans.
    report : path, optional
        JSON report; default ``OUT.report.json``.

    Returns
    -------
    dict: the report (``before``/``after`` inspect statistics, ``changes``, ``kind``, ``seconds``).

    Raises
    ------
    InputError
        Unreadable input or bad arguments.
    RepairError
        The result does not meet ``kind``'s requirements (the report is still written, with
        ``ok: false``; no mesh is written).
    """
    from meshprep.inspect import count_self_intersections, inspect_arrays
    from meshprep.io import (check_writable, faces_with_missing_vertices, load_cameras, load_meshset,
                             save_meshset, write_json)

    t0 = time.perf_counter()
    out_path = check_writable(out_path)
    cams = load_cameras(cameras) if isinstance(cameras, (str, Path)) else (
        None if cameras is None else np.asarray(cameras, dtype=np.float64).reshape(-1, 3))
    ms = load_meshset(in_path)
    before = inspect_arrays(*_arrays(ms), self_intersections=self_intersections)
    info, after = _repair_meshset(ms, kind=kind, cameras=cams, max_hole_edges=max_hole_edges,
                                  junk_diag_rel=junk_diag_rel, junk_faces=junk_faces)
    # The last pass analysed the result already; only the self-intersection count is left to do.
    if self_intersections is None:
        self_intersections = 0 < after["faces"] <= constants.SELF_INTERSECTION_MAX_FACES
    if self_intersections and after["faces"] and after["non_finite_vertices"] == 0:
        after["self_intersecting_faces"] = count_self_intersections(*_arrays(ms))
    dropped = faces_with_missing_vertices(in_path)
    if dropped["count"]:
        # Dropped by the reader, before ``before`` was measured: the first change of the repair.
        info["changes"].insert(0, {"step": "drop faces that point at a missing vertex (on reading)",
                                   "vertices": 0, "faces": -dropped["count"], "examples": dropped["examples"]})
    rep = {"command": "repair", "input": str(in_path), "output": str(out_path), **info,
           "before": before, "after": after}
    report_path = Path(report) if report else out_path.with_name(out_path.name + ".report.json")
    try:
        check_repaired(after, info["kind"], str(in_path))
    except RepairError as e:
        rep.update(ok=False, error=str(e), seconds=round(time.perf_counter() - t0, 3))
        write_json(report_path, rep)
        raise
    save_meshset(ms, out_path)
    rep.update(ok=True, seconds=round(time.perf_counter() - t0, 3))
    write_json(report_path, rep)
    log.info("repaired %s -> %s in %.2f s", in_path, out_path, rep["seconds"])
    return rep
