"""Collision proxies for physics.

Room (open scan surface): an unsigned distance grid (NPZ), exact near the surface and EDT-based
farther out, and, with camera positions, a signed one where the sign is reliable. Keys:

- ``origin`` (3,) float64, metres: position of grid point [0, 0, 0]
- ``spacing`` () float64, metres: grid step; point [i,j,k] is at ``origin + spacing * (i, j, k)``
- ``udf`` (nx, ny, nz) float32, metres: distance to the surface, clipped at ``max_distance``
- ``max_distance`` () float64, metres
- ``sdf`` (nx, ny, nz) float32 and ``sdf_valid`` (nx, ny, nz) bool, only with cameras: the surface
  is oriented towards the cameras (free space); ``sdf = +udf`` in front of it, ``-udf`` behind it,
  valid where the voxel is within the exact band and lies in front of or behind its closest face
  rather than beside an open border. Elsewhere ``sdf = udf`` and ``sdf_valid`` is false.

Object (closed): ``hull_vertices`` (H,3) float64, ``hull_faces`` (G,3) int32; convex parts, only
when the hull deviates from the shape by more than the tolerance, as ``parts_vertices`` (PV,3),
``parts_faces`` (PF,3) int32 (indices into parts_vertices), ``parts_vertex_counts`` and
``parts_face_counts`` (P,) int32 (P = 0: use the hull); ``samples`` (S,3) float64 surface points
with outward unit ``sample_normals`` (S,3); ``volume``, ``mass``, ``density``, ``com`` (3,),
``inertia`` (3,3) about the com; ``scale`` (factor applied to the input's coordinates).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from meshprep import constants
from meshprep.errors import InputError

log = logging.getLogger(__name__)

KINDS = ("auto", "room", "object")


def room_distance_grid(vertices: np.ndarray, faces: np.ndarray, *,
                       spacing: float = constants.ROOM_SPACING_M,
                       max_distance: float = constants.ROOM_MAX_DISTANCE_M,
                       cameras: np.ndarray | None = None,
                       band_voxels: int = constants.ROOM_EXACT_BAND_VOXELS,
                       pad: float = constants.ROOM_PAD_M, seed: int = 0) -> dict[str, np.ndarray]:
    """Distance grid of a room surface (see the module docstring for the keys).

    Parameters
    ----------
    vertices : (V, 3) float, metres
    faces : (F, 3) int
    spacing, max_distance, pad : float, metres
    cameras : (N, 3) float, optional
        Camera centres; when given, faces are turned towards them and ``sdf``/``sdf_valid`` are added.
    band_voxels : int
        Exact point-to-triangle distances within this many voxels of the surface; grid (EDT)
        distances beyond (0 computes every voxel exactly).
    seed : int
        Seed of the surface sampling that seeds the EDT.
    """
    from scipy import ndimage

    from meshprep.metrics import open3d_module, sample_surface

    o3d = open3d_module()

    if not (spacing > 0 and max_distance > 0):
        raise InputError(f"spacing {spacing} and max distance {max_distance} must be positive")
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    f = f[np.isfinite(v[f]).all(axis=(1, 2))]
    if len(f) == 0:
        raise InputError("the room mesh has no valid faces")
    if cameras is not None:
        from meshprep.repair import orient_towards_cameras

        f = orient_towards_cameras(v, f, cameras).astype(np.int64)
    used = v[np.unique(f)]
    lo, hi = used.min(0) - pad, used.max(0) + pad
    shape = tuple(int(x) for x in np.ceil((hi - lo) / spacing).astype(int) + 1)
    nvox = int(np.prod(shape))
    if nvox > constants.ROOM_MAX_VOXELS:
        raise InputError(f"a {spacing} m grid over this {np.round(hi - lo, 2).tolist()} m room has "
                         f"{nvox:,} voxels (> {constants.ROOM_MAX_VOXELS:,}); raise --spacing "
                         f"(or check the units: is the mesh in millimetres? use --scale 0.001)")
    origin = lo
    # Seeds: grid points nearest to dense surface samples (step < spacing/2) and to the vertices.
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum()
    n_samples = int(min(max(4 * area / (0.5 * spacing) ** 2, 1000), 5e7))
    pts, _ = sample_surface(v, f, n_samples, seed=seed)
    pts = np.vstack([pts, used])
    ijk = np.clip(np.rint((pts - origin) / spacing).astype(np.int64), 0, np.array(shape) - 1)
    seedmask = np.ones(shape, dtype=bool)
    seedmask[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = False
    d = ndimage.distance_transform_edt(seedmask, sampling=spacing).astype(np.float32)
    del seedmask
    band = d <= (band_voxels * spacing if band_voxels > 0 else np.inf)
    idx = np.nonzero(band)
    centre = 0.5 * (lo + hi)
    q = (np.stack(idx, axis=1) * spacing + (origin - centre)).astype(np.float32)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(np.ascontiguousarray(v - centre, dtype=np.float32),
                        np.ascontiguousarray(f, dtype=np.uint32))
    exact = np.empty(len(q), dtype=np.float32)
    sdf_sign = np.ones(len(q), dtype=np.float32) if cameras is not None else None
    sdf_ok = np.zeros(len(q), dtype=bool) if cameras is not None else None
    step = 1 << 20
    for i in range(0, len(q), step):
        qi = q[i:i + step]
        if cameras is None:
            exact[i:i + step] = scene.compute_distance(qi).numpy()
        else:
            cp = scene.compute_closest_points(qi)
            diff = qi - cp["points"].numpy()
            dist = np.linalg.norm(diff, axis=1)
            exact[i:i + step] = dist
            nrm = cp["primitive_normals"].numpy()
            with np.errstate(invalid="ignore", divide="ignore"):
                cos = np.einsum("ij,ij->i", diff, nrm) / np.maximum(dist, 1e-12)
            sdf_sign[i:i + step] = np.where(cos < 0, -1.0, 1.0)
            sdf_ok[i:i + step] = (np.abs(cos) >= constants.ROOM_SIGN_MIN_COS) | (dist < 1e-6)
    d[idx] = exact
    np.minimum(d, np.float32(max_distance), out=d)
    out = {"origin": origin.astype(np.float64), "spacing": np.float64(spacing), "udf": d,
           "max_distance": np.float64(max_distance)}
    if cameras is not None:
        sdf = d.copy()
        sdf[idx] = exact.clip(max=max_distance) * sdf_sign
        valid = np.zeros(shape, dtype=bool)
        valid[idx] = sdf_ok
        out["sdf"] = sdf
        out["sdf_valid"] = valid
    return out


def object_proxy_arrays(vertices: np.ndarray, faces: np.ndarray, *, density: float = 1000.0,
                        samples: int = constants.OBJECT_SAMPLES, seed: int = 0,
                        concavity_tol_rel: float = constants.CONCAVITY_TOL_REL,
                        max_parts: int = constants.MAX_CONVEX_PARTS, where: str = "mesh") -> dict:
    """Object collision proxy (see the module docstring for the keys) of a closed mesh."""
    from meshprep.metrics import sample_surface
    from meshprep.solid import solid_arrays

    s = solid_arrays(vertices, faces, density=density, concavity_tol_rel=concavity_tol_rel,
                     max_parts=max_parts, where=where)
    v, f = s["vertices"], s["faces"]
    pts, fi = sample_surface(v, f, samples, seed=seed)
    n = np.cross(v[f[fi, 1]] - v[f[fi, 0]], v[f[fi, 2]] - v[f[fi, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    parts = s["parts"]
    pv_counts = np.array([len(pv) for pv, _ in parts], dtype=np.int32)
    pf_counts = np.array([len(pf) for _, pf in parts], dtype=np.int32)
    offs = np.concatenate([[0], np.cumsum(pv_counts)[:-1]]).astype(np.int64) if parts else []
    pv = np.vstack([pv for pv, _ in parts]) if parts else np.zeros((0, 3))
    pf = (np.vstack([pf + o for (_, pf), o in zip(parts, offs)]) if parts
          else np.zeros((0, 3), dtype=np.int32))
    return {"hull_vertices": s["hull_vertices"], "hull_faces": s["hull_faces"].astype(np.int32),
            "parts_vertices": pv.astype(np.float64), "parts_faces": pf.astype(np.int32),
            "parts_vertex_counts": pv_counts, "parts_face_counts": pf_counts,
            "samples": pts, "sample_normals": n,
            "volume": np.float64(s["volume"]), "mass": np.float64(s["mass"]),
            "density": np.float64(density), "com": np.asarray(s["com"], dtype=np.float64),
            "inertia": np.asarray(s["inertia"], dtype=np.float64),
            "hull_concavity": np.float64(s["hull_concavity"])}


def object_parts(proxy: dict[str, np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The convex parts of an object proxy as a list of (vertices (Vi,3), faces (Fi,3) local indices)."""
    out = []
    vo = fo = 0
    for nv, nf in zip(proxy["parts_vertex_counts"], proxy["parts_face_counts"]):
        out.append((proxy["parts_vertices"][vo:vo + nv], proxy["parts_faces"][fo:fo + nf] - vo))
        vo += int(nv)
        fo += int(nf)
    return out


def proxy(in_path: str | Path, out_path: str | Path, *, kind: str = "auto",
          cameras: np.ndarray | str | Path | None = None, spacing: float = constants.ROOM_SPACING_M,
          max_distance: float = constants.ROOM_MAX_DISTANCE_M, density: float = 1000.0,
          scale: float = 1.0, samples: int = constants.OBJECT_SAMPLES, seed: int = 0,
          report: str | Path | None = None) -> dict:
    """Write a collision proxy NPZ for a room scan or an object, and a JSON report.

    Parameters
    ----------
    kind : {'auto', 'room', 'object'}
        ``auto``: ``room`` when cameras are given or the mesh is an open surface
        (:func:`meshprep.repair.decide_kind`), else ``object``.
    cameras : (N, 3) array or path, optional
        Camera positions (rooms): orient the surface and add ``sdf``.
    spacing, max_distance : float
        Room grid step and clip distance, in the mesh's units after ``scale`` (metres).
    density, samples, seed : object mass density (kg/m^3), surface samples and their seed.
    scale : float
        Factor applied to the coordinates first (0.001 for millimetre models).
    """
    from meshprep.io import arrays_of, check_writable, load_cameras, load_meshset, save_npz, write_json
    from meshprep.repair import decide_kind

    t0 = time.perf_counter()
    if kind not in KINDS:
        raise InputError(f"--kind {kind!r} is not one of {', '.join(KINDS)}")
    if not (scale > 0 and np.isfinite(scale)):
        raise InputError(f"--scale {scale} must be a positive number (0.001 turns millimetres into metres)")
    out_path = check_writable(out_path, (".npz",))
    cams = load_cameras(cameras) if isinstance(cameras, (str, Path)) else (
        None if cameras is None else np.asarray(cameras, dtype=np.float64).reshape(-1, 3))
    reason = "given"
    if kind == "auto":
        v, f = arrays_of(load_meshset(in_path))
        ok = np.isfinite(v[f]).all(axis=(1, 2)) if len(f) else np.zeros(0, bool)
        k, reason = decide_kind(v, f[ok], cams)
        kind = "room" if k == "scan" else "object"
    rep: dict = {"command": "proxy", "input": str(in_path), "output": str(out_path), "kind": kind,
                 "kind_reason": reason, "scale": scale}
    if kind == "room":
        v, f = arrays_of(load_meshset(in_path))
        arrays = room_distance_grid(v * scale, f, spacing=spacing, max_distance=max_distance,
                                    cameras=None if cams is None else cams * scale, seed=seed)
        rep.update(shape=list(arrays["udf"].shape), spacing=spacing, max_distance=max_distance,
                   origin=arrays["origin"], signed="sdf" in arrays,
                   sdf_valid_fraction_near_surface=(
                       float(arrays["sdf_valid"][arrays["udf"] < 2 * spacing].mean())
                       if "sdf" in arrays else None))
    else:
        from meshprep.solid import load_object_arrays

        v, f, info = load_object_arrays(in_path, scale=scale)
        arrays = object_proxy_arrays(v, f, density=density, samples=samples, seed=seed,
                                     where=str(in_path))
        arrays["scale"] = np.float64(scale)
        rep.update(repair=info, volume=arrays["volume"], mass=arrays["mass"], com=arrays["com"],
                   inertia=arrays["inertia"], hull_faces=int(len(arrays["hull_faces"])),
                   convex_parts=int(len(arrays["parts_face_counts"])),
                   hull_concavity=arrays["hull_concavity"], samples=samples)
    save_npz(out_path, arrays)
    rep.update(ok=True, seconds=round(time.perf_counter() - t0, 3))
    write_json(Path(report) if report else out_path.with_name(out_path.name + ".report.json"), rep)
    return rep
