"""Benchmark of the synthetic scan generator (issue 4): generation time of the tiny and demo presets.

Run: ``.venv/bin/python -m bench.synthscan``. Writes bench/results/synthscan.json and .png.

Targets (issue 4): tiny (160x120, 8 frames) well under 2 s; demo (640x480, 50 frames) <= 20 s on the
2-core machine. Imports are warmed first (a test or the demo pays them once per process). The baseline,
measured in the same run, is the bare rendering floor: one colour and one depth render per frame with
the same renderer, nothing else; the ratio says how much the rest (blur sub-frames, sensor models,
scan mesh, writers, ground truth) adds. Accuracy axis: the largest pose error after reading the
written layout back with the layout's reader (pipeline.scanformats), against the ground truth.
"""

from __future__ import annotations

import math
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import BenchResult


def _render_floor(width: int, height: int, frames: int) -> float:
    """Seconds for one colour + one depth render per frame (the same room, trajectory and renderer)."""
    from pipeline.seeding import item_rng
    from pipeline.camera import Camera
    from pipeline.synthscan.render import RasterPhotoRenderer
    from pipeline.synthscan.room import make_room, tessellate
    from pipeline.synthscan.trajectory import intrinsics, walk

    room = make_room(item_rng(0, "synthscan", "room"))
    mesh = tessellate(room, 0.1)
    poses = walk(room, item_rng(0, "synthscan", "trajectory", str(frames)), frames)
    K = intrinsics(width, height, 585 / 640, item_rng(0, "k"))
    t0 = time.perf_counter()
    r = RasterPhotoRenderer(room, mesh, np.ones((len(mesh.vertices), 3), np.float32))
    for T in poses:
        r.render_color(Camera(K, T, width, height))
        r.render_depth(Camera(K, T, width, height))
    r.close()
    return time.perf_counter() - t0


def _readback_error(scan: Path) -> float:
    from pipeline.scanformats.detect import read_scan

    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = read_scan(scan)
    with np.load(scan / "ground_truth" / "cameras.npz") as z:
        T, valid = z["T_c2w"], z["pose_valid"]
    return float(np.abs(s.T_c2w - T[valid]).max())


def main() -> None:
    from pipeline.gl import pyrender_module
    from pipeline.synthscan import make_scan

    pyrender_module()
    import cv2  # noqa: F401
    import embreex  # noqa: F401
    import scipy.ndimage  # noqa: F401

    res = BenchResult("synthscan", speed_label="seconds per scan", accuracy_label="max pose read-back error",
                      lower_is_better=True)
    tmp = Path(tempfile.mkdtemp(prefix="bench-synthscan-"))
    load0 = os.getloadavg()[0]
    try:
        # Warm-up (first OSMesa context, shader compilation, caches).
        make_scan(tmp / "warm", layout="7scenes", seed=0, width=64, height=48, frames=2)

        tiny, tiny_cpu = [], []
        for k in range(5):
            shutil.rmtree(tmp / "tiny", ignore_errors=True)
            t0, c0 = time.perf_counter(), time.process_time()
            make_scan(tmp / "tiny", layout="7scenes", seed=0, width=160, height=120, frames=8)
            tiny.append(time.perf_counter() - t0)
            tiny_cpu.append(time.process_time() - c0)
        floor_tiny = statistics.median(_render_floor(160, 120, 8) for _ in range(3))
        err_tiny = _readback_error(tmp / "tiny")
        res.add_point("render floor (baseline)", speed=floor_tiny, accuracy=0.0, label="tiny floor", baseline=True)
        res.add_point("make_scan 7scenes", speed=statistics.median(tiny), accuracy=err_tiny, label="tiny 160x120x8")

        per_layout = {}
        for layout in ("3rscan", "scannet", "transforms"):
            t0 = time.perf_counter()
            make_scan(tmp / layout, layout=layout, seed=0, width=160, height=120, frames=8)
            per_layout[layout] = time.perf_counter() - t0
            res.add_point(f"make_scan {layout}", speed=per_layout[layout], accuracy=_readback_error(tmp / layout),
                          label="tiny")

        t0, c0 = time.perf_counter(), time.process_time()
        make_scan(tmp / "demo", layout="7scenes", seed=0, width=640, height=480, frames=50,
                  contact_sheet=tmp / "demo_sheet.png")
        demo = time.perf_counter() - t0
        demo_cpu = time.process_time() - c0
        floor_demo = _render_floor(640, 480, 50)
        err_demo = _readback_error(tmp / "demo")
        res.add_point("render floor (baseline)", speed=floor_demo, accuracy=0.0, label="demo floor")
        res.add_point("make_scan 7scenes", speed=demo, accuracy=err_demo, label="demo 640x480x50")

        # What the demo scan holds.
        import json

        doc = json.loads((tmp / "demo" / "ground_truth" / "scan.json").read_text())
        kinds = [f["blur"]["kind"] for f in doc["frames_info"]]
        strengths = [f["blur"]["strength_px"] for f in doc["frames_info"] if f["blur"]["kind"] != "none"]
        gt = cv2.imread(str(tmp / "demo" / doc["frames_info"][0]["gt_depth"]), cv2.IMREAD_UNCHANGED) * 1e-4
        errs, drop = [], []
        for f in doc["frames_info"]:
            g = cv2.imread(str(tmp / "demo" / f["gt_depth"]), cv2.IMREAD_UNCHANGED) * 1e-4
            s = cv2.imread(str(tmp / "demo" / f["depth"]), cv2.IMREAD_UNCHANGED) * 1e-3
            both = (g > 0) & (s > 0)
            errs.append(np.abs(s[both] - g[both]))
            drop.append(float(((g > 0) & (s == 0)).sum() / max((g > 0).sum(), 1)))
        errs = np.concatenate(errs)
        size_mb = sum(p.stat().st_size for p in (tmp / "demo").rglob("*") if p.is_file()) / 1e6
        thin = json.loads((tmp / "demo" / "ground_truth" / "thin_parts.json").read_text())["thin_parts"]
        del gt

        res.figures.update({
            "tiny_seconds_median": round(statistics.median(tiny), 3),
            "tiny_seconds_all": [round(t, 3) for t in tiny],
            "tiny_cpu_seconds_median": round(statistics.median(tiny_cpu), 3),
            "demo_cpu_seconds": round(demo_cpu, 2),
            "tiny_render_floor_seconds": round(floor_tiny, 3),
            "tiny_ratio_to_render_floor": round(statistics.median(tiny) / floor_tiny, 2),
            "tiny_seconds_by_layout": {k: round(v, 3) for k, v in per_layout.items()},
            "demo_seconds": round(demo, 2),
            "demo_render_floor_seconds": round(floor_demo, 2),
            "demo_ratio_to_render_floor": round(demo / floor_demo, 2),
            "demo_size_mb": round(size_mb, 1),
            "demo_blurred_frames": {"motion": kinds.count("motion"), "defocus": kinds.count("defocus"),
                                    "none": kinds.count("none")},
            "demo_blur_strength_px_range": [round(min(strengths), 2), round(max(strengths), 2)],
            "demo_sensor_depth_abs_error_mm": {"median": round(float(np.median(errs)) * 1e3, 2),
                                               "p90": round(float(np.quantile(errs, 0.9)) * 1e3, 2)},
            "demo_sensor_depth_dropout_fraction_mean": round(float(np.mean(drop)), 3),
            "demo_thin_parts_missing_fraction_mean": round(float(np.mean([t["scan_mesh_missing_fraction"]
                                                                           for t in thin])), 3),
            "pose_readback_error_max": max(err_tiny, err_demo),
            "load_average_at_start": round(load0, 2),
            "load_average_at_end": round(os.getloadavg()[0], 2),
            "targets": {"tiny_seconds": "well under 2", "demo_seconds": "<= 20"},
        })
        res.notes.append("cpu seconds = process CPU time (all threads, OSMesa's included): what the run costs "
                         "when the 2 cores are not shared; wall seconds depend on the other developers' load")
        res.notes.append("machine shared with other developers: see load averages; timings are wall clock with "
                         "warm imports (pyrender, OpenCV, embreex, SciPy imports cost ~1-3 s once per process)")
        res.notes.append("7scenes pose files are written with %.18e (exact round trip); ScanNet's %f rounding "
                         "(<= 5e-7) appears in the scannet point")
        jp, pp = res.write()
        print(f"cpu: tiny {statistics.median(tiny_cpu):.2f} s, demo {demo_cpu:.1f} s; wall: "
              f"tiny: median {statistics.median(tiny):.2f} s (runs {', '.join(f'{t:.2f}' for t in tiny)}), "
              f"render floor {floor_tiny:.2f} s; demo: {demo:.1f} s, render floor {floor_demo:.1f} s; "
              f"load {load0:.1f} -> {os.getloadavg()[0]:.1f}; wrote {jp} and {pp}")
        assert math.isfinite(demo)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
