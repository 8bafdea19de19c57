"""Raster benchmark: milliseconds per frame for all raster passes, and clipping with/without fusion.

Run: ``nice .venv/bin/python -m bench.raster [--frames N]``. Writes bench/results/raster.json + .png.

Setup (everything measured in this run, on this machine):

- A synthetic scan from :mod:`pipeline.synthscan` (7-Scenes layout, 640x480): its sensor-like depth
  maps (noise, holes, mm quantisation) are the "real" depth; its scanner mesh (thin parts such as
  table and chair legs partly missing) is the room mesh; its true geometry is the truth.
- 10 objects per frame (LM-O models from ../shared/data when present, else the built-in shapes),
  half of them placed on the floor just behind a thin part seen by the camera (where clipping
  happens), the others on the floor in view.
- Speed: :func:`pipeline.raster.render_frame` (object passes, composition, occlusion, fusion,
  annotations) with the room depth read from the on-disk cache as the stage does, and the real depth
  read from its PNG; the room mesh subdivided to ~200k faces (geometry unchanged). Also with the room
  depth rendered each frame (no cache), and the baseline: the same passes by Open3D ray casting.
- Accuracy (y axis): mean per-instance visible-mask IoU against the visibility from the TRUE geometry.
  Clipped-pixel share: pixels annotated visible that the true geometry hides (the object looks as if
  drawn through a chair leg), over all pixels annotated visible; with and without real-depth fusion.
"""

from __future__ import annotations

import argparse
import json
import os
import logging
import time
from pathlib import Path

import numpy as np

from bench.common import SHARED_DATA, BenchResult

CACHE = Path(__file__).resolve().parents[1] / ".cache" / "bench-raster"
log = logging.getLogger("bench.raster")


def _read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.load(str(path), process=False, force="mesh")
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int32)


def _subdivide_to(v: np.ndarray, f: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint-subdivide faces (geometry unchanged) until the mesh has about ``target`` faces."""
    import trimesh.remesh

    while len(f) * 4 <= target:
        v, f = trimesh.remesh.subdivide(v, f)
    extra = (target - len(f)) // 3
    if extra > 0:
        v, f = trimesh.remesh.subdivide(v, f, face_index=np.arange(extra))
    return np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int32)


def _objects():
    from pipeline.objects import builtin_shapes, load_library

    lmo = SHARED_DATA / "objects" / "lmo" / "models"
    if lmo.is_dir():
        return load_library([str(lmo)]), "LM-O (../shared/data/objects/lmo)"
    return builtin_shapes(), "built-in shapes"


def _placement(rng, objects, K, T_c2w, width, height, true_depth, thin_parts, up, floor_h):
    """10 instances: 5 just behind thin parts seen by the camera, 5 on the floor in view."""
    from scipy.spatial.transform import Rotation

    from pipeline.types import Placement

    T_w2c = np.linalg.inv(T_c2w)
    eye = T_c2w[:3, 3]
    anchors = []
    for tp in thin_parts:
        c = (np.asarray(tp["bbox_min"]) + np.asarray(tp["bbox_max"])) / 2
        pc = T_w2c[:3, :3] @ c + T_w2c[:3, 3]
        if pc[2] > 0.3 and 0 <= K[0, 0] * pc[0] / pc[2] + K[0, 2] < width \
                and 0 <= K[1, 1] * pc[1] / pc[2] + K[1, 2] < height:
            anchors.append(c)
    ys, xs = np.nonzero(true_depth > 0)
    pts = []
    for k in range(10):
        obj = objects[rng.integers(len(objects))]
        r = float(obj.info.get("diameter", 0.1)) / 2
        if k < 5 and anchors:
            c = anchors[k % len(anchors)]
            d = c - eye
            d -= (d @ up) * up
            d /= np.linalg.norm(d)
            p = c + d * rng.uniform(0.08, 0.25) + np.cross(up, d) * rng.uniform(-0.08, 0.08)
        else:
            i = rng.integers(len(xs))
            z = true_depth[ys[i], xs[i]]
            pc = np.array([(xs[i] - K[0, 2]) / K[0, 0] * z, (ys[i] - K[1, 2]) / K[1, 1] * z, z])
            p = T_c2w[:3, :3] @ pc + eye
        p = p - (p @ up - (floor_h + r * 0.6)) * up  # on the floor, partly sunk like a resting object
        pts.append((obj.obj_id, Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), p))
    n = len(pts)
    return Placement(scene="bench", drop=0, obj_ids=np.array([p[0] for p in pts], np.int32),
                     R_m2w=np.array([p[1] for p in pts]), t_m2w=np.array([p[2] for p in pts]),
                     at_rest=np.ones(n, bool), max_penetration=0.0, verdict="accepted")


def _raycast_frame(objects_by_id, placement, room, K, T_c2w, width, height):
    """Baseline: every raster pass by Open3D ray casting (room, each instance alone, all together)."""
    from tests.support.reference import raycast

    posed = []
    for oid, R, t in zip(placement.obj_ids, placement.R_m2w, placement.t_m2w):
        o = objects_by_id[int(oid)]
        posed.append((o.vertices @ R.T + t, o.faces))
    amodal = [raycast([m], K, T_c2w, width, height)[1] == 0 for m in posed]
    depth, idx = raycast([room] + posed, K, T_c2w, width, height)
    return idx, amodal


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=12, help="frames of the synthetic scan to measure")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    import cv2

    from pipeline import annotate
    from pipeline.config import RasterConfig
    from pipeline.io import atomic_save_npz, load_npz
    from pipeline.raster import ensure_objects, render_frame
    from pipeline.render_gl import MeshRasterizer
    from pipeline.synthscan import make_scan
    from tests.support.reference import iou

    W, H = 640, 480
    scan_dir = CACHE / f"synth-seed{args.seed}-{args.frames}"
    if not (scan_dir / "ground_truth" / "scan.json").is_file():
        t = time.perf_counter()
        make_scan(scan_dir, layout="7scenes", seed=args.seed, width=W, height=H, frames=args.frames)
        log.info("synthetic scan made in %.1f s", time.perf_counter() - t)
    gt = json.loads((scan_dir / "ground_truth" / "scan.json").read_text())
    cams = load_npz(scan_dir / "ground_truth" / "cameras.npz")
    K = np.asarray(cams["K"], dtype=np.float64)
    Ts = cams["T_c2w"]
    valid = cams["pose_valid"]
    up = np.asarray(gt["up_w"], dtype=np.float64)
    thin = json.loads((scan_dir / "ground_truth" / "thin_parts.json").read_text())["thin_parts"]
    true_mesh = _read_mesh(scan_dir / "ground_truth" / "mesh.ply")
    scan_mesh = _read_mesh(scan_dir / "ground_truth" / "scan_mesh.ply")
    floor_h = float(np.percentile(true_mesh[0] @ up, 0.5))
    room200k = _subdivide_to(*scan_mesh, 200_000)
    objects, obj_source = _objects()
    by_id = {o.obj_id: o for o in objects}

    r = MeshRasterizer()
    keys = ensure_objects(r, objects)
    r.add_mesh("truth", *true_mesh)
    r.add_mesh("scan", *scan_mesh)
    r.add_mesh("room200k", *room200k)
    rng = np.random.default_rng(args.seed)
    cfg_fused = RasterConfig(min_visible_area=0.0)
    cfg_plain = RasterConfig(min_visible_area=0.0, real_depth_fusion=False)

    t_cached, t_fused, t_uncached, t_ray = [], [], [], []
    cpu_fused = []
    breakdown = {"objects_ms": [], "room_cache_load_ms": [], "real_depth_read_ms": []}
    iou_truth = {"mesh": [], "fused": []}
    iou_vs_ray, amodal_vs_ray = [], []
    clipped = {"mesh": [0, 0], "fused": [0, 0]}       # [false-visible px, annotated-visible px]
    hidden_wrong = {"mesh": 0, "fused": 0}
    residual = {"real_invalid": 0, "within_tolerance": 0}  # why fused frames still clip
    TOLS = (0.005, 0.01, 0.02, 0.04, 0.08)
    sweep = {t: [0, 0, 0] for t in TOLS}  # tol_abs -> [false-visible px, annotated-visible px, false-hidden px]
    truly_visible = 0
    frames_used = 0
    for i in np.flatnonzero(valid):
        T = Ts[i]
        true_depth = r.render_depth(K, T, W, H, [("truth", np.eye(4))])
        pl = _placement(rng, objects, K, T, W, H, true_depth, thin, up, floor_h)
        cache = CACHE / "scene_depth" / f"f{i:06d}.npz"
        atomic_save_npz(cache, depth=r.render_depth(K, T, W, H, [("room200k", np.eye(4))]))
        dpath = scan_dir / gt["frames_info"][i]["depth"]
        real_m = lambda: cv2.imread(str(dpath), cv2.IMREAD_UNCHANGED).astype(np.float32) * 0.001  # noqa: E731
        # The stage decodes each frame's sensor depth once and caches it for every drop (as here).
        real_cache = CACHE / "real_depth" / f"f{i:06d}.npz"
        atomic_save_npz(real_cache, depth=real_m())

        def cached_room():
            t0 = time.perf_counter()
            d = load_npz(cache)["depth"]
            breakdown["room_cache_load_ms"].append((time.perf_counter() - t0) * 1e3)
            return d

        def timed_real():
            t0 = time.perf_counter()
            d = load_npz(real_cache)["depth"]
            breakdown["real_depth_read_ms"].append((time.perf_counter() - t0) * 1e3)
            return d

        # speed: cached room depth, with and without fusion; and the room rendered every frame
        t0 = time.perf_counter()
        res_plain = render_frame(r, K=K, T_c2w=T, width=W, height=H, placement=pl, mesh_keys=keys,
                                 scene_depth=cached_room, real_depth=timed_real, cfg=cfg_plain)
        t_cached.append((time.perf_counter() - t0) * 1e3)
        t0, c0 = time.perf_counter(), time.process_time()
        res_fused = render_frame(r, K=K, T_c2w=T, width=W, height=H, placement=pl, mesh_keys=keys,
                                 scene_depth=cached_room, real_depth=timed_real, cfg=cfg_fused)
        t_fused.append((time.perf_counter() - t0) * 1e3)
        cpu_fused.append((time.process_time() - c0) * 1e3)
        t0 = time.perf_counter()
        render_frame(r, K=K, T_c2w=T, width=W, height=H, placement=pl, mesh_keys=keys,
                     scene_depth=lambda: r.render_depth(K, T, W, H, [("room200k", np.eye(4))]),
                     real_depth=real_m, cfg=cfg_fused)
        t_uncached.append((time.perf_counter() - t0) * 1e3)
        breakdown["objects_ms"].append(t_cached[-1] - breakdown["room_cache_load_ms"][-1])
        if res_plain.status != "ok" or not (res_plain.labels > 0).any():
            continue
        frames_used += 1
        # truth: the same object passes, occluded by the true geometry
        vis_true = annotate.visible_labels(res_plain.depth, res_plain.front, true_depth, None,
                                           tol_abs=0.0, tol_rel=0.0).labels
        truly_visible += int((vis_true > 0).sum())
        real_now = real_m()
        room_now = load_npz(cache)["depth"]
        for tol in TOLS:
            lab = annotate.visible_labels(res_plain.depth, res_plain.front, room_now, real_now, tol_abs=tol,
                                          tol_rel=cfg_fused.fusion_tol_rel).labels
            sweep[tol][0] += int(((lab > 0) & (vis_true == 0)).sum())
            sweep[tol][1] += int((lab > 0).sum())
            sweep[tol][2] += int(((lab == 0) & (vis_true > 0)).sum())
        still = (res_fused.labels > 0) & (vis_true == 0)
        residual["real_invalid"] += int((still & (real_now == 0)).sum())
        residual["within_tolerance"] += int((still & (real_now > 0)).sum())
        for name, res in (("mesh", res_plain), ("fused", res_fused)):
            lab = res.labels
            clipped[name][0] += int(((lab > 0) & (vis_true == 0)).sum())
            clipped[name][1] += int((lab > 0).sum())
            hidden_wrong[name] += int(((lab == 0) & (vis_true > 0)).sum())
            for k in range(len(pl.obj_ids)):
                if (vis_true == k + 1).sum() >= 50 or (lab == k + 1).sum() >= 50:
                    iou_truth[name].append(iou(lab == k + 1, vis_true == k + 1))
        # baseline: Open3D ray casting of the same passes (scan mesh as room), on a few frames
        if len(t_ray) < 3:
            t0 = time.perf_counter()
            idx, amodal = _raycast_frame(by_id, pl, room200k, K, T, W, H)
            t_ray.append((time.perf_counter() - t0) * 1e3)
            for k in range(len(pl.obj_ids)):
                if (idx == k + 1).sum() >= 50:
                    iou_vs_ray.append(iou(res_plain.labels == k + 1, idx == k + 1))
                if amodal[k].sum() >= 50:
                    amodal_vs_ray.append(iou(res_plain.amodal[k], amodal[k]))

    # Same frames with the built-in procedural shapes (few triangles): where the time goes with light meshes.
    from pipeline.objects import builtin_shapes

    shapes = builtin_shapes()
    skeys = ensure_objects(r, shapes)
    t_shapes, cpu_shapes = [], []
    tri_lmo = float(np.mean([len(o.faces) for o in objects]))
    for i in np.flatnonzero(valid):
        T = Ts[i]
        true_depth = r.render_depth(K, T, W, H, [("truth", np.eye(4))])
        pl = _placement(rng, shapes, K, T, W, H, true_depth, thin, up, floor_h)
        cache = CACHE / "scene_depth" / f"f{i:06d}.npz"
        dpath = scan_dir / gt["frames_info"][i]["depth"]
        t0, c0 = time.perf_counter(), time.process_time()
        render_frame(r, K=K, T_c2w=T, width=W, height=H, placement=pl, mesh_keys=skeys,
                     scene_depth=lambda: load_npz(cache)["depth"],
                     real_depth=lambda: cv2.imread(str(dpath), cv2.IMREAD_UNCHANGED).astype(np.float32) * 0.001,
                     cfg=cfg_fused)
        t_shapes.append((time.perf_counter() - t0) * 1e3)
        cpu_shapes.append((time.process_time() - c0) * 1e3)

    med = lambda a: float(np.median(a)) if len(a) else float("nan")  # noqa: E731
    share = {k: v[0] / max(v[1], 1) for k, v in clipped.items()}
    res = BenchResult("raster", speed_label="ms per frame (640x480, 10 objects, median)",
                      accuracy_label="visible-mask IoU vs true geometry (mean per instance)")
    res.add_point("Open3D ray casting (baseline), scan mesh", speed=med(t_ray),
                  accuracy=float(np.mean(iou_truth["mesh"])), label="baseline", baseline=True)
    res.add_point("raster, occlusion by scan mesh only", speed=med(t_cached),
                  accuracy=float(np.mean(iou_truth["mesh"])), label="cached room")
    res.add_point("raster + real-depth fusion (default)", speed=med(t_fused),
                  accuracy=float(np.mean(iou_truth["fused"])), label="cached room")
    res.add_point("raster + real-depth fusion, room rendered per frame", speed=med(t_uncached),
                  accuracy=float(np.mean(iou_truth["fused"])), label="")
    res.figures.update({
        "object_triangles_mean_lmo": round(tri_lmo, 0),
        "object_triangles_mean_shapes": round(float(np.mean([len(o.faces) for o in shapes])), 0),
        "ms_per_frame_shapes_cached_fused_median": round(med(t_shapes), 2),
        "cpu_ms_per_frame_shapes_cached_fused_median": round(med(cpu_shapes), 2),
        "ms_per_frame_cached_fused_median": round(med(t_fused), 2),
        "ms_per_frame_cached_mesh_only_median": round(med(t_cached), 2),
        "cpu_ms_per_frame_cached_fused_median": round(med(cpu_fused), 2),
        "ms_per_frame_cached_fused_min": round(float(np.min(t_fused)), 2),
        "ms_per_frame_shapes_cached_fused_min": round(float(np.min(t_shapes)), 2),
        "load_average_1min_at_end": round(os.getloadavg()[0], 2),
        "ms_per_frame_uncached_fused_median": round(med(t_uncached), 2),
        "ms_per_frame_raycast_baseline_median": round(med(t_ray), 1),
        "speedup_vs_raycast": round(med(t_ray) / med(t_fused), 1),
        "target_ms": 60,
        "breakdown_median_ms": {k: round(med(v), 2) for k, v in breakdown.items()},
        "room_faces": int(len(room200k[1])), "room_faces_original": int(len(scan_mesh[1])),
        "objects": obj_source, "frames": frames_used, "width": W, "height": H,
        "clipped_pixel_share_mesh_only": round(share["mesh"], 4),
        "clipped_pixel_share_fused": round(share["fused"], 4),
        "clipped_px_mesh_only": clipped["mesh"][0], "clipped_px_fused": clipped["fused"][0],
        "clipped_px_fused_where_real_depth_invalid": residual["real_invalid"],
        "clipped_px_fused_where_real_depth_valid": residual["within_tolerance"],
        "fusion_tol_abs_sweep": {f"{t:g}": {"clipped_share": round(v[0] / max(v[1], 1), 4),
                                             "false_hidden_share": round(v[2] / max(truly_visible, 1), 4)}
                                 for t, v in sweep.items()},
        "fusion_tol_rel": cfg_fused.fusion_tol_rel,
        "false_hidden_share_mesh_only": round(hidden_wrong["mesh"] / max(truly_visible, 1), 4),
        "false_hidden_share_fused": round(hidden_wrong["fused"] / max(truly_visible, 1), 4),
        "iou_vs_truth_mesh_only": round(float(np.mean(iou_truth["mesh"])), 4),
        "iou_vs_truth_fused": round(float(np.mean(iou_truth["fused"])), 4),
        "visible_iou_vs_raycast_min": round(min(iou_vs_ray), 5) if iou_vs_ray else None,
        "amodal_iou_vs_raycast_min": round(min(amodal_vs_ray), 5) if amodal_vs_ray else None,
    })
    res.notes += [
        f"synthetic 7-Scenes-layout scan (pipeline.synthscan seed {args.seed}): sensor-like depth = real depth, "
        "scanner mesh (thin parts partly missing) = room mesh, true geometry = truth",
        "clipped-pixel share = pixels annotated visible that the true geometry hides / pixels annotated visible",
        "false-hidden share = truly visible pixels annotated hidden / truly visible pixels (what fusion costs)",
        "speed includes reading the cached room depth (NPZ) and the real depth PNG; machine shared by ~8 "
        "developers on 2 cores (see load_average_1min_at_end): wall times are inflated by the load, compare "
        "ratios within this run; cpu_ms is the process's CPU time (llvmpipe's 2 threads included)",
    ]
    jp, pp = res.write()
    log.info("%s", json.dumps(res.figures, indent=1))
    log.info("wrote %s and %s", jp, pp)
    r.release()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
