"""Benchmark: ingest of the real 7-Scenes sample with TSDF reconstruction.

For each voxel size, the whole scan item is ingested (read + validate 100 frames, TSDF fusion, up
direction, writing scan.json/frames.npz/room.ply) and timed; then the reconstructed mesh's depth is
rendered (Open3D ray casting) at every frame's pose and compared with the real depth map where both are
valid: median and 90th percentile absolute difference. Baseline: 2 cm voxels (the default), measured in
the same run. Targets (issue 3): median <= 1.5 cm, ingest <= 30 s for the 100 frames.

Run: ``nice .venv/bin/python -m bench.ingest`` (writes bench/results/ingest.json and .png).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import SHARED_DATA, BenchResult

VOXELS_M = (0.01, 0.015, 0.02, 0.03)
BASELINE_M = 0.02
REPEATS = 2
TRUNC_VOXELS = 4.0  # truncation = 4 voxels, as the default config (2 cm / 8 cm)


def measure(scan_dir: Path, voxel: float, work: Path) -> dict:
    from pipeline.config import build_config
    from pipeline.ingest import ingest_scan
    from pipeline.runfolder import load_room_mesh
    from pipeline.scanformats.common import read_depth
    from tests.support.reference import raycast

    cfg = build_config({"scan": {"paths": [str(scan_dir)]},
                        "ingest": {"tsdf_voxel": voxel, "tsdf_trunc": TRUNC_VOXELS * voxel}})
    seconds, cpu = [], []
    for rep in range(REPEATS):  # the machine is shared: keep the least disturbed of a few runs
        t0, c0 = time.perf_counter(), time.process_time()
        scan = ingest_scan(scan_dir, "kitchen", work / f"v{voxel:.3f}-{rep}", cfg)
        seconds.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    seconds, cpu = min(seconds), min(cpu)
    V, F, _ = load_room_mesh(scan)
    diffs, valid, covered = [], 0, 0
    for i in range(scan.num_frames):
        real = read_depth(scan, i)
        mesh = raycast([(V, F)], scan.K[i], scan.T_c2w[i], scan.width, scan.height)[0]
        ok_real = (real > 0) & (real <= cfg.ingest.depth_max)
        both = ok_real & (mesh > 0)
        valid += int(ok_real.sum())
        covered += int(both.sum())
        diffs.append(np.abs(mesh[both] - real[both]))
    d = np.concatenate(diffs)
    return {"voxel_m": voxel, "seconds": seconds, "cpu_seconds": cpu, "median_m": float(np.median(d)),
            "p90_m": float(np.percentile(d, 90)), "coverage": covered / max(valid, 1),
            "frames": scan.num_frames, "faces": int(len(F)),
            "up_vs_floor_deg": scan.meta["up"].get("metadata_vs_floor_deg")}


def main() -> int:
    scan_dir = SHARED_DATA / "scans" / "7scenes-redkitchen"
    if not scan_dir.is_dir():
        print(f"bench.ingest: {scan_dir} is absent; nothing to measure", file=sys.stderr)
        return 1
    res = BenchResult("ingest", speed_label="ingest CPU seconds, all threads (100 frames, incl. TSDF)",
                      accuracy_label="|rendered mesh depth - real depth| (cm)", lower_is_better=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        # import cost (open3d, cv2) paid once before timing, so the first setting is not penalised
        from meshprep.metrics import open3d_module

        open3d_module()
        for v in VOXELS_M:
            r = measure(scan_dir, v, Path(tmp))
            rows.append(r)
            print(f"voxel {v * 100:.1f} cm: {r['seconds']:.1f} s ({r['cpu_seconds']:.1f} s CPU), median {r['median_m'] * 100:.2f} cm, "
                  f"p90 {r['p90_m'] * 100:.2f} cm, coverage {r['coverage']:.3f}, {r['faces']} faces",
                  file=sys.stderr)
    base = next(r for r in rows if r["voxel_m"] == BASELINE_M)
    for r in rows:
        lab = f"{r['voxel_m'] * 100:g} cm"
        extra = {"voxel_m": r["voxel_m"], "faces": r["faces"], "cpu_seconds": round(r["cpu_seconds"], 2), "coverage": round(r["coverage"], 4),
                 "seconds_ratio_to_baseline": round(r["seconds"] / base["seconds"], 3),
                 "cpu_ratio_to_baseline": round(r["cpu_seconds"] / base["cpu_seconds"], 3),
                 "median_ratio_to_baseline": round(r["median_m"] / base["median_m"], 3)}
        is_base = r["voxel_m"] == BASELINE_M
        extra["wall_seconds"] = round(r["seconds"], 2)
        res.add_point("median", speed=r["cpu_seconds"], accuracy=r["median_m"] * 100, label=lab,
                      baseline=is_base, **extra)
        res.add_point("p90", speed=r["cpu_seconds"], accuracy=r["p90_m"] * 100, label=lab, **extra)
    res.figures.update({
        "default_voxel_m": BASELINE_M,
        "default_median_cm": round(base["median_m"] * 100, 3),
        "default_p90_cm": round(base["p90_m"] * 100, 3),
        "default_ingest_seconds": round(base["seconds"], 2),
        "default_ingest_cpu_seconds": round(base["cpu_seconds"], 2),
        "default_coverage": round(base["coverage"], 4),
        "up_metadata_vs_floor_deg": round(base["up_vs_floor_deg"], 3),
        "target_median_cm": 1.5, "target_seconds": 30.0,
        "meets_median_target": base["median_m"] * 100 <= 1.5,
        "meets_time_target": base["seconds"] <= 30.0,
        "frames": base["frames"],
    })
    res.notes += [
        "x axis: process CPU seconds (least of 2 runs); wall seconds are in each point's wall_seconds "
        "and in the figures (the 30 s target is wall time).",
        "Each point: one full ingest of the scan item (read + validate 100 frames, TSDF fusion with Open3D "
        "0.19 ScalableTSDFVolume, floor/up, writing outputs), truncation = 4 voxels.",
        "Accuracy: the reconstructed mesh's depth ray-cast at each of the 100 frames' poses vs the real "
        "Kinect depth, over pixels valid in both (real depth <= 4 m); the mesh is fused from the same frames.",
        "The machine is shared (2 cores, other developers' jobs running); run under nice: seconds are noisy, "
        "ratios to the 2 cm baseline of the same run are the comparable figure; cpu_seconds (process CPU "
        "time, all threads) is less sensitive to the other jobs.",
        "OMP_WAIT_POLICY=PASSIVE (set by pipeline.reconstruct before importing open3d): with OpenMP's default "
        "spinning, the 2 cm ingest took 98 s wall / 29 s CPU at load 10 instead of ~5 s.",
    ]
    j, p = res.write()
    print(f"wrote {j} and {p}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
