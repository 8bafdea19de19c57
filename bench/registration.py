"""Benchmark: colour camera registration (pipeline.registration) on the real 7-Scenes redkitchen sample.

7-Scenes ships the depth camera's K (585 px) only; the photos come from the Kinect's colour camera. The
colour camera is fitted on the even frames (50) and judged on the odd frames (50): per held-out frame, the
median distance (pixels) from the depth edge points seen through a colour camera to the nearest photo edge.
Cameras compared: identity (colour K = depth K, the baseline), the issue's hand fit (0.90 scale about the
centre, -6 px horizontal shift) and the fitted camera. Check: no extra scale or shift of the fitted camera
improves the held-out median by more than 0.2 px.

Run: ``nice .venv/bin/python -m bench.registration`` (writes bench/results/registration.json and .png).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from bench.common import SHARED_DATA, BenchResult


def scaled(K: np.ndarray, s: float, du: float, dv: float) -> np.ndarray:
    """``K`` scaled by ``s`` about its principal point, then shifted by ``(du, dv)`` pixels."""
    K = np.array(K, np.float64)
    K[:2, :2] *= s
    K[0, 2] += du
    K[1, 2] += dv
    return K


def exported_pairs(run: Path) -> dict:
    """Per exported image of ``run``'s BOP dataset: the distance from the exported depth's edges to the
    exported photo's edges (:func:`tests.support.reference.depth_photo_edge_distance`), pixels."""
    import json

    import cv2

    from tests.support.reference import depth_photo_edge_distance

    out = {}
    for scene in sorted((run / "export" / "dataset" / "train_pbr").glob("*")):
        cams = json.loads((scene / "scene_camera.json").read_text())
        for rgb_path in sorted((scene / "rgb").glob("*")):
            key = str(int(rgb_path.stem))
            depth = cv2.imread(str(scene / "depth" / f"{rgb_path.stem}.png"), cv2.IMREAD_UNCHANGED)
            rgb = cv2.cvtColor(cv2.imread(str(rgb_path)), cv2.COLOR_BGR2RGB)
            z = depth.astype(np.float64) * float(cams[key]["depth_scale"]) / 1000.0
            out[f"{scene.name}/{rgb_path.stem}"] = depth_photo_edge_distance(z, rgb)
    return out


def main() -> int:
    from pipeline.registration import edge_distances, estimate_color_camera, frame_edges
    from pipeline.scanformats.detect import read_scan

    scan_dir = SHARED_DATA / "scans" / "7scenes-redkitchen"
    if not scan_dir.is_dir():
        print(f"bench.registration: {scan_dir} is absent; nothing to measure", file=sys.stderr)
        return 1
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--export", type=Path, default=None,
                    help="a run folder of configs/7scenes.toml: also measure its exported depth PNGs against its "
                         "exported photos (OpenCV-only measure)")
    ap.add_argument("--export-baseline", type=Path, default=None,
                    help="with --export: a run folder of the same config made before the colour camera was "
                         "estimated (e.g. at commit 29df921), measured the same way")
    args = ap.parse_args()
    scan = read_scan(scan_dir, "7scenes")
    fit_idx, test_idx = np.arange(0, scan.num_frames, 2), np.arange(1, scan.num_frames, 2)
    t0, c0 = time.perf_counter(), time.process_time()
    reg = estimate_color_camera(scan, fit_idx)
    fit_s, fit_cpu = time.perf_counter() - t0, time.process_time() - c0
    rng = np.random.default_rng(1)
    test = [fe for i in test_idx if (fe := frame_edges(scan, int(i), max_points=2000, rng=rng)) is not None]
    K_d, I4 = scan.K[0], np.eye(4)
    cams = {"identity (colour K = depth K)": (K_d, I4),
            "issue's hand fit (0.90 scale, -6 px)": (scaled(K_d, 0.90, -6.0, 0.0), I4),
            "fitted": (reg.color_K, reg.T_d2c)}
    per_frame = {name: edge_distances(test, K, T) for name, (K, T) in cams.items()}
    med = {name: float(np.nanmedian(d)) for name, d in per_frame.items()}
    # Does any extra scale or shift of the fitted camera do better on the held-out frames?
    best = (med["fitted"], 1.0, 0.0, 0.0)
    for s in np.arange(0.98, 1.0201, 0.005):
        for du in np.arange(-3.0, 3.01, 1.0):
            for dv in np.arange(-3.0, 3.01, 1.0):
                m = float(np.nanmedian(edge_distances(test, scaled(reg.color_K, s, du, dv), reg.T_d2c)))
                if m < best[0]:
                    best = (m, float(s), float(du), float(dv))
    gain = med["fitted"] - best[0]

    res = BenchResult("registration", speed_label="fit seconds (50 frames)",
                      accuracy_label="held-out median edge distance (px)", lower_is_better=True)
    for name in cams:
        res.add_point("held-out median", speed=fit_s if name == "fitted" else 0.0, accuracy=med[name],
                      label=name, baseline=name.startswith("identity"),
                      p90_px=float(np.nanpercentile(per_frame[name], 90)))
    Kc, T = reg.color_K, reg.T_d2c
    rot_deg = float(np.rad2deg(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1))))
    res.figures.update({
        "frames_fit": int(len(reg.frames)), "frames_test": len(test),
        "median_before_px": round(med["identity (colour K = depth K)"], 3),
        "median_issue_hand_fit_px": round(med["issue's hand fit (0.90 scale, -6 px)"], 3),
        "median_after_px": round(med["fitted"], 3),
        "fit_median_before_px": round(reg.median_before_px, 3), "fit_median_after_px": round(reg.median_after_px, 3),
        "color_fx": round(Kc[0, 0], 2), "color_fy": round(Kc[1, 1], 2), "color_cx": round(Kc[0, 2], 2),
        "color_cy": round(Kc[1, 2], 2), "T_d2c_t_m": [round(x, 4) for x in T[:3, 3]],
        "T_d2c_rot_deg": round(rot_deg, 3), "reliable": reg.reliable, "reason": reg.reason,
        "fit_seconds": round(fit_s, 2), "fit_cpu_seconds": round(fit_cpu, 2),
        "best_extra_scale_shift": {"median_px": round(best[0], 3), "scale": best[1], "du": best[2], "dv": best[3]},
        "extra_scale_shift_gain_px": round(gain, 3), "extra_scale_shift_gain_below_0_2px": bool(gain <= 0.2),
        "per_frame_before_px": [round(float(x), 2) for x in per_frame["identity (colour K = depth K)"]],
        "per_frame_after_px": [round(float(x), 2) for x in per_frame["fitted"]],
    })
    res.notes += [
        "Edge distance: depth edge points (midpoints of neighbour pairs across a depth jump, at the nearer "
        "depth, at most 2000 per frame) projected through the colour camera; distance to the nearest Canny edge "
        "of the blurred gray photo (cv2.distanceTransform); per-frame median over points inside the photo.",
        "Fit on the even frames, figures on the odd (held-out) frames; the issue's figures (4.9 px before, 2.8 px "
        "with its hand fit) came from another edge-distance measurement over 20 frames.",
        "Extra scale/shift check: scale 0.98..1.02 step 0.005 about the principal point, shifts -3..3 px step 1.",
    ]
    if args.export is not None:
        from tests.support.reference import depth_photo_edge_distance
        from pipeline.scanformats.common import read_color, read_depth

        pairs = exported_pairs(args.export)
        src = [depth_photo_edge_distance(read_depth(scan, int(i)), read_color(scan, int(i))) for i in test_idx]
        res.figures["exported_dataset"] = {
            "run": str(args.export), "images": len(pairs),
            "median_px": round(float(np.nanmedian(list(pairs.values()))), 3),
            "per_image_px": {k: round(float(v), 2) for k, v in pairs.items()},
            "source_frames_with_depth_K_median_px": round(float(np.nanmedian(src)), 3)}
        if args.export_baseline is not None:
            base = np.array(list(exported_pairs(args.export_baseline).values()), float)
            res.figures["exported_dataset"]["baseline"] = {
                "run": str(args.export_baseline), "images": len(base),
                "median_px": round(float(np.nanmedian(base)), 3), "mean_px": round(float(np.nanmean(base)), 3),
                "p90_px": round(float(np.nanpercentile(base, 90)), 3)}
            v = np.array(list(pairs.values()), float)
            res.figures["exported_dataset"].update(mean_px=round(float(np.nanmean(v)), 3),
                                                   p90_px=round(float(np.nanpercentile(v, 90)), 3))
        res.notes.append(
            "exported_dataset: the BOP depth PNGs against the rgb images of a configs/7scenes.toml run, measured "
            "by tests.support.reference.depth_photo_edge_distance (depth jumps > 5 % + 3 cm against Canny edges, "
            "OpenCV only); source_frames_with_depth_K: the same measure on the held-out source frames with the depth "
            "camera's K for the photo (what the dataset had before the colour camera was estimated); baseline: the "
            "exported dataset of the same config from a checkout before the estimate (distances are quantised by "
            "OpenCV's 5x5 distance transform: 1, 1.4, 2, ... px).")
    j, p = res.write()
    before, hand, after = med.values()
    print(f"before {before:.2f} px, hand fit {hand:.2f} px, after {after:.2f} px; "
          f"extra scale/shift gain {gain:.3f} px; fit {fit_s:.1f} s; wrote {j} and {p}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
