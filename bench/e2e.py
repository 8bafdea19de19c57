"""End-to-end throughput: images per hour of `scansynth run` on the real 7-Scenes config, per preset.

    .venv/bin/python -m bench.e2e [--config configs/7scenes.toml] [--work DIR] [--presets fast,default,high]
                                  [--subset high=1]

Each stage runs as its own ``scansynth run CONFIG --out DIR --from S --to S`` process, so that besides
its wall seconds (and run.json's per-item seconds) the benchmark gets its CPU seconds (user + system of
the process and its pool workers, from ``resource.getrusage(RUSAGE_CHILDREN)``): this machine is shared,
wall time depends on the load, CPU time much less.

The presets only change the ``[trace]`` table (pipeline/presets.py; checked below), so the stages before
trace (ingest, select, prep, simulate, raster) do the same work and write the same bytes for every
preset: they run once, in the ``default`` run folder, and the other presets' folders start from a copy
of their outputs. Every preset's end-to-end figure counts those shared stages' seconds plus its own
trace, composite and export seconds.

``--subset PRESET=N`` runs that preset's own stages on the first N drops only (the ``high`` preset
costs many times the others' trace time); its shared stages are then charged by the share of the raster
frames it uses, so its images per hour stay comparable. The JSON says which presets were subset.

Baseline measured in the same run: the ``fast`` preset; ratios beside absolute figures. Quality axis:
the trace stage's mean samples per object pixel (its error against a reference for given settings is
measured by bench/trace.py).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench.common import SHARED_DATA, BenchResult

REPO = Path(__file__).resolve().parents[1]
SHARED_STAGES = ("ingest", "select", "prep", "simulate", "raster")
PRESET_STAGES = ("trace", "composite", "export")


def _cpu_children() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_stage(cfg: Path, out: Path, stage: str, workers: int) -> dict:
    """One stage as its own process: wall and CPU seconds, exit code and run.json's entry for it."""
    cmd = [sys.executable, "-m", "pipeline", "run", str(cfg), "--out", str(out), "--from", stage, "--to", stage,
           "--progress", "off", "-q", "--set", f"run.workers={workers}"]
    env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE")
    c0, t0 = _cpu_children(), time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
    wall, cpu = time.perf_counter() - t0, _cpu_children() - c0
    if r.returncode not in (0, 1):
        raise SystemExit(f"{stage}: scansynth exited {r.returncode}:\n{r.stderr[-3000:]}")
    rep = json.loads((out / "run.json").read_text())["stages"][0]
    return {"stage": stage, "wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "rc": r.returncode,
            "run_json_s": rep["seconds"], "items": rep["done"], "failed": rep["failed"],
            "s_per_item": rep["seconds_per_item"], "failures": dict(list(rep["failures"].items())[:3])}


def raster_frames(out: Path) -> int:
    """Rendered (not rejected) raster frames of a run folder."""
    return sum(1 for _ in (out / "raster").glob("*/drop*/f*.npz"))


def images(out: Path) -> int:
    return sum(1 for p in (out / "export").rglob("rgb/*") if p.suffix in (".jpg", ".png"))


def mean_spp(out: Path) -> float:
    vals = []
    for m in (out / "trace" / "_items").rglob("*.done.json"):
        res = json.loads(m.read_text()).get("result") or json.loads(m.read_text())
        for f in (res.get("frames") or {}).values():
            if f.get("object_px"):
                vals.append(f["mean_spp"])
    return float(sum(vals) / len(vals)) if vals else 0.0


def preset_config(base: Path, preset: str, work: Path) -> Path:
    """``base`` with ``run.preset = preset`` (config files resolve their relative paths from their folder,
    so the copy is written beside the original)."""
    import tomllib

    doc = tomllib.loads(base.read_text())
    text = base.read_text()
    if "preset" in doc.get("run", {}):
        raise SystemExit(f"{base}: sets run.preset already; give a config without it")
    text = text.replace("[run]", f'[run]\npreset = "{preset}"', 1) if "[run]" in text else \
        f'[run]\npreset = "{preset}"\n' + text
    path = base.parent / f".bench-e2e-{preset}.toml"
    path.write_text(text)
    return path


def check_presets_touch_only_trace(presets: list[str]) -> None:
    from pipeline.presets import PRESETS

    for p in presets:
        extra = set(PRESETS[p]) - {"trace"}
        if extra:
            raise SystemExit(f"preset {p} changes {sorted(extra)}: the shared-stage shortcut of this "
                             f"benchmark is not valid; run each preset from scratch")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "7scenes.toml")
    ap.add_argument("--work", type=Path, default=Path("/tmp/scansynth-bench-e2e"))
    ap.add_argument("--presets", default="fast,default,high")
    ap.add_argument("--workers", type=int, default=0, help="run.workers (0 = one per core)")
    ap.add_argument("--keep", action="store_true", help="reuse finished stages in --work (resume)")
    ap.add_argument("--subset", default="", help="PRESET=N[,PRESET=N]: run that preset's own stages on the "
                                                 "first N drops only")
    args = ap.parse_args(argv)
    subset = {k: int(v) for k, v in (kv.split("=") for kv in args.subset.split(",") if kv)}
    import signal

    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))    # cut short: still remove the temp configs
    if not SHARED_DATA.is_dir():
        print(f"bench.e2e: {SHARED_DATA} is absent; nothing to measure", file=sys.stderr)
        return 0
    presets = args.presets.split(",")
    check_presets_touch_only_trace(presets)
    if not args.keep and args.work.exists():
        shutil.rmtree(args.work)
    args.work.mkdir(parents=True, exist_ok=True)
    cores = os.cpu_count() or 1
    load0 = os.getloadavg()[0]
    results: dict[str, dict] = {}
    cfgs = {p: preset_config(args.config, p, args.work) for p in presets}
    try:
        base = args.work / "default"
        shared = [run_stage(cfgs.get("default") or preset_config(args.config, "default", args.work), base, s,
                            args.workers) for s in SHARED_STAGES]
        for p in presets:
            out = args.work / p
            if p != "default":
                from pipeline.cli import init_run_dir
                from pipeline.config import load_config

                if not (out / "config.toml").exists():
                    init_run_dir(out, load_config(cfgs[p]))
                    for s in SHARED_STAGES:
                        shutil.copytree(base / s, out / s, dirs_exist_ok=True)
                    if p in subset:
                        for d in (out / "raster").glob("*/drop*"):
                            if d.is_dir() and int(d.name[4:]) >= subset[p]:
                                shutil.rmtree(d)
            own = [run_stage(cfgs[p], out, s, args.workers) for s in PRESET_STAGES]
            share = raster_frames(out) / max(1, raster_frames(base))
            stages = [dict(st, wall_s=round(st["wall_s"] * share, 2), cpu_s=round(st["cpu_s"] * share, 2),
                           charged_share=round(share, 4)) if share < 1 else st for st in shared] + own
            wall = sum(s["wall_s"] for s in stages)
            cpu = sum(s["cpu_s"] for s in stages)
            n = images(out)
            results[p] = {
                "images": n, "wall_s": round(wall, 1), "cpu_s": round(cpu, 1),
                "images_per_hour_wall": round(3600 * n / wall, 1) if wall else 0.0,
                # the same work with the machine's cores to itself: CPU seconds spread over the cores
                "images_per_hour_cpu": round(3600 * n * cores / cpu, 1) if cpu else 0.0,
                "mean_spp": round(mean_spp(out), 2), "stages": stages,
                "subset_drops": subset.get(p), "raster_frames_share": round(share, 4)}
            print(f"{p}: {n} images, wall {wall:.0f} s, cpu {cpu:.0f} s -> "
                  f"{results[p]['images_per_hour_wall']:.0f} img/h wall, "
                  f"{results[p]['images_per_hour_cpu']:.0f} img/h by CPU time", file=sys.stderr)
            # written after every preset, so a run cut short still leaves the finished presets' figures
            write_results(results, presets, args, cores, load0)
    finally:
        for c in cfgs.values():
            c.unlink(missing_ok=True)
    return 0


def write_results(results: dict[str, dict], presets: list[str], args, cores: int, load0: float) -> None:
    """bench/results/e2e.json + e2e.png (+ e2e_stages.png) from the presets finished so far."""
    base_name = "fast" if "fast" in results else presets[0]
    b = results[base_name]
    res = BenchResult("e2e", speed_label="images per hour (CPU time over the 2 cores; wall beside)",
                      accuracy_label="trace mean samples per object pixel")
    for p, r in results.items():
        res.add_point("presets", speed=r["images_per_hour_cpu"], accuracy=r["mean_spp"], label=p,
                      baseline=(p == base_name), wall_images_per_hour=r["images_per_hour_wall"])
        r["ratio_vs_" + base_name] = {
            "images_per_hour_wall": round(r["images_per_hour_wall"] / b["images_per_hour_wall"], 3)
            if b["images_per_hour_wall"] else None,
            "images_per_hour_cpu": round(r["images_per_hour_cpu"] / b["images_per_hour_cpu"], 3)
            if b["images_per_hour_cpu"] else None}
    res.figures.update({
        "config": str(args.config.relative_to(REPO)) if args.config.is_relative_to(REPO) else str(args.config),
        "cores": cores, "workers": args.workers, "load_average_start": round(load0, 2),
        "load_average_end": round(os.getloadavg()[0], 2), "target_images_per_hour_default": 1800,
        "baseline": base_name, "presets": results})
    if "default" in results:
        d = results["default"]
        res.figures["default_images_per_hour_wall"] = d["images_per_hour_wall"]
        res.figures["default_images_per_hour_cpu"] = d["images_per_hour_cpu"]
        res.figures["default_meets_target_wall"] = d["images_per_hour_wall"] >= 1800
        res.figures["default_meets_target_cpu"] = d["images_per_hour_cpu"] >= 1800
    res.notes += [
        "Stages before trace run once (presets change only [trace]); every preset's figure includes them.",
        "images_per_hour_cpu = images x cores x 3600 / CPU seconds: the rate with the machine to ourselves; "
        "images_per_hour_wall is what this (shared, loaded) machine gave during the run.",
        "Per-stage split: results.presets.<p>.stages (wall_s, cpu_s, run.json seconds and items).",
        "A preset with subset_drops ran trace/composite/export on its first drops only; its shared stages' "
        "seconds are charged by raster_frames_share (its share of the rendered frames).",
    ]
    missing = [p for p in presets if p not in results]
    if missing:
        res.notes.append(f"not measured (the run was cut short): {', '.join(missing)}")
    res.write()
    _stage_chart(results)


def _stage_chart(results: dict[str, dict]) -> None:
    """Second panel: per-stage CPU seconds per image, stacked, per preset (bench/results/e2e_stages.png)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bench.common import RESULTS

    fig, ax = plt.subplots(figsize=(7, 4))
    names = list(results)
    bottom = [0.0] * len(names)
    for s in (*SHARED_STAGES, *PRESET_STAGES):
        vals = []
        for p in names:
            st = next(x for x in results[p]["stages"] if x["stage"] == s)
            vals.append(st["cpu_s"] / max(1, results[p]["images"]))
        ax.bar(names, vals, bottom=bottom, label=s)
        bottom = [a + b for a, b in zip(bottom, vals)]
    ax.set_ylabel("CPU seconds per image")
    ax.set_title("scansynth end to end on 7-Scenes redkitchen + LM-O, 640x480")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(RESULTS / "e2e_stages.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
