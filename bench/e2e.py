"""End to end: images per hour of a whole ``scansynth run`` against the images' accuracy, per preset.

    .venv/bin/python -m bench.e2e [--config configs/7scenes.toml] [--drops 20] [--workers 2]
                                  [--presets fast,default,high] [--preset-drops high=2] [--repeats 2]
                                  [--baseline-tree /path/to/main-clone] [--mode whole|stages] [--seeds 0,1,2]

Speed: the pipeline on the config (``simulate.drops`` raised by ``--drops`` so that the run makes enough
images for its fixed costs to be amortised as in production), into a fresh run folder, timed by
:func:`bench.runs.measure_run`: as one ``python -m pipeline run`` process (``--mode whole``, the default:
what a user's run from a fresh clone costs) or one process per stage (``--mode stages``: each stage's CPU
seconds, each process's start-up on top). Per run: images, wall and CPU seconds, images per hour (wall,
and by CPU time over the machine's cores), each stage's seconds, and the fixed per-scan costs apart
(ingest, select, prep and the light fit inside trace), with the rate of the images without them.

Accuracy: the light suite's held-out rooms (:data:`bench.lighting.HELD_OUT`, rendered by Mitsuba 3;
:mod:`bench.lightsuite`), each run through the CLI with the fit variant at the preset and scored against
the truth by the checkout's own :func:`bench.lighting.run_room` (its objects PSNR and the PSNR of the band
around them), at each run seed of ``--seeds`` for the default preset (the one issue 60's accuracy condition
is about) and of ``--other-seeds`` (default: the first of ``--seeds``) for the others.

Baseline in the same run: ``--baseline-tree`` names another checkout (e.g. a clone of main); every
measurement runs once with each checkout's code (``PYTHONPATH`` and the working folder its root), the
two alternating (A/B/A/B over ``--repeats``), and the JSON gives the ratios beside the figures. Without
it, the ``fast`` preset is the reference the ratios are taken against.

Writes ``OUT.json`` and ``OUT.png`` (``--out``, default bench/results/e2e): images per hour against the
objects' PSNR and the band's, per preset and checkout, the 5,000 images/h target, Blender Cycles' points
from bench/results/cycles.json when that file exists, and the wall seconds per image of each stage.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench.runs import FIXED_STAGES, REPO, STAGES, Tree, measure_run

RESULTS = REPO / "bench" / "results"
TARGET_PER_HOUR = 5000        # issue 60: images per hour, wall, default preset, 2 workers, fixed costs included
MIN_IMAGES = 300              # ... on a run that makes at least this many images
PSNR_DROP_DB = 0.3            # ... with the held-out objects PSNR at most this far below the baseline's
CYCLES_CORES = 2              # Cycles' seconds per image are turned into images per hour on this many cores
PRESETS = ("fast", "default", "high")

# Runs in the measured checkout: its own bench.lighting scores one room with the fit variant at a preset and
# run seed (bench.lighting.main adds --set options to SETTINGS the same way).
_ROOM_SCORER = """
import json, sys
from pathlib import Path
import bench.lighting as lighting
room, work, preset, seed, frames = sys.argv[1:6]
lighting.SETTINGS["fit"] = [*lighting.SETTINGS["fit"], "run.preset=" + preset]
r = lighting.run_room(Path(room), Path(work), ("fit",), int(frames) if frames else None, False, int(seed))
v = r["variants"]["fit"]
print(json.dumps({"psnr_objects": v["psnr_objects"], "psnr_band": v["psnr_band"],
                  "photo_band_psnr": r["photo_band_psnr"], "brightness": v["brightness"],
                  "frames_scored": v["frames_scored"], "cpu_s_per_frame": v["cpu_s_per_frame"],
                  "fit_s": v.get("fit_s"), "render": r.get("render")}))
"""


def score_room(tree: Tree, room_dir: Path, work: Path, preset: str, seed: int, frames: int | None) -> dict:
    """One suite room through ``tree``'s pipeline with the fit variant at ``preset`` and ``seed``, scored by
    ``tree``'s bench.lighting. The stages up to raster run once per ``work`` folder (kept between calls)."""
    cmd = [sys.executable, "-c", _ROOM_SCORER, str(room_dir), str(work), preset, str(seed),
           "" if frames is None else str(frames)]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=tree.root, env=tree.env(), capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"scoring {room_dir.name} with {tree.name}'s code ({tree.root}) at {preset}, seed {seed} "
                           f"failed ({p.returncode}):\n{p.stderr[-3000:]}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    return out


def measure_accuracy(trees: list[Tree], presets: list[str], seeds: dict[str, list[int]], suite: Path,
                     rooms: list[str], work: Path, frames: int | None, log) -> dict:
    """{tree: {preset: {"rooms": {room: [figures per seed]}, "psnr_objects_per_seed", "psnr_band_per_seed"}}}:
    the held-out rooms' means per seed (``seeds``: the run seeds of each preset). The checkouts alternate room
    by room."""
    acc: dict = {t.name: {p: {"rooms": {r: [] for r in rooms}} for p in presets} for t in trees}
    for preset in presets:
        for seed in seeds[preset]:
            for room in rooms:
                for tree in trees:
                    got = score_room(tree, suite / room, work / tree.name / room, preset, seed, frames)
                    got["seed"] = seed
                    acc[tree.name][preset]["rooms"][room].append(got)
                    log(f"accuracy {tree.name} {preset} seed {seed} {room}: objects {got['psnr_objects']:.2f} dB, "
                        f"band {got['psnr_band']:.2f} dB ({got['wall_s']:.0f} s)")
    for t in acc.values():
        for preset, a in t.items():
            per = [[a["rooms"][r][i] for r in rooms] for i in range(len(seeds[preset]))]
            a["seeds"] = seeds[preset]
            for k in ("psnr_objects", "psnr_band"):
                a[k + "_per_seed"] = [round(float(np.mean([x[k] for x in s])), 3) for s in per]
                a[k] = round(float(np.mean(a[k + "_per_seed"])), 3)
            a["band_over_photo_db_per_seed"] = [
                round(float(np.mean([x["psnr_band"] - x["photo_band_psnr"] for x in s])), 3) for s in per]
    return acc


def accuracy_held(acc: dict, preset: str = "default") -> dict | None:
    """Issue 60's accuracy condition, ours against the baseline at ``preset``: at every seed the held-out objects
    PSNR no more than :data:`PSNR_DROP_DB` below, the band's not lower. None without a baseline."""
    if "baseline" not in acc or preset not in acc.get("ours", {}):
        return None
    a, b = acc["ours"][preset], acc["baseline"][preset]
    d_obj = [round(x - y, 3) for x, y in zip(a["psnr_objects_per_seed"], b["psnr_objects_per_seed"])]
    d_band = [round(x - y, 3) for x, y in zip(a["psnr_band_per_seed"], b["psnr_band_per_seed"])]
    return {"preset": preset, "seeds": a["seeds"], "objects_db_vs_baseline": d_obj, "band_db_vs_baseline": d_band,
            "objects_held": all(d >= -PSNR_DROP_DB for d in d_obj), "band_held": all(d >= 0 for d in d_band)}


def measure_speed(trees: list[Tree], presets: list[str], config: Path, work: Path, sets_for, repeats: int, mode: str,
                  keep: bool, log, on_run=None) -> list[dict]:
    """Every preset on every checkout, ``repeats`` times, the checkouts alternating run by run (A/B, then B/A
    the next repeat, so that neither always runs first): a list of :func:`bench.runs.measure_run` results with
    ``preset`` and ``repeat``."""
    runs = []
    for rep in range(repeats):
        for preset in presets:
            for tree in (trees if rep % 2 == 0 else trees[::-1]):
                out = work / "runs" / f"{tree.name}-{preset}-{rep}"
                r = measure_run(tree, config, out, sets_for(preset), mode)
                r.update(preset=preset, repeat=rep)
                runs.append(r)
                log(f"speed {tree.name} {preset} #{rep}: {r['images']} images, {r['wall_s']:.0f} s wall, "
                    f"{r['images_per_hour_wall']:.0f} images/h wall ({r['images_per_hour_wall_without_fixed']:.0f} "
                    f"without the fixed {r['fixed_total_wall_s']:.0f} s), {r['images_per_hour_cpu']:.0f}/h by CPU")
                if not keep:
                    shutil.rmtree(out, ignore_errors=True)
                if on_run:
                    on_run(runs)
    return runs


def summarise_speed(runs: list[dict], reference: str) -> dict:
    """Per checkout and preset: the runs' means and per-run figures; ``ratio``: each over the reference's
    (the baseline checkout at the same preset, else ours at ``fast``), run by run in the order they ran."""
    keys = ("images", "wall_s", "cpu_s", "images_per_hour_wall", "images_per_hour_cpu",
            "images_per_hour_wall_without_fixed", "fixed_total_wall_s", "peak_rss_mb")
    out: dict = {}
    for r in runs:
        out.setdefault(r["tree"], {}).setdefault(r["preset"], {"runs": []})["runs"].append(r)
    for tree, by_preset in out.items():
        for preset, s in by_preset.items():
            for k in keys:
                s[k] = round(float(np.mean([r[k] for r in s["runs"]])), 2)
            s["fixed_wall_s"] = {k: round(float(np.mean([r["fixed_wall_s"][k] for r in s["runs"]])), 2)
                                 for k in s["runs"][0]["fixed_wall_s"]}
            s["stage_wall_s"] = {st: round(float(np.mean([r["stages"][st]["wall_s"] for r in s["runs"]])), 2)
                                 for st in STAGES if st in s["runs"][0]["stages"]}
            if "cpu_s" in next(iter(s["runs"][0]["stages"].values())):
                s["stage_cpu_s"] = {st: round(float(np.mean([r["stages"][st]["cpu_s"] for r in s["runs"]])), 2)
                                    for st in s["stage_wall_s"]}
            ref = out.get("baseline", {}).get(preset) if reference == "baseline" else out.get("ours", {}).get("fast")
            if ref is not None and ref is not s:
                s["ratio"] = {k: [round(a[k] / b[k], 3) if b[k] else None for a, b in zip(s["runs"], ref["runs"])]
                              for k in ("images_per_hour_wall", "images_per_hour_cpu",
                                        "images_per_hour_wall_without_fixed")}
                s["ratio_against"] = "baseline" if reference == "baseline" else "ours fast"
    return out


def read_cycles(path: Path) -> list[dict]:
    """Blender Cycles' points from ``path`` (bench/cycles.py's JSON: ``summary.cycles`` maps samples per pixel to
    ``cpu_s_per_image``, ``psnr_objects`` and ``psnr_band``) as ``{label, images_per_hour, psnr_objects,
    psnr_band}``, CPU seconds spread over :data:`CYCLES_CORES` cores; [] when the file is absent."""
    if not path.is_file():
        return []
    doc = json.loads(path.read_text())
    out = []
    for spp, p in sorted(((doc.get("summary") or {}).get("cycles") or {}).items(), key=lambda kv: int(kv[0])):
        if p.get("cpu_s_per_image") and p.get("psnr_objects") is not None:
            per_hour = 3600.0 * CYCLES_CORES / float(p["cpu_s_per_image"])
            out.append({"label": f"Cycles {spp} spp", "images_per_hour": per_hour,
                        "psnr_objects": float(p["psnr_objects"]),
                        "psnr_band": None if p.get("psnr_band") is None else float(p["psnr_band"])})
    return out


def headline(speed: dict, acc: dict, min_images: int = MIN_IMAGES) -> dict:
    """Issue 60's figure: ours at the default preset, images per hour wall with the fixed costs included, against
    :data:`TARGET_PER_HOUR` on a run of at least ``min_images`` images; the ratio to the baseline; the accuracy
    condition."""
    d = speed.get("ours", {}).get("default")
    if d is None:
        return {}
    h = {"images": d["images"], "images_per_hour_wall": d["images_per_hour_wall"],
         "images_per_hour_wall_per_run": [r["images_per_hour_wall"] for r in d["runs"]],
         "images_per_hour_cpu": d["images_per_hour_cpu"], "fixed_wall_s": d["fixed_wall_s"],
         "images_per_hour_wall_without_fixed": d["images_per_hour_wall_without_fixed"],
         "target_images_per_hour": TARGET_PER_HOUR, "min_images": min_images,
         "run_large_enough": d["images"] >= min_images,
         "meets_target": d["images_per_hour_wall"] >= TARGET_PER_HOUR and d["images"] >= min_images}
    if "ratio" in d:
        h["ratio_vs_" + d["ratio_against"].replace(" ", "_")] = d["ratio"]["images_per_hour_wall"]
    held = accuracy_held(acc)
    if held is not None:
        h["accuracy_held"] = held
    return h


def chart(speed: dict, acc: dict, cycles: list[dict], path: Path, title: str) -> None:
    """Images per hour against the held-out objects' PSNR and the band's (per preset and checkout; bars over
    the seeds' range), and the wall seconds per image of each stage at the default preset."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, ax = plt.subplots(1, 3, figsize=(17, 5))
    colours = {"ours": "tab:blue", "baseline": "tab:gray"}
    for k, (key, name) in enumerate((("psnr_objects", "objects"), ("psnr_band", "band"))):
        a = ax[k]
        for tree, by_preset in speed.items():
            pts = [(by_preset[p]["images_per_hour_wall"], acc[tree][p]) for p in PRESETS
                   if p in by_preset and p in acc.get(tree, {})]
            if not pts:
                continue
            xs = [x for x, _ in pts]
            ys = [v[key] for _, v in pts]
            lo = [y - min(v[key + "_per_seed"]) for y, (_, v) in zip(ys, pts)]
            hi = [max(v[key + "_per_seed"]) - y for y, (_, v) in zip(ys, pts)]
            a.errorbar(xs, ys, yerr=[lo, hi], fmt="o-", color=colours.get(tree), label=tree, capsize=3)
            for x, y, p in zip(xs, ys, [p for p in PRESETS if p in by_preset and p in acc.get(tree, {})]):
                a.annotate(p, (x, y), fontsize=7, textcoords="offset points", xytext=(4, 4))
        cyc = [c for c in cycles if c[key] is not None]
        if cyc:
            a.plot([c["images_per_hour"] for c in cyc], [c[key] for c in cyc], "^", color="tab:red",
                   label=f"Blender Cycles ({CYCLES_CORES} cores)")
            for c in cyc:
                a.annotate(c["label"], (c["images_per_hour"], c[key]), fontsize=7, textcoords="offset points",
                           xytext=(4, -9))
        a.axvline(TARGET_PER_HOUR, ls="--", c="k", lw=0.8, label=f"target {TARGET_PER_HOUR}/h")
        a.set_xscale("log")
        a.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())   # minor labels overlap on a short range
        a.set_xlabel("images per hour, wall (whole run, fixed costs included)")
        a.set_ylabel(f"{name} PSNR vs Mitsuba truth (dB)")
        a.set_title(f"{name} PSNR, held-out rooms' mean (bars: range over seeds)", fontsize=9)
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    names = [(t, p) for t, by in speed.items() for p in PRESETS if p in by]
    bottom = np.zeros(len(names))
    for st in (*FIXED_STAGES, "light_fit", *[s for s in STAGES if s not in FIXED_STAGES]):
        vals = np.array([_stage_wall(speed[t][p], st) / max(1, speed[t][p]["images"]) for t, p in names])
        ax[2].bar([f"{t}\n{p}" for t, p in names], vals, bottom=bottom, label=st.replace("_", " "),
                  hatch="//" if st in (*FIXED_STAGES, "light_fit") else None)
        bottom += vals
    ax[2].set_ylabel("wall seconds per image (hatched: per-scan costs)")
    ax[2].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _stage_wall(s: dict, stage: str) -> float:
    """Wall seconds of a stage in a preset's summary, the light fit apart from the rest of trace."""
    fit = s["fixed_wall_s"].get("light_fit", 0.0)
    if stage == "light_fit":
        return fit
    return s["stage_wall_s"].get(stage, 0.0) - (fit if stage == "trace" else 0.0)


def _parse_ints(text: str, what: str, ap: argparse.ArgumentParser) -> list[int]:
    try:
        vals = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        ap.error(f"{what} {text!r}: give integers separated by commas, e.g. 0,1,2")
    if not vals or min(vals) < 0 or len(set(vals)) != len(vals):
        ap.error(f"{what} {text!r}: give distinct non-negative integers, e.g. 0,1,2")
    return vals


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    from bench.lighting import HELD_OUT, SUITE

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "7scenes.toml")
    ap.add_argument("--work", type=Path, default=Path("/tmp/scansynth-bench-e2e"))
    ap.add_argument("--out", type=Path, default=RESULTS / "e2e", help="output prefix: OUT.json and OUT.png")
    ap.add_argument("--presets", default=",".join(PRESETS))
    ap.add_argument("--drops", type=int, default=0, help="simulate.drops (0: the config's)")
    ap.add_argument("--preset-drops", default="", help="PRESET=N[,PRESET=N]: simulate.drops for that preset's "
                    "speed runs (the high preset's trace costs many times the others')")
    ap.add_argument("--workers", type=int, default=2, help="run.workers (0 = one per core)")
    ap.add_argument("--set", action="append", default=[], help="extra TABLE.KEY=VALUE for the speed runs")
    ap.add_argument("--repeats", type=int, default=1, help="speed runs per preset and checkout")
    ap.add_argument("--mode", choices=("whole", "stages"), default="whole",
                    help="whole: one scansynth process per run; stages: one per stage (CPU seconds per stage)")
    ap.add_argument("--baseline-tree", type=Path, default=None, help="another checkout measured alternately")
    ap.add_argument("--seeds", default="0", help="run seeds of the default preset's accuracy runs, e.g. 0,1,2")
    ap.add_argument("--other-seeds", default="", help="run seeds of the other presets' accuracy runs (default: the "
                    "first of --seeds)")
    ap.add_argument("--suite", type=Path, default=SUITE, help="the light suite's folder (bench.lightsuite)")
    ap.add_argument("--rooms", default=",".join(HELD_OUT), help="the suite's rooms scored (default: held out)")
    ap.add_argument("--frames", type=int, default=None, help="score the first N frames of each room")
    ap.add_argument("--skip", choices=("", "speed", "accuracy"), default="", help="leave one half out")
    ap.add_argument("--keep", action="store_true", help="keep the speed runs' folders in --work")
    a = ap.parse_args(argv)
    a.seeds = _parse_ints(a.seeds, "--seeds", ap)
    a.other_seeds = _parse_ints(a.other_seeds, "--other-seeds", ap) if a.other_seeds else a.seeds[:1]
    a.presets = [p for p in a.presets.split(",") if p]
    if bad := [p for p in a.presets if p not in PRESETS]:
        ap.error(f"--presets: unknown preset(s) {', '.join(bad)}; choose from {', '.join(PRESETS)}")
    try:
        a.preset_drops = {k.strip(): int(v) for k, v in (kv.split("=") for kv in a.preset_drops.split(",") if kv)}
    except ValueError:
        ap.error(f"--preset-drops {a.preset_drops!r}: give PRESET=N pairs, e.g. high=2")
    a.rooms = [r.strip() for r in a.rooms.split(",") if r.strip()]
    if a.repeats < 1:
        ap.error(f"--repeats {a.repeats}: give at least 1")
    if a.baseline_tree is not None and not (a.baseline_tree / "pipeline").is_dir():
        ap.error(f"--baseline-tree {a.baseline_tree}: not a checkout of this project (no pipeline/ folder); "
                 f"e.g. git clone --branch main <repo> /tmp/main-clone")
    beside = a.baseline_tree.resolve().parent / "shared" / "data" if a.baseline_tree is not None else None
    if beside is not None and a.skip != "accuracy" and not beside.is_dir():
        ap.error(f"--baseline-tree {a.baseline_tree}: its light suite runs read the LM-O models from ../shared/data "
                 f"beside it, absent there; clone it beside {REPO.parent / 'shared'} or link shared/ beside it")
    if a.skip != "accuracy":
        missing = [r for r in a.rooms if not (a.suite / r / "done.json").is_file()]
        if missing:
            ap.error(f"--suite {a.suite}: room(s) {', '.join(missing)} not rendered; build them with "
                     f"python -m bench.lightsuite (or give --skip accuracy)")
    return a


def main(argv: list[str] | None = None) -> int:
    a = parse_args(argv)

    def log(msg: str) -> None:
        print(f"{time.strftime('%H:%M:%S')} {msg}", file=sys.stderr, flush=True)

    trees = [Tree("ours", REPO)] + ([Tree("baseline", a.baseline_tree.resolve())] if a.baseline_tree else [])
    reference = "baseline" if a.baseline_tree else "fast"
    a.work.mkdir(parents=True, exist_ok=True)

    def sets_for(preset: str) -> list[str]:
        drops = a.preset_drops.get(preset, a.drops)
        return ([f"run.workers={a.workers}", f"run.preset={preset}"] + ([f"simulate.drops={drops}"] if drops else [])
                + list(a.set))

    doc = {"config": _rel(a.config), "mode": a.mode, "workers": a.workers, "drops": a.drops,
           "preset_drops": a.preset_drops, "repeats": a.repeats, "seeds": a.seeds, "other_seeds": a.other_seeds,
           "rooms": a.rooms, "suite": str(a.suite), "code": {t.name: t.version() for t in trees},
           "cores": os.cpu_count(),
           "machine": os.uname().nodename, "date": time.strftime("%Y-%m-%d %H:%M"),
           "load_average_start": round(os.getloadavg()[0], 2)}
    acc: dict = {}
    if a.skip != "accuracy":
        shutil.rmtree(a.work / "accuracy", ignore_errors=True)     # the rooms' stages up to raster, per checkout
        seeds = {p: a.seeds if p == "default" else a.other_seeds for p in a.presets}
        acc = measure_accuracy(trees, a.presets, seeds, a.suite, a.rooms, a.work / "accuracy", a.frames, log)
    speed: dict = {}
    runs: list[dict] = []
    if a.skip != "speed":
        def partial(done: list[dict]) -> None:   # a run cut short still leaves what it measured
            write(a.out, dict(doc, partial=True), summarise_speed(done, reference), acc)

        runs = measure_speed(trees, a.presets, a.config, a.work, sets_for, a.repeats, a.mode, a.keep, log, partial)
        speed = summarise_speed(runs, reference)
    write(a.out, doc, speed, acc)
    print(json.dumps(headline(speed, acc), indent=1))
    return 0


def write(out: Path, doc: dict, speed: dict, acc: dict) -> None:
    """OUT.json (the settings, the headline, speed per checkout and preset, accuracy) and OUT.png."""
    cycles = read_cycles(RESULTS / "cycles.json")
    full = dict(doc, headline=headline(speed, acc), speed=speed, accuracy=acc, cycles=cycles,
                load_average_end=round(os.getloadavg()[0], 2),
                notes=["images_per_hour_wall: images over the whole run's wall seconds, fixed per-scan costs included "
                       "(fixed_wall_s: ingest, select, prep and the light fit inside trace); "
                       "images_per_hour_wall_without_fixed: over the rest.",
                       "images_per_hour_cpu = images x cores x 3600 / CPU seconds of the run and its workers.",
                       "ratio: each run over the reference's run of the same repeat (the checkouts alternate).",
                       "accuracy: the fit variant at each preset on the light suite's held-out rooms (bench.lighting), "
                       "means over the rooms per run seed."])
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(full, indent=1, default=float) + "\n")
    chart(speed, acc, cycles, out.with_suffix(".png"),
          f"scansynth end to end: {doc['config']}, {doc['workers']} workers, held-out rooms {', '.join(doc['rooms'])}")


def _rel(p: Path) -> str:
    p = p.resolve()
    return str(p.relative_to(REPO)) if p.is_relative_to(REPO) else str(p)


if __name__ == "__main__":
    sys.exit(main())
