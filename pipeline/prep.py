"""The prep stage: collision proxies for physics and a traceable room mesh, made with meshprep.

Items: ``<scene>/room`` per scene and ``objects`` once. Outputs:

- ``RUN/prep/<scene>/room_proxy.npz``: meshprep's room distance grid (``origin``, ``spacing``,
  ``udf``; ``sdf``/``sdf_valid`` where the cameras make a sign reliable) plus the room surface
  ``mesh_vertices`` (V, 3) float32 / ``mesh_faces`` (T, 3) int32 for exact contact distances;
- ``RUN/prep/<scene>/room_trace.ply``: the room simplified within ``prep.room_max_error``;
- ``RUN/prep/objects/obj_<id>.npz``: meshprep's object proxy (hull, parts, samples, ``mass``, ``com``,
  ``inertia`` at ``prep.density``; ``repair``: what it took). A model that is not a closed solid as
  given is repaired by meshprep (``kind="object"``) for its mass properties; only one the repair cannot
  close falls back to the mass properties of its convex hull (``fallback_hull = 1``, logged).
"""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import numpy as np

from pipeline.io import atomic_save_npz, atomic_write_bytes
from pipeline.runfolder import (OBJECT_PROXY_TPATH, ROOM_PROXY_TPATH, ROOM_TRACE_TPATH, list_scenes, load_objects,
                                load_room_mesh, load_scan, path)
from pipeline.stages import Item, Stage, StageContext

log = logging.getLogger(__name__)


def hull_proxy(vertices: np.ndarray, faces: np.ndarray, density: float) -> dict[str, np.ndarray]:
    """Fallback object proxy from the convex hull (for meshes meshprep cannot close)."""
    import trimesh

    hull = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces)).convex_hull
    mp = hull.mass_properties
    return {"hull_vertices": np.asarray(hull.vertices, float), "hull_faces": np.asarray(hull.faces, np.int32),
            "volume": np.float64(mp["volume"]), "mass": np.float64(mp["volume"] * density),
            "density": np.float64(density), "com": np.asarray(mp["center_mass"], float),
            "inertia": np.asarray(mp["inertia"], float) * density, "fallback_hull": np.int32(1)}


def object_proxy(vertices: np.ndarray, faces: np.ndarray, density: float,
                 where: str = "mesh") -> dict[str, np.ndarray]:
    """meshprep's object proxy of a mesh, repairing it into a closed solid first where it is not one.

    A model as given is used when meshprep can make a solid of it. Otherwise meshprep's repair
    (``kind="object"``: coherent orientation, non-manifold edges, holes, ...) runs on it and the proxy is
    made from the repaired mesh; the mesh that is rendered and annotated stays the model as given. Only
    when the repair cannot close it does :func:`hull_proxy` give the convex hull's mass properties.
    The key ``repair`` (a one-line ``str`` array) says what it took: ``"none"``, the repair steps, or why
    the hull was used; it is logged too.
    """
    from meshprep.errors import MeshprepError
    from meshprep.proxy import object_proxy_arrays

    try:
        out = object_proxy_arrays(vertices, faces, density=density, where=where)
        out["fallback_hull"] = np.int32(0)
        out["repair"] = np.array("none")
        return out
    except (MeshprepError, ValueError, RuntimeError) as e:
        first = str(e)
    from meshprep.inspect import inspect_arrays
    from meshprep.io import arrays_of, meshset_from_arrays
    from meshprep.repair import check_repaired, repair_meshset

    try:
        ms = meshset_from_arrays(vertices, faces)
        info = repair_meshset(ms, kind="object")
        v, f = arrays_of(ms)
        check_repaired(inspect_arrays(v, f, self_intersections=False), "object", where)
        out = object_proxy_arrays(v, f, density=density, where=where)
    except (MeshprepError, ValueError, RuntimeError) as e:
        log.warning("%s: meshprep could not make a solid (%s), nor repair it into one (%s); using the "
                    "convex hull's mass properties", where, first, e)
        out = hull_proxy(vertices, faces, density)
        out["repair"] = np.array(f"convex hull: {e}")
        return out
    steps = "; ".join(_step_text(c) for c in info["changes"]) or "no change"
    log.info("%s: not a closed solid as given (%s); meshprep repair: %s -> solid of %.1f cm^3",
             where, first, steps, float(out["volume"]) * 1e6)
    out["fallback_hull"] = np.int32(0)
    out["repair"] = np.array(f"repaired: {steps}")
    return out


def _step_text(change: dict) -> str:
    """``"orient faces coherently (faces_flipped 7)"`` from a meshprep repair change record."""
    extra = ", ".join(f"{k} {v}" for k, v in change.items() if k != "step" and v)
    return f"{change['step']} ({extra})" if extra else change["step"]


def plan(ctx: StageContext) -> list[Item]:
    return [Item(key=f"{s}/room", data={"scene": s}) for s in list_scenes(ctx.run_dir)] + \
        [Item(key="objects", data={})]


def run_item(ctx: StageContext, item: Item) -> dict:
    cfg = ctx.cfg.prep
    if item.key == "objects":
        out = {}
        for obj in load_objects(ctx.run_dir):
            pr = object_proxy(obj.vertices, obj.faces, cfg.density, where=f"object {obj.obj_id} ({obj.name})")
            atomic_save_npz(path(ctx.run_dir, OBJECT_PROXY_TPATH, obj_id=obj.obj_id), **pr)
            out[str(obj.obj_id)] = {"mass": float(pr["mass"]), "fallback_hull": int(pr["fallback_hull"]),
                                    "repair": str(pr["repair"])}
        return {"objects": out}
    from meshprep.proxy import room_distance_grid
    from meshprep.simplify import simplify

    scene = item.data["scene"]
    scan = load_scan(ctx.run_dir, scene)
    v, f, _ = load_room_mesh(scan)
    grid = room_distance_grid(v, f, spacing=cfg.room_spacing, cameras=scan.T_c2w[:, :3, 3], seed=0)
    # the surface itself: physics measures contacts exactly against it (the grid is the broad phase)
    grid["mesh_vertices"] = np.asarray(v, np.float32)
    grid["mesh_faces"] = np.asarray(f, np.int32)
    atomic_save_npz(path(ctx.run_dir, ROOM_PROXY_TPATH, scene=scene), **grid)
    trace = path(ctx.run_dir, ROOM_TRACE_TPATH, scene=scene)
    # meshprep writes its report (with timings) beside its output: keep both out of the run folder, so
    # the run's files are the same bytes every time, and move the mesh in atomically.
    with tempfile.TemporaryDirectory(prefix="scansynth-prep-") as tmpdir:
        tmp = Path(tmpdir) / "room_trace.ply"
        rep = simplify(scan.mesh_path, tmp, max_error=cfg.room_max_error, report=Path(tmpdir) / "report.json")
        atomic_write_bytes(trace, tmp.read_bytes())
    return {"scene": scene, "grid": list(grid["udf"].shape), "trace_faces": rep.get("after", {}).get("faces")}


STAGE = Stage("prep", plan, run_item)
