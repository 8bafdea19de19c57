"""Real-capture benchmark: inserted objects against the real objects a photo shows, light judged by real photos.

Protocol (per object of a real RGB-D capture with ground-truth poses, BOP scene layout): the object's own
surface is cut out of the capture's depth (its rendered silhouette where the sensor saw it, grown by
``CUT_GROW`` pixels), the capture becomes a one-image scan (ingest's BOP reader), and ``scansynth run`` inserts
the object's model at its true pose (``raster.poses``) through composite. The photo already shows the real
object there, so it is the reference: over the object's visible pixels (its silhouette where the sensor depth
agrees with the model's, shrunk by ``SCORE_ERODE`` pixels against registration slop) we report

- PSNR of the composite against the photo (8-bit sRGB), beside a **naive paste** of the model's own colours
  (each pixel the colour of the model vertex nearest to it: no light at all);
- per-channel brightness, photo over ours, in linear light (1 = right; 2 = ours half as bright), and photo over
  the paste (how far the model's own colours are from the real object's under this photo's light and camera);
- the lights the fit found for each cut-out of the same photo: total power and colour (the angle between RGB
  power vectors), whose spread across cut-outs measures stability.

Captures: ``../shared/data/captures/*`` (each a BOP scene folder with ``scene_gt.json``; its models from
``CAPTURE_MODELS``). Objects with a visible fraction of at least ``--min-visib`` (scene_gt_info) are used.

Run: ``.venv/bin/python -m bench.real_captures [--set trace.KEY=VALUE ...]``. Writes
bench/results/real_captures.json and real_captures.png (PSNR against CPU seconds per capture run, ours and paste).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import SHARED_DATA, BenchResult

ROOT = Path(__file__).resolve().parents[1]
CAPTURES = SHARED_DATA / "captures"
CAPTURE_MODELS = {"lmo-test-000002-000003": SHARED_DATA / "objects" / "lmo" / "models"}
CUT_GROW = 3            # pixels: the cut-out grows by this much (edge pixels mix object and table depth)
CUT_TOL = 0.03          # metres: sensor depth within this of the model's is the object's own surface
SCORE_ERODE = 2         # pixels: the scored region shrinks by this much (pose and registration slop)
MIN_SCORED = 400        # pixels: an object with fewer scored pixels is skipped


def _read_rgb(path: Path) -> np.ndarray:
    import cv2
    return cv2.imread(str(path), cv2.IMREAD_COLOR)[:, :, ::-1].copy()


def _read_depth(path: Path, scale_mm: float) -> np.ndarray:
    import cv2
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64) * scale_mm / 1000.0


def _model(models: Path, obj_id: int):
    from pipeline.objects import load_object_file
    return load_object_file(models / f"obj_{obj_id:06d}.ply", obj_id=obj_id, scale=0.001, unit_note="mm")


def _render_depth(model, K: np.ndarray, T_m2c: np.ndarray, w: int, h: int) -> np.ndarray:
    """The model's depth at its pose (camera at the origin), 0 where it is not."""
    from pipeline.render_gl import shared_rasterizer
    r = shared_rasterizer()
    key = f"bench_obj_{model.obj_id}"
    if not r.has_mesh(key):
        r.add_mesh(key, model.vertices.astype(np.float32), model.faces.astype(np.int32))
    return np.asarray(r.render_depth(K, np.eye(4), w, h, [(key, T_m2c)]), np.float64)


def _paste(model, depth: np.ndarray, K: np.ndarray, T_m2c: np.ndarray) -> np.ndarray:
    """The model's own colour (sRGB, 0..255) at each pixel of ``depth``: the colour of the nearest vertex."""
    from scipy.spatial import cKDTree
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    pc = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], 1)
    pm = (pc - T_m2c[:3, 3]) @ T_m2c[:3, :3]
    _, idx = cKDTree(model.vertices).query(pm)
    out = np.zeros(depth.shape + (3,), np.float64)
    cols = model.vertex_colors[:, :3].astype(np.float64)
    out[v, u] = cols[idx] * (255.0 if cols.max() <= 1.0 else 1.0)
    return out


def _psnr(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> float:
    mse = float(np.mean((a[m].astype(np.float64) - b[m].astype(np.float64)) ** 2))
    return 10 * math.log10(255.0 ** 2 / max(mse, 1e-12))


def _linear(srgb_u8: np.ndarray) -> np.ndarray:
    from pipeline.color import decode_u8
    return decode_u8(np.clip(np.round(srgb_u8), 0, 255).astype(np.uint8)).astype(np.float64)


def objects_of(cap: Path, min_visib: float) -> list[dict]:
    """The capture's image and the ground-truth instances worth scoring."""
    cams = json.loads((cap / "scene_camera.json").read_text())
    gts = json.loads((cap / "scene_gt.json").read_text())
    info = json.loads((cap / "scene_gt_info.json").read_text())
    out = []
    for im in sorted(cams, key=int):
        for k, (gt, gi) in enumerate(zip(gts.get(im, []), info.get(im, []))):
            if gi.get("visib_fract", 0.0) >= min_visib:
                T = np.eye(4)
                T[:3, :3] = np.asarray(gt["cam_R_m2c"], float).reshape(3, 3)
                T[:3, 3] = np.asarray(gt["cam_t_m2c"], float) / 1000.0
                out.append({"im_id": int(im), "gt_index": k, "obj_id": int(gt["obj_id"]), "T_m2c": T,
                            "visib_fract": float(gi["visib_fract"])})
    return out


def prepare(cap: Path, inst: dict, models: Path, work: Path) -> dict:
    """A one-image scan of ``cap`` with ``inst``'s own surface cut out, its poses file and config; the
    scored pixels and the naive paste."""
    import cv2
    im = inst["im_id"]
    cam = json.loads((cap / "scene_camera.json").read_text())[str(im)]
    K = np.asarray(cam["cam_K"], float).reshape(3, 3)
    scale = float(cam.get("depth_scale", 1.0))
    rgb_path = next((cap / "rgb").glob(f"{im:06d}.*"))
    photo = _read_rgb(rgb_path)
    h, w = photo.shape[:2]
    real = _read_depth(cap / "depth" / f"{im:06d}.png", scale)
    model = _model(models, inst["obj_id"])
    obj = _render_depth(model, K, inst["T_m2c"], w, h)
    sil = obj > 0
    own = sil & (real > 0) & (np.abs(real - obj) < CUT_TOL)
    cut = cv2.dilate(own.astype(np.uint8), np.ones((2 * CUT_GROW + 1,) * 2, np.uint8)).astype(bool) & (
        (real == 0) | (real > obj - CUT_TOL) | ~sil)
    visible = sil & ((real == 0) | (real > obj - CUT_TOL / 1.5))
    scored = cv2.erode(visible.astype(np.uint8), np.ones((2 * SCORE_ERODE + 1,) * 2, np.uint8)).astype(bool)

    scan = work / "scan"
    for d in ("rgb", "depth"):
        (scan / d).mkdir(parents=True, exist_ok=True)
    shutil.copy(rgb_path, scan / "rgb" / rgb_path.name)
    raw = cv2.imread(str(cap / "depth" / f"{im:06d}.png"), cv2.IMREAD_UNCHANGED)
    raw[cut] = 0
    cv2.imwrite(str(scan / "depth" / f"{im:06d}.png"), raw)
    (scan / "scene_camera.json").write_text(json.dumps({str(im): {"cam_K": K.reshape(-1).tolist(),
                                                                  "depth_scale": scale}}))
    models_dir = work / "models"
    models_dir.mkdir(exist_ok=True)
    for f in (f"obj_{inst['obj_id']:06d}.ply", "models_info.json"):
        shutil.copy(models / f, models_dir / f)
    cfg = work / "capture.toml"
    cfg.write_text(f"[run]\nseed = 0\nworkers = 1\n\n[scan]\npaths = [{json.dumps(str(scan))}]\nformat = \"bop\"\n\n"
                   f"[objects]\npaths = [{json.dumps(str(models_dir))}]\n\n"
                   f"[raster]\nmin_visible_area = 0.0005\n")   # small objects on a whole photo
    return {"photo": photo, "scored": scored, "paste": _paste(model, np.where(scored, obj, 0.0), K, inst["T_m2c"]),
            "config": cfg, "cut_px": int(cut.sum())}


def run_capture(cfg: Path, inst: dict, run: Path, extra: list[str]) -> tuple[np.ndarray, float, dict]:
    """``scansynth run`` up to composite with the object at its true pose: the composite, CPU seconds, lights."""
    py = str(ROOT / ".venv" / "bin" / "python")
    t0 = time.time()
    probe = run.parent / "probe"        # the scene's name and camera pose in ingest's world frame
    subprocess.run([py, "-m", "pipeline", "run", str(cfg), "--out", str(probe), "--to", "ingest", "-q", *extra],
                   check=True, cwd=ROOT)
    scene = json.loads(next((probe / "ingest").glob("*/scan.json")).read_text())["name"]
    from pipeline.runfolder import load_scan
    T_m2w = load_scan(probe, scene).T_c2w[0] @ inst["T_m2c"]
    poses = run.parent / "poses.json"
    poses.write_text(json.dumps({"scene": scene, "drop": 0, "frames": [0], "instances": [
        {"obj_id": inst["obj_id"], "R_m2w": T_m2w[:3, :3].tolist(), "t_m2w": T_m2w[:3, 3].tolist()}]}))
    r = subprocess.run([py, "-m", "pipeline", "run", str(cfg), "--out", str(run), "--to", "composite",
                        "--poses", str(poses), "-q", *extra], cwd=ROOT, capture_output=True, text=True)
    if r.returncode:
        raise RuntimeError(f"scansynth run failed: {r.stderr[-2000:]}")
    seconds = time.time() - t0
    comp = next((run / "composite").rglob("f*.png"))
    lights = {}
    lp = next((run / "trace").glob("*/lights.npz"), None)
    if lp is not None:
        from pipeline.trace.lightfit import RoomLights
        rl = RoomLights.load(lp)
        lights = light_power(rl)
    return _read_rgb(comp), seconds, lights


def light_power(rl) -> dict:
    """The fitted light's total power by channel (radiance x area over the emitting triangles and the closing
    box), and the summary's note."""
    v, f = rl.vertices.astype(np.float64), rl.faces
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    rad = rl.radiance[f].mean(axis=1).astype(np.float64)
    emit = np.zeros(len(f), bool)
    emit[rl.num_mesh_tris:] = True         # the closing box and the lamps: what the fit made emit
    p = (rad[emit] * area[emit, None]).sum(axis=0) * math.pi
    return {"power_rgb": p.tolist(), "note": rl.summary.get("note", ""),
            "capture_note": rl.summary.get("capture_note", "")}


def angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    c = float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12))
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def score(photo, ours, paste, m) -> dict:
    lp, lo, la = _linear(photo)[m], _linear(ours)[m], _linear(paste)[m]
    return {"psnr": _psnr(photo, ours, m), "paste_psnr": _psnr(photo, paste, m),
            "brightness_rgb": (lp.mean(0) / np.maximum(lo.mean(0), 1e-6)).tolist(),
            "paste_brightness_rgb": (lp.mean(0) / np.maximum(la.mean(0), 1e-6)).tolist(), "pixels": int(m.sum())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--min-visib", type=float, default=0.6)
    ap.add_argument("--captures", nargs="*", default=None, help="capture folder names (default: all)")
    ap.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE")
    ap.add_argument("--work", default="", help="keep the runs here (default: a temporary folder)")
    ap.add_argument("--out", default="", help="results folder (default bench/results)")
    a = ap.parse_args(argv)
    extra = [x for s in a.set for x in ("--set", s)]
    caps = [c for c in sorted(CAPTURES.glob("*")) if c.name in CAPTURE_MODELS
            and (a.captures is None or c.name in a.captures)]
    if not caps:
        print(f"no capture found under {CAPTURES}; see ../shared/data/README.md", file=sys.stderr)
        return 2
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="realcap-"))
    res = BenchResult("real_captures", speed_label="CPU-wall seconds per capture run (one object inserted)",
                      accuracy_label="PSNR over the object's visible pixels, dB")
    report: dict = {}
    for cap in caps:
        rows = []
        for inst in objects_of(cap, a.min_visib):
            wd = work / cap.name / f"obj{inst['obj_id']:02d}-{inst['gt_index']}"
            if wd.exists():
                shutil.rmtree(wd)
            wd.mkdir(parents=True)
            p = prepare(cap, inst, CAPTURE_MODELS[cap.name], wd)
            if p["scored"].sum() < MIN_SCORED:
                continue
            ours, secs, lights = run_capture(p["config"], inst, wd / "run", extra)
            s = score(p["photo"], ours, p["paste"], p["scored"])
            row = {"obj_id": inst["obj_id"], "visib_fract": round(inst["visib_fract"], 3), "seconds": round(secs, 1),
                   **{k: (round(v, 2) if isinstance(v, float) else [round(x, 3) for x in v]
                          if isinstance(v, list) else v) for k, v in s.items()}, "lights": lights}
            rows.append(row)
            print(f"{cap.name} obj {inst['obj_id']}: ours {s['psnr']:.2f} dB, paste {s['paste_psnr']:.2f} dB, "
                  f"photo/ours {np.round(s['brightness_rgb'], 2)}, {secs:.0f} s", flush=True)
        if not rows:
            continue
        b = np.array([r["brightness_rgb"] for r in rows])
        pw = [np.asarray(r["lights"].get("power_rgb", [0, 0, 0])) for r in rows]
        tot = np.array([p.sum() for p in pw])
        mean_p = np.mean(pw, axis=0)
        summary = {
            "objects": len(rows),
            "psnr_mean": round(float(np.mean([r["psnr"] for r in rows])), 2),
            "paste_psnr_mean": round(float(np.mean([r["paste_psnr"] for r in rows])), 2),
            "brightness_mean_rgb": np.round(b.mean(0), 3).tolist(),
            "brightness_worst": round(float(b.flat[np.argmax(np.abs(np.log(b)))]), 3),
            "power_spread": round(float((tot.max() - tot.min()) / max(tot.mean(), 1e-12)), 3) if tot.any() else None,
            "colour_spread_deg": round(max(angle_deg(p, mean_p) for p in pw), 2) if tot.any() else None,
            "rows": rows}
        report[cap.name] = summary
        res.add_point(f"{cap.name} ours", speed=float(np.mean([r["seconds"] for r in rows])),
                      accuracy=summary["psnr_mean"])
        res.add_point(f"{cap.name} naive paste", speed=0.0, accuracy=summary["paste_psnr_mean"], baseline=True)
        print(json.dumps({k: v for k, v in summary.items() if k != "rows"}))
    res.figures.update(report)
    res.figures["settings"] = a.set
    if a.out:
        res.write(Path(a.out))
    else:
        res.write()
    return 0


if __name__ == "__main__":
    sys.exit(main())
