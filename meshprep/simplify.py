"""Quadric edge-collapse simplification that keeps colours, UVs and boundaries.

PyMeshLab's quadric edge collapse (Garland-Heckbert) with boundary preservation and, for meshes with
per-wedge UVs, the texture-aware variant. ``max_error`` searches the face count: the smallest mesh
whose measured deviation (:func:`meshprep.metrics.surface_deviation`) stays under the bound.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from meshprep import constants
from meshprep.errors import InputError

if TYPE_CHECKING:  # pragma: no cover
    import pymeshlab

log = logging.getLogger(__name__)

ERROR_STATS = ("max", "p95", "mean")


BOUNDARY_MODES = ("weighted", "locked", "free")


def _decimation_params(target_faces: int, boundary: str) -> dict:
    """PyMeshLab quadric parameters. Boundary modes: ``weighted`` adds border-plane quadrics
    (weight BOUNDARY_QUADRIC_WEIGHT) so open borders stay where they are but may lose vertices;
    ``locked`` forbids moving or removing border vertices (exact borders, but a scan with many holes
    stops reducing once the borders are most of what is left, and the last collapses fold); ``free``
    treats borders like any edge."""
    return dict(targetfacenum=int(max(target_faces, 1)), qualitythr=0.3,
                preserveboundary=boundary == "locked",
                boundaryweight=constants.BOUNDARY_QUADRIC_WEIGHT if boundary == "weighted" else 1.0,
                preservenormal=True, optimalplacement=True, planarquadric=True)


def _decimate_part(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None,
                   target_faces: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Worker: decimate one slab given as arrays. Its borders (the cuts, and with them the mesh's
    own open borders) are always kept in place, so the slabs weld back exactly."""
    import pymeshlab

    kw = {} if colors is None else {"v_color_matrix": colors}
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vertices, face_matrix=faces, **kw))
    ms.meshing_decimation_quadric_edge_collapse(**_decimation_params(target_faces, "locked"),
                                                preservetopology=False, autoclean=True)
    m = ms.current_mesh()
    m.compact()
    return (np.array(m.vertex_matrix()), np.array(m.face_matrix()),
            np.array(m.vertex_color_matrix()) if colors is not None else None)


def _simplify_parallel(ms: "pymeshlab.MeshSet", target_faces: int, workers: int) -> None:
    """Split the current mesh into ``workers`` slabs along its longest axis, decimate them in
    separate processes with the cuts kept fixed (boundary preservation), and weld the slabs back
    (the cut vertices are untouched, so they match bit for bit). Replaces the current mesh."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    import pymeshlab

    m = ms.current_mesh()
    v = np.array(m.vertex_matrix())
    f = np.array(m.face_matrix())
    col = np.array(m.vertex_color_matrix()) if m.has_vertex_color() else None
    axis = int(np.argmax(v.max(0) - v.min(0)))
    key = v[f, axis].mean(axis=1)
    cuts = np.quantile(key, np.linspace(0, 1, workers + 1)[1:-1])
    slab = np.searchsorted(cuts, key)
    jobs = []
    for k in range(workers):
        fk = f[slab == k]
        used, inv = np.unique(fk, return_inverse=True)
        jobs.append((v[used], inv.reshape(-1, 3).astype(np.int32), None if col is None else col[used],
                     int(round(target_faces * len(fk) / len(f)))))
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as ex:
        parts = list(ex.map(_decimate_part, *zip(*jobs)))
    off = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    vv = np.vstack([p[0] for p in parts])
    ff = np.vstack([p[1] + o for p, o in zip(parts, off)]).astype(np.int32)
    kw = {} if col is None else {"v_color_matrix": np.vstack([p[2] for p in parts])}
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vv, face_matrix=ff, **kw))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_unreferenced_vertices()


def simplify_meshset(ms: "pymeshlab.MeshSet", target_faces: int, *, boundary: str = "weighted",
                     workers: int | None = None) -> int:
    """Add a simplified copy (about ``target_faces`` faces) of the current mesh of ``ms``.

    The copy lives in the same MeshSet (so it shares the texture images), becomes the current mesh,
    and its id is returned; the original mesh is not modified.

    ``workers`` > 1 decimates slabs of the mesh in parallel processes (meshes without UVs; the slab
    cuts are kept exactly, so the seams add a line of unsimplified edges, and open borders are
    always preserved). ``None``: two
    workers for meshes of ``PARALLEL_MIN_FACES`` faces or more when two cores exist, else one.
    """
    import os

    m = ms.current_mesh()
    if workers is None:
        workers = (min(2, os.cpu_count() or 1)
                   if m.face_number() >= constants.PARALLEL_MIN_FACES else 1)
    if target_faces >= m.face_number():
        ms.generate_copy_of_current_mesh()
        return ms.current_mesh_id()
    if workers > 1 and not m.has_wedge_tex_coord() and not m.has_vertex_tex_coord():
        _simplify_parallel(ms, target_faces, workers)
        return ms.current_mesh_id()
    ms.generate_copy_of_current_mesh()
    new = ms.current_mesh_id()
    common = _decimation_params(target_faces, boundary)
    if ms.current_mesh().has_wedge_tex_coord():
        ms.meshing_decimation_quadric_edge_collapse_with_texture(**common, extratcoordw=1.0)
    else:
        ms.meshing_decimation_quadric_edge_collapse(**common, preservetopology=False, autoclean=True)
    ms.current_mesh().compact()
    return new


def _arrays_id(ms: "pymeshlab.MeshSet", mid: int) -> tuple[np.ndarray, np.ndarray]:
    m = ms.mesh(mid)
    return (np.array(m.vertex_matrix(), dtype=np.float64), np.array(m.face_matrix(), dtype=np.int32))


def _deviation(ms: "pymeshlab.MeshSet", a: int, b: int, samples: int, seed: int) -> dict:
    from meshprep.metrics import surface_deviation

    return surface_deviation(*_arrays_id(ms, a), *_arrays_id(ms, b), samples=samples, seed=seed)


def _drop(ms: "pymeshlab.MeshSet", mid: int) -> None:
    ms.set_current_mesh(mid)
    ms.delete_current_mesh()


def simplify(in_path: str | Path, out_path: str | Path, *, target_faces: int | None = None,
             max_error: float | None = None, error_stat: str = "max", relative: bool = False,
             boundary: str = "weighted", report: str | Path | None = None,
             samples: int = constants.DEVIATION_SAMPLES, seed: int = 0,
             workers: int | None = None) -> dict:
    """Simplify a mesh file to a face count or an error bound; write the mesh and a JSON report.

    Parameters
    ----------
    in_path, out_path : path
    target_faces : int, optional
        Face count to reach (exactly one of ``target_faces`` and ``max_error``).
    max_error : float, optional
        Bound on the deviation, in mesh units (or as a fraction of the bounding-box diagonal when
        ``relative``); the smallest mesh meeting it is kept.
    error_stat : {'max', 'p95', 'mean'}
        Which deviation statistic the bound applies to (symmetric, sampled).
    boundary : {'weighted', 'locked', 'free'}
        How open borders (scans) are treated; see :func:`_decimation_params`.
    samples, seed
        Deviation sampling (points per surface, seed).
    workers : int, optional
        Parallel decimation processes (see :func:`simplify_meshset`).

    Returns
    -------
    dict report: ``before``/``after`` face counts, ``deviation`` (mean/p95/max in mesh units and as
    fractions of the diagonal), ``tries`` (for ``max_error``), ``seconds``.
    """
    from meshprep.io import check_writable, load_meshset, save_meshset, write_json

    t0 = time.perf_counter()
    if (target_faces is None) == (max_error is None):
        raise InputError("give exactly one of --target-faces N and --max-error E")
    if target_faces is not None and target_faces < 1:
        raise InputError(f"--target-faces {target_faces} must be a positive face count")
    if max_error is not None and not (max_error > 0 and np.isfinite(max_error)):
        raise InputError(f"--max-error {max_error} must be a positive distance")
    if boundary not in BOUNDARY_MODES:
        raise InputError(f"--boundary {boundary!r} is not one of {', '.join(BOUNDARY_MODES)}")
    if error_stat not in ERROR_STATS:
        raise InputError(f"--error-stat {error_stat!r} is not one of {', '.join(ERROR_STATS)}")
    out_path = check_writable(out_path)
    ms = load_meshset(in_path)
    src = ms.current_mesh_id()
    n0 = int(ms.current_mesh().face_number())
    if n0 == 0:
        raise InputError(f"{in_path}: has no faces to simplify (a point cloud?); give a triangle mesh")
    tries = []
    if target_faces is not None:
        best = simplify_meshset(ms, target_faces, boundary=boundary, workers=workers)
        dev = _deviation(ms, src, best, samples, seed)
    else:
        v0, _ = _arrays_id(ms, src)
        diag = float(np.linalg.norm(v0.max(0) - v0.min(0)))
        bound = max_error * diag if relative else max_error
        lo, hi = 0, n0          # hi: a face count known to meet the bound (the input itself)
        best, dev = src, {"mean": 0.0, "p95": 0.0, "max": 0.0, "diagonal": diag}
        n = max(n0 // 2, 4)
        # Halve while the bound holds, then bisect between the last good and first bad count.
        while 4 <= n < hi:
            ms.set_current_mesh(src)
            cand = simplify_meshset(ms, n, boundary=boundary, workers=workers)
            d = _deviation(ms, src, cand, samples, seed)
            ok = d[error_stat] <= bound
            tries.append({"target_faces": n, "faces": int(ms.mesh(cand).face_number()),
                          error_stat: d[error_stat], "ok": bool(ok)})
            if ok:
                if best != src:
                    _drop(ms, best)
                hi, best, dev = n, cand, d
            else:
                _drop(ms, cand)
                lo = n
            if lo == 0:
                n = n // 2
            else:
                if hi - lo <= max(constants.MAX_ERROR_SEARCH_REL * hi, 1):
                    break
                n = (lo + hi) // 2
    ms.set_current_mesh(best)
    save_meshset(ms, out_path)
    diag = dev["diagonal"]
    rep = {"command": "simplify", "input": str(in_path), "output": str(out_path),
           "before": {"faces": n0, "vertices": int(ms.mesh(src).vertex_number())},
           "after": {"faces": int(ms.mesh(best).face_number()),
                     "vertices": int(ms.mesh(best).vertex_number())},
           "reduction": n0 / max(int(ms.mesh(best).face_number()), 1),
           "deviation": {**dev, **{f"{k}_rel": (dev[k] / diag if diag > 0 else 0.0)
                                   for k in ("mean", "p95", "max")}},
           "target_faces": target_faces, "max_error": max_error, "error_stat": error_stat,
           "relative": relative, "boundary": boundary, "tries": tries, "ok": True,
           "seconds": round(time.perf_counter() - t0, 3)}
    write_json(Path(report) if report else out_path.with_name(out_path.name + ".report.json"), rep)
    return rep
