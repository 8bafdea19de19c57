"""Benchmark of the trace stage's core: RMSE against seconds per frame, with and without denoising.

A 640x480 frame of the real 7-Scenes "redkitchen" room (TSDF-reconstructed by pipeline.ingest from the
100 shared frames) with LM-O models placed in front of the camera (~30k object pixels, mm -> m by the
BOP loader). The reference is the same tracer at a high fixed sample count (its own noise is reported).
Each point renders AO + PBR at a fixed spp (adaptive stop off), plus the default TraceConfig quality;
"denoised" points add Intel Open Image Denoise (pyoidn) guided by albedo and normals.

The process is pinned to one core (os.sched_setaffinity), so seconds are single-core seconds. The
Embree-only time replays exactly the ray batches the default render cast (recorded by a wrapper around
the intersector) through the same Embree scene; the ratio tracer / Embree is reported beside it.

Run: ``.venv/bin/python -m bench.trace`` (add ``--quick`` for a smaller, faster run).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import SHARED_DATA, BenchResult

log = logging.getLogger("bench.trace")

LMO = SHARED_DATA / "objects" / "lmo" / "models"
SCAN = SHARED_DATA / "scans" / "7scenes-redkitchen"
OBJ_IDS = (5, 6, 8, 9)  # can, cat, driller, duck
TARGET_PX = 30_000


class RecordingIntersector:
    """Wraps an intersector and keeps every query, to replay it through Embree alone."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.num_triangles = inner.num_triangles
        self.calls: list[tuple] = []

    def intersect(self, origins, dirs, tmax=None):
        self.calls.append(("i", np.array(origins, np.float32), np.array(dirs, np.float32),
                           None if tmax is None else np.array(tmax, np.float32)))
        return self.inner.intersect(origins, dirs, tmax)

    def occluded(self, origins, dirs, tmax):
        self.calls.append(("o", np.array(origins, np.float32), np.array(dirs, np.float32), np.array(tmax, np.float32)))
        return self.inner.occluded(origins, dirs, tmax)


def replay_seconds(inner, calls) -> tuple[float, int]:
    t0 = time.process_time()
    n = 0
    for kind, o, d, t in calls:
        if kind == "i":
            inner.intersect(o, d, t)
        else:
            inner.occluded(o, d, t)
        n += o.shape[0]
    return time.process_time() - t0, n


def room_mesh(work: Path):
    from pipeline.config import build_config
    from pipeline.ingest import ingest_scan
    from pipeline.runfolder import load_room_mesh

    scan = ingest_scan(SCAN, "redkitchen", work / "ingest" / "redkitchen", build_config({}))
    v, f, c = load_room_mesh(scan)
    return scan, v, f, c


def place_objects(scan, frame: int, models, scene_builder, rng):
    """Poses in front of the camera of ``frame``, scaled in depth to cover about TARGET_PX pixels."""
    from pipeline.trace.scene import instance_from_model

    T = scan.T_c2w[frame]
    offsets = np.array([[-0.16, 0.04, 0.0], [-0.05, 0.07, 0.06], [0.06, 0.03, -0.02], [0.16, 0.06, 0.04]])

    def instances(z):
        out = []
        for m, off in zip(models, offsets):
            q = rng_rot(rng_seed=m.obj_id)
            c = np.asarray(m.vertices).mean(axis=0)
            p_cam = np.array([off[0] * z / 0.7, off[1] * z / 0.7, z + off[2]])
            R = T[:3, :3] @ q
            t = T[:3, :3] @ p_cam + T[:3, 3] - R @ c
            out.append(instance_from_model(m, R, t))
        return out

    return instances


def rng_rot(rng_seed: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=np.random.default_rng(rng_seed)).as_matrix()


def labels_of(scene, cam) -> np.ndarray:

    n = cam.width * cam.height
    o, d = cam.rays(np.arange(n), np.full((n, 2), 0.5))
    h = scene.intersector.intersect(o, d)
    return np.where(h.hit, scene.tri_inst[np.maximum(h.prim, 0)], 0).astype(np.uint16).reshape(cam.height, cam.width)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer points and a lower reference spp")
    ap.add_argument("--frame", type=int, default=20)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

    from pipeline.config import TraceConfig
    from pipeline.objects import load_library
    from pipeline.trace.denoise import denoise, oidn_available
    from pipeline.camera import Camera
    from pipeline.trace.pbr import render, trace_mask
    from pipeline.trace.scene import build_scene
    from pipeline.trace.stage import settings_from_config

    res = BenchResult("trace", speed_label="CPU seconds per frame (AO + PBR, one core)",
                      accuracy_label="relative RMSE over object pixels vs reference", lower_is_better=True)
    with tempfile.TemporaryDirectory(prefix="bench-trace-") as tmp:
        t0 = time.perf_counter()
        scan, rv, rf, rc = room_mesh(Path(tmp))
        res.figures["room_triangles"] = int(len(rf))
        res.figures["room_reconstruct_seconds"] = round(time.perf_counter() - t0, 1)
    models = {m.obj_id: m for m in load_library([str(LMO)])}
    models = [models[i] for i in OBJ_IDS]
    frame = args.frame
    cam = Camera(K=scan.K[frame], T_c2w=scan.T_c2w[frame], width=scan.width, height=scan.height)
    make = place_objects(scan, frame, models, None, None)
    z = 0.7
    for _ in range(3):
        sc = build_scene(rv, rf, rc, make(z), up=scan.up_w)
        npx = int((labels_of(sc, cam) > 0).sum())
        z *= float(np.sqrt(max(npx, 1) / TARGET_PX))
    t0 = time.perf_counter()
    sc = build_scene(rv, rf, rc, make(z), up=scan.up_w)
    build_s = time.perf_counter() - t0
    labels = labels_of(sc, cam)
    mask = trace_mask(labels, 1)
    res.figures.update({"object_px": int((labels > 0).sum()), "traced_px": int(mask.sum()),
                        "object_depth_m": round(z, 3), "scene_build_seconds": round(build_s, 3),
                        "area_lights": sc.area_lights.count, "frame": frame})
    log.info("frame %d: %d object pixels at %.2f m, scene build %.2f s, %d clipped light triangles",
             frame, res.figures["object_px"], z, build_s, sc.area_lights.count)

    default = settings_from_config(TraceConfig())
    ref_spp = 64 if args.quick else 256
    ref_set = dataclasses.replace(default, spp=ref_spp, spp_min=ref_spp, spp_batch=8, noise_target=0.0)
    t0 = time.perf_counter()
    refs = [render(sc, cam, mask, ref_set, np.random.default_rng(100 + k)) for k in range(2)]
    ref_s = time.perf_counter() - t0
    ref_pbr = 0.5 * (refs[0].pbr + refs[1].pbr)
    inner = refs[0].coverage >= 1.0
    scale = float(ref_pbr[inner].mean())

    def rel_rmse(img):
        return float(np.sqrt(np.mean((img[inner] - ref_pbr[inner]) ** 2)) / scale)

    # noise of the reference itself: half the RMSE between two independent halves
    res.figures["reference_spp"] = 2 * ref_spp
    res.figures["reference_rel_rmse_estimate"] = round(rel_rmse(refs[0].pbr) / np.sqrt(2) / np.sqrt(2), 5)
    res.figures["reference_seconds"] = round(ref_s, 1)
    log.info("reference: 2 x %d spp in %.1f s", ref_spp, ref_s)

    use_oidn = oidn_available()
    sweep = (1, 2, 4, 8) if args.quick else (1, 2, 4, 8, 16, 32)
    for spp in sweep:
        s = dataclasses.replace(default, spp=spp, spp_min=spp, spp_batch=min(4, spp), noise_target=0.0)
        t0 = time.process_time()
        fb = render(sc, cam, mask, s, np.random.default_rng(spp))
        sec = time.process_time() - t0
        res.add_point("raw", speed=sec, accuracy=rel_rmse(fb.pbr), label=f"{spp} spp", spp=spp, rays=fb.rays)
        if use_oidn:
            t0 = time.process_time()
            dn = denoise(fb.pbr, fb.albedo, fb.normal, fb.coverage > 0, method="oidn")
            dsec = time.process_time() - t0
            res.add_point("denoised (OIDN)", speed=sec + dsec, accuracy=rel_rmse(dn), label=f"{spp} spp", spp=spp,
                          denoise_seconds=dsec)
        log.info("%3d spp: %.2f s, rel RMSE %.4f", spp, sec, res.series["raw"][-1]["accuracy"])

    # the default quality (adaptive), with the ray batches recorded for the Embree-only replay
    rec = RecordingIntersector(sc.intersector)
    sc_rec = dataclasses.replace(sc, intersector=rec)
    t0, w0 = time.process_time(), time.perf_counter()
    fb = render(sc, cam, mask, default, np.random.default_rng(7))
    sec, wall = time.process_time() - t0, time.perf_counter() - w0
    fb_rec = render(sc_rec, cam, mask, default, np.random.default_rng(7))
    emb_s, emb_rays = replay_seconds(sc.intersector, rec.calls)
    assert np.array_equal(fb.pbr, fb_rec.pbr)
    res.add_point("default config", speed=sec, accuracy=rel_rmse(fb.pbr), label="default", baseline=True)
    res.figures.update({
        "default_seconds_per_frame": round(sec, 3),
        "default_wall_seconds_per_frame": round(wall, 3),
        "default_rel_rmse": round(rel_rmse(fb.pbr), 5),
        "default_mean_spp": round(float(fb.spp[mask].mean()), 2),
        "default_rays": int(fb.rays),
        "embree_only_cpu_seconds": round(emb_s, 3),
        "embree_only_rays_per_second": round(emb_rays / emb_s),
        "tracer_over_embree_ratio": round(sec / emb_s, 2),
        "default_settings": dataclasses.asdict(default),
    })
    if use_oidn:
        t0 = time.process_time()
        dn = denoise(fb.pbr, fb.albedo, fb.normal, fb.coverage > 0, method="oidn")
        dsec = time.process_time() - t0
        res.add_point("default config + OIDN", speed=sec + dsec, accuracy=rel_rmse(dn), label="default+oidn")
        res.figures["default_oidn_rel_rmse"] = round(rel_rmse(dn), 5)
        res.figures["oidn_seconds"] = round(dsec, 3)
    # the rest of a stage frame: the shadow-ratio pass at the default settings (its own intersectors)
    from pipeline.trace.shadow import shadow_ratio, split_intersectors

    cfg = TraceConfig()
    t0 = time.process_time()
    room_i, obj_i = split_intersectors(sc)
    split_s = time.process_time() - t0
    t0 = time.process_time()
    sr = shadow_ratio(sc, cam, labels, np.random.default_rng(3), samples=cfg.shadow_samples,
                      min_effect=cfg.shadow_min_effect, stride=cfg.shadow_stride, smooth=cfg.shadow_smooth,
                      room_isect=room_i, obj_isect=obj_i)
    shadow_s = time.process_time() - t0
    res.figures.update({"shadow_cpu_seconds": round(shadow_s, 3), "shadow_px_below_0.99": int((sr < 0.99).sum()),
                        "split_intersectors_cpu_seconds": round(split_s, 3)})
    log.info("shadow ratio: %.2f s CPU, %d pixels below 0.99", shadow_s, int((sr < 0.99).sum()))
    res.notes += [
        "shadow_cpu_seconds: the shadow-ratio pass of one frame at the default TraceConfig (not in the "
        "AO + PBR figure); split_intersectors_cpu_seconds: its room-only/object-only Embree scenes, "
        "built once per drop by the stage",
    ]
    res.notes += [
        "seconds: CPU time (time.process_time) of pipeline.trace.pbr.render (AO + PBR) with the process "
        "pinned to one core; CPU time, not wall time, because the 2-core machine is shared and wall time "
        "mostly measures the other users; the default point also reports its wall time",
        "OIDN points add the denoiser's CPU time (OIDN is limited to the same core)",
        "reference: the same tracer, two independent renders at reference_spp/2 spp each, averaged",
        "scene_build_seconds (Embree BVH of room + objects) is per drop and not in seconds per frame",
        "embree_only_seconds: the default render's recorded ray batches replayed through the same Embree "
        "scene (includes embreex's Python call overhead, excludes all shading); ratio = tracer CPU seconds / "
        "Embree-only CPU seconds",
    ]
    log.info("default: %.2f s/frame, rel RMSE %.4f, tracer/Embree = %.2f", sec, rel_rmse(fb.pbr),
             sec / emb_s)
    j, p = res.write()
    log.info("wrote %s and %s", j, p)


if __name__ == "__main__":
    main()
