"""How the cost of a run grows: images per hour against objects per drop, image size and workers, and peak
memory of a long run against a short one.

    .venv/bin/python -m bench.scaling [--config configs/7scenes.toml] [--drops 6] [--workers 2]
                                      [--objects 1,5,10,20] [--scales 1,2] [--worker-counts 1,2]
                                      [--memory-drops 6,60] [--quick]

Every point runs the pipeline from ``simulate`` to ``export`` in one ``python -m pipeline run`` process
(:func:`bench.runs.run_timed`), on a copy of a run folder whose per-scan stages (ingest, select, prep)
ran once per worker count: those stages do the same work at every point, and their seconds are reported
apart and added back for the whole-run rate. Each point gives images per hour wall three ways: the
images' own stages without the light fit (the per-image cost, what the axes change), with it, and with
every per-scan cost (a whole run's rate at this run's length).

- objects: ``simulate.objects_per_drop`` over ``--objects`` (the library is drawn with repetition,
  ``simulate.repeat_objects``, so 20 objects from LM-O's 8 is allowed);
- image size: ``raster.image_scale`` over ``--scales`` (7-Scenes is 640x480: 2 renders 1280x960);
- workers: ``run.workers`` over ``--worker-counts``, beside the ideal line (the first count's rate times
  the worker ratio);
- memory: the peak resident set (the largest process of the run, and the run's processes summed) of runs
  of ``--memory-drops`` drops (about 100 and 1,000 images on 7-Scenes): flat within
  :data:`MEMORY_FLAT` is the target.

``--quick`` shrinks everything (the built-in tiny scan, 4 frames, one drop, the fast preset, the scan's own
lighting, small axes) so that a test runs it in about a minute; its figures only show the file's shape.
Writes ``OUT.json`` and ``OUT.png`` (``--out``, default bench/results/scaling).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

from bench.runs import FIXED_STAGES, REPO, Tree, light_fit, pipeline_cmd, run_json_stages, run_timed

RESULTS = REPO / "bench" / "results"
MEMORY_FLAT = 0.10     # issue 60: the long run's peak memory within 10 % of the short run's
QUICK = {
    "sets": ['scan.paths=["builtin:tiny"]', "select.max_frames=4", "prep.room_spacing=0.04", "simulate.max_time=10.0",
             "run.preset=fast", "trace.lighting=scan", 'export.formats=["coco"]', "raster.min_visible_area=0.0"],
    "drops": 1, "objects": "1,2", "base_objects": 2, "scales": "1,2", "worker_counts": "1,2", "memory_drops": "1,2",
}


def _config_for(config: Path, sets: list[str]):
    from pipeline.config import load_config

    return load_config(config, sets)


def prefix_run(tree: Tree, config: Path, out: Path, sets: list[str]) -> dict:
    """The per-scan stages (ingest to prep) into a fresh ``out``: wall and CPU seconds, per stage, peak memory."""
    shutil.rmtree(out, ignore_errors=True)
    t = run_timed(pipeline_cmd(config, out, sets, "", FIXED_STAGES[-1]), tree)
    st = run_json_stages(out, t)
    return {"wall_s": round(t.wall_s, 2), "cpu_s": round(t.cpu_s, 2), "peak_rss_mb": round(t.peak_rss_mb, 1),
            "stages_wall_s": {s: st[s]["wall_s"] for s in FIXED_STAGES}}


def point_run(tree: Tree, config: Path, prefix: Path, out: Path, sets: list[str]) -> dict:
    """simulate to export on a copy of ``prefix`` with ``sets`` (the copy's recorded config becomes the point's:
    the per-scan stages it holds do not read what the points change)."""
    from pipeline.cli import CONFIG_NAME
    from pipeline.config import dump_config

    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(prefix, out)
    (out / "run.json").unlink(missing_ok=True)
    (out / CONFIG_NAME).write_text(dump_config(_config_for(config, sets)))
    t = run_timed(pipeline_cmd(config, out, sets, "simulate", ""), tree)
    st = run_json_stages(out, t)
    from bench.runs import images

    n = images(out)
    fit = light_fit(t.lines)
    fit_wall = fit["wall_s"] if fit else 0.0
    return {"images": n, "wall_s": round(t.wall_s, 2), "cpu_s": round(t.cpu_s, 2), "light_fit": fit,
            "stages_wall_s": {s: d["wall_s"] for s, d in st.items()},
            "failed_items": sum(d["failed"] for d in st.values()),
            "peak_rss_mb": round(t.peak_rss_mb, 1), "peak_tree_rss_mb": round(t.peak_tree_rss_mb, 1),
            "images_per_hour_wall_per_image_stages": _rate(n, t.wall_s - fit_wall),
            "images_per_hour_wall_with_fit": _rate(n, t.wall_s)}


def _rate(n: int, seconds: float) -> float:
    return round(3600.0 * n / seconds, 1) if seconds > 0 else 0.0


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def measure(a: argparse.Namespace, log) -> dict:
    """Every point of the three axes and the memory runs; points shared between axes run once."""
    tree = Tree("ours", REPO)
    cfg = _config_for(a.config, a.set)
    base_objects = cfg.simulate.objects_per_drop if a.base_objects == 0 else a.base_objects
    base_workers = a.workers
    prefixes: dict[int, dict] = {}
    points: dict[tuple, dict] = {}

    def point(workers: int, objects: int, scale: float, drops: int) -> dict:
        key = (workers, objects, scale, drops)
        if key in points:
            return points[key]
        if workers not in prefixes:
            pre = a.work / f"prefix-w{workers}"
            prefixes[workers] = prefix_run(tree, a.config, pre, [*a.set, f"run.workers={workers}"])
            log(f"per-scan stages, {workers} worker(s): {prefixes[workers]['wall_s']:.0f} s wall")
        sets = [*a.set, f"run.workers={workers}", f"simulate.objects_per_drop={objects}", f"raster.image_scale={scale}",
                f"simulate.drops={drops}"]
        out = a.work / "point"
        r = point_run(tree, a.config, a.work / f"prefix-w{workers}", out, sets)
        fixed = prefixes[workers]["wall_s"]
        r.update(workers=workers, objects_per_drop=objects, image_scale=scale, drops=drops,
                 per_scan_wall_s=fixed, images_per_hour_wall_whole_run=_rate(r["images"], r["wall_s"] + fixed))
        shutil.rmtree(out, ignore_errors=True)
        points[key] = r
        log(f"workers {workers}, {objects} objects/drop, scale {scale:g}, {drops} drops: {r['images']} images, "
            f"{r['wall_s']:.0f} s wall, {r['images_per_hour_wall_per_image_stages']:.0f} images/h (per-image stages), "
            f"peak {r['peak_rss_mb']:.0f} MB")
        return r

    axes = {
        "objects": [point(base_workers, n, 1.0, a.drops) for n in _ints(a.objects)],
        "image_scale": [point(base_workers, base_objects, s, a.drops) for s in _floats(a.scales)],
        "workers": [point(w, base_objects, 1.0, a.drops) for w in _ints(a.worker_counts)],
    }
    w = axes["workers"]
    for p in w:
        one = w[0]["images_per_hour_wall_per_image_stages"] / w[0]["workers"]
        p["ideal_images_per_hour"] = round(one * p["workers"], 1)
        p["efficiency"] = round(p["images_per_hour_wall_per_image_stages"] / p["ideal_images_per_hour"], 3) \
            if p["ideal_images_per_hour"] else None
    mem = [point(base_workers, base_objects, 1.0, d) for d in _ints(a.memory_drops)]
    short, long_ = mem[0], mem[-1]
    growth = long_["peak_rss_mb"] / short["peak_rss_mb"] - 1 if short["peak_rss_mb"] else None
    tree_growth = long_["peak_tree_rss_mb"] / short["peak_tree_rss_mb"] - 1 if short["peak_tree_rss_mb"] else None
    keys = ("drops", "images", "wall_s", "peak_rss_mb", "peak_tree_rss_mb")
    memory = {"runs": [{k: p[k] for k in keys} for p in mem],
              "per_scan_peak_rss_mb": max(x["peak_rss_mb"] for x in prefixes.values()),
              "growth": None if growth is None else round(growth, 3),
              "tree_growth": None if tree_growth is None else round(tree_growth, 3),
              "target_growth": MEMORY_FLAT,
              "flat": None if growth is None else bool(abs(growth) <= MEMORY_FLAT)}
    return {"axes": axes, "memory": memory, "per_scan": {str(k): v for k, v in prefixes.items()},
            "base": {"workers": base_workers, "objects_per_drop": base_objects, "image_scale": 1.0, "drops": a.drops}}


def chart(res: dict, path: Path, title: str) -> None:
    """Four panels: images per hour against objects per drop, image scale and workers (with the ideal line),
    and peak memory against the images of the run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 4, figsize=(18, 4.5))
    for k, (axis, key, label) in enumerate((("objects", "objects_per_drop", "objects per drop"),
                                            ("image_scale", "image_scale", "raster.image_scale (1 = the scan's size)"),
                                            ("workers", "workers", "workers"))):
        pts = res["axes"][axis]
        xs = [p[key] for p in pts]
        ax[k].plot(xs, [p["images_per_hour_wall_per_image_stages"] for p in pts], "o-", label="per-image stages")
        ax[k].plot(xs, [p["images_per_hour_wall_with_fit"] for p in pts], "s--", label="with the light fit")
        ax[k].plot(xs, [p["images_per_hour_wall_whole_run"] for p in pts], "^:", label="whole run (per-scan costs in)")
        if axis == "workers":
            ax[k].plot(xs, [p["ideal_images_per_hour"] for p in pts], "k-", lw=0.8, label="ideal (per-image stages)")
        ax[k].set_xlabel(label)
        ax[k].set_ylabel("images per hour, wall")
        ax[k].set_xticks(xs)
        ax[k].grid(alpha=0.3)
        ax[k].legend(fontsize=7)
    m = res["memory"]
    ax[3].plot([r["images"] for r in m["runs"]], [r["peak_rss_mb"] for r in m["runs"]], "o-", label="largest process")
    ax[3].plot([r["images"] for r in m["runs"]], [r["peak_tree_rss_mb"] for r in m["runs"]], "s--",
               label="all processes, summed")
    ax[3].set_xlabel("images in the run")
    ax[3].set_ylabel("peak resident memory (MB)")
    ax[3].set_ylim(bottom=0)
    ax[3].grid(alpha=0.3)
    ax[3].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0, 1, 0.94))
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=Path, default=REPO / "configs" / "7scenes.toml")
    ap.add_argument("--work", type=Path, default=Path("/tmp/scansynth-bench-scaling"))
    ap.add_argument("--out", type=Path, default=RESULTS / "scaling", help="output prefix: OUT.json and OUT.png")
    ap.add_argument("--drops", type=int, default=6, help="simulate.drops of the axes' points")
    ap.add_argument("--workers", type=int, default=2, help="run.workers of the objects and image-size points")
    ap.add_argument("--objects", default="1,5,10,20")
    ap.add_argument("--base-objects", type=int, default=0,
                    help="objects per drop of the image-size, workers and memory points (0: the config's)")
    ap.add_argument("--scales", default="1,2")
    ap.add_argument("--worker-counts", default="1,2")
    ap.add_argument("--memory-drops", default="6,60", help="drops of the short and the long run")
    ap.add_argument("--set", action="append", default=[], help="extra TABLE.KEY=VALUE for every run")
    ap.add_argument("--quick", action="store_true", help="tiny runs that show the output's shape in about a minute")
    a = ap.parse_args(argv)
    if a.quick:
        a.set = [*QUICK["sets"], *a.set]
        a.drops, a.base_objects = QUICK["drops"], QUICK["base_objects"]
        a.objects, a.scales = QUICK["objects"], QUICK["scales"]
        a.worker_counts, a.memory_drops = QUICK["worker_counts"], QUICK["memory_drops"]
    try:
        for name in ("objects", "worker_counts", "memory_drops"):
            if not _ints(getattr(a, name)):
                raise ValueError(name)
        if not _floats(a.scales):
            raise ValueError("scales")
    except ValueError:
        ap.error("--objects, --scales, --worker-counts and --memory-drops take numbers separated by commas")
    a.work.mkdir(parents=True, exist_ok=True)

    def log(msg: str) -> None:
        print(f"{time.strftime('%H:%M:%S')} {msg}", file=sys.stderr, flush=True)

    load0 = os.getloadavg()[0]
    t0 = time.time()
    res = measure(a, log)
    doc = {"config": str(a.config), "sets": a.set, "quick": a.quick, "code": Tree("ours", REPO).version(),
           "cores": os.cpu_count(), "machine": os.uname().nodename, "date": time.strftime("%Y-%m-%d %H:%M"),
           "load_average": [round(load0, 2), round(os.getloadavg()[0], 2)], "wall_seconds": round(time.time() - t0, 1),
           **res,
           "notes": ["images_per_hour_wall_per_image_stages: images over the wall seconds of simulate to export less "
                     "the light fit; _with_fit: with it; _whole_run: with the per-scan stages (ingest, select, prep) "
                     "of the same worker count added.",
                     "peak_rss_mb: the largest resident set of any one process of the run (os.wait4); "
                     "peak_tree_rss_mb: the run's processes summed, polled every 0.25 s."]}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n")
    chart(res, a.out.with_suffix(".png"), f"scansynth: how the cost grows ({Path(a.config).name}"
          f"{', quick' if a.quick else ''})")
    print(json.dumps({"memory": res["memory"], "workers": [(p["workers"], p["images_per_hour_wall_per_image_stages"])
                                                           for p in res["axes"]["workers"]]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
