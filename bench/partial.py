"""Partial-capture benchmark (issue 20): drops of LM-O objects onto scans that are not whole rooms.

Two captures made from real redkitchen data (tests/support/captures.py): a one-view scan (one frame's photo, depth
and pose; its mesh from that depth alone) and a table cropped out of it (the faces 0.55-1.0 m above the
frame's floor: a tabletop capture without the floor). Each goes through ingest, select and prep with the
real CLI, then the simulate stage's own drop function (:func:`pipeline.simulate.simulate`, with the spawn
view map) runs ``--drops`` drops of 3 objects. Baseline, same run: the same drops as before issue 20's
third fix: the view map counts every upward surface the depth sees (also where the mesh has none) and
the spawn slab stays where the room's height range puts it.

Reported per capture, as bench/physics.py does: acceptance share and verdicts, and for every object of an
accepted drop what holds it up: the scan (its gap to the scan mesh itself: the smallest signed distance
of its hull vertices), another object, or nothing the scan has (the floor plane under the capture's
lowest surface, or the air: such an object hangs in the photo).

Run: ``.venv/bin/python -m bench.partial [--drops 30]``. Writes bench/results/partial.json and
partial.png (acceptance and median rest gap against CPU seconds per drop).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.common import SHARED_DATA, BenchResult
from bench.physics import supports

log = logging.getLogger(__name__)
ROOT = Path(__file__).resolve().parents[1]
SCENE = "one-view"


def prepared_run(kind: str, cache: Path) -> Path:
    """A run folder of the capture ``kind`` ("one-view" or "cropped table") through prep (cached)."""
    from tests.support.captures import cropped_table_scan, one_view_scan

    base = cache / kind.replace(" ", "-")
    run = base / "run"
    if (run / "prep").is_dir():
        return run
    if kind == "one-view":
        scan, mesh, _, _ = one_view_scan(SHARED_DATA, base)
    else:
        scan, mesh, _, _ = cropped_table_scan(SHARED_DATA, base)
    cfg = base / "capture.toml"
    cfg.write_text(f"[run]\nseed = 0\nworkers = 1\n[scan]\npaths = [{json.dumps(str(scan))}]\n"
                   f"mesh = {json.dumps(str(mesh))}\n[objects]\n"
                   f"paths = [{json.dumps(str(SHARED_DATA / 'objects' / 'lmo' / 'models'))}]\n")
    r = subprocess.run([sys.executable, "-m", "pipeline", "run", str(cfg), "--out", str(run), "--to", "prep"],
                       cwd=ROOT, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{kind}: prep failed:\n{r.stderr[-2000:]}")
    return run


def drops(run: Path, n_drops: int, *, raise_slab: bool) -> dict:
    from pipeline import simulate as S
    from pipeline.config import build_config
    from pipeline.threads import one_blas_thread
    from pipeline.runfolder import ROOM_PROXY_TPATH, file_stamp, load_object_proxy, load_objects, load_scan, path
    from pipeline.seeding import item_rng

    scan = load_scan(run, SCENE)
    up = np.asarray(scan.up_w, float)
    room, info = S._cached_room(file_stamp(path(run, ROOM_PROXY_TPATH, scene=SCENE)), tuple(up))
    if raise_slab:
        view = S._view_map(run, scan, room, info.R_w2g)
    else:    # as before: every surface the depth sees votes, and the slab stays at the room's fractions
        from pipeline.runfolder import load_selection
        from pipeline.view_spawn import view_map

        view = view_map(scan, load_selection(run, SCENE), info.R_w2g)
        view = replace(view, top=np.full_like(view.top, -np.inf)) if len(view.score) else None
    cfg = build_config({"simulate": {"objects_per_drop": 3}})
    proxies = {o.obj_id: load_object_proxy(run, o.obj_id) for o in load_objects(run)}
    verdicts, cpu, held = {}, [], {"scan": [], "object": 0, "nothing": []}
    with one_blas_thread():
        for d in range(n_drops):
            rng = item_rng(0, "bench-partial", f"drop{d:04d}")
            c0 = time.process_time()
            pl, _ = S.simulate(cfg.simulate, scene=SCENE, drop=d, room=room, up=up, proxies=proxies, rng=rng,
                               view=view, info=info)
            cpu.append(time.process_time() - c0)
            verdicts[pl.verdict] = verdicts.get(pl.verdict, 0) + 1
            if pl.verdict != "accepted":
                continue
            bodies = [S.body_of(proxies[int(i)], cfg.simulate.friction) for i in pl.obj_ids]
            for what, v in supports(room, up, bodies, pl.R_m2w, pl.t_m2w):   # bench.physics
                if what == "object":
                    held["object"] += 1
                else:
                    held[what].append(v)
    g = np.array(held["scan"])
    acc = verdicts.get("accepted", 0) / n_drops
    return {"drops": n_drops, "accepted_share": acc, "verdicts": verdicts,
            "median_cpu_s_per_drop": float(np.median(cpu)), "mean_cpu_s_per_drop": float(np.mean(cpu)),
            "objects_on_scan": len(g), "objects_on_objects": held["object"],
            "objects_on_nothing": len(held["nothing"]),
            "on_nothing_height_above_scan_mm": [round(1e3 * v, 1) for v in held["nothing"]],
            "gap_median_mm": 1e3 * float(np.median(g)) if len(g) else None,
            "gap_p90_mm": 1e3 * float(np.percentile(g, 90)) if len(g) else None,
            "penetration_p99_mm": 1e3 * max(0.0, -float(np.percentile(g, 1))) if len(g) else None,
            "view_cells": 0 if view is None else len(view.score)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--drops", type=int, default=30)
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "scansynth_bench_partial")
    args = ap.parse_args()
    logging.basicConfig(level=os.environ.get("LOGLEVEL", "WARNING"))
    if not (SHARED_DATA / "scans" / "7scenes-redkitchen").is_dir():
        print(f"bench.partial: {SHARED_DATA} has no redkitchen scan; nothing to measure", file=sys.stderr)
        return 1
    res = BenchResult("partial", "median CPU seconds per drop (3 LM-O objects)",
                      "accepted drops (share)", lower_is_better=False)
    load0 = os.getloadavg()
    for kind in ("one-view", "cropped table"):
        run = prepared_run(kind, args.cache)
        for raise_slab in (False, True):
            r = drops(run, args.drops, raise_slab=raise_slab)
            name = f"{kind}, " + ("slab above the seen surface" if raise_slab else "room-height slab (before)")
            res.figures[name] = r
            res.add_point(kind, speed=r["median_cpu_s_per_drop"], accuracy=r["accepted_share"],
                          label="slab above the surface" if raise_slab else "before", baseline=not raise_slab,
                          gap_median_mm=r["gap_median_mm"])
            print(f"{name}: accepted {r['accepted_share']:.0%} {r['verdicts']}; on scan {r['objects_on_scan']} "
                  f"(gap median {r['gap_median_mm']} mm, p90 {r['gap_p90_mm']} mm), on objects "
                  f"{r['objects_on_objects']}, on nothing {r['objects_on_nothing']}; "
                  f"{r['median_cpu_s_per_drop']:.2f} s CPU/drop")
    res.figures["load_average_start_end"] = [list(load0), list(os.getloadavg())]
    res.notes.append(
        "Captures from tests/support/captures.py (redkitchen frame 0; the cropped table keeps faces 0.55-1.0 m above "
        "the frame's floor). Drops: pipeline.simulate.simulate with the spawn view map of the kept frame, "
        "3 LM-O objects per drop (meshprep solids), seeds item_rng(0, 'bench-partial', dropNNNN). Objects of "
        "accepted drops are classed by what holds them up (bench.physics.supports); gap = smallest signed "
        "distance of the object's hull vertices to the scan mesh. CPU seconds of this process, BLAS on one "
        "thread. Baseline (same run): the view map without the on-the-mesh filter and its surface heights "
        "set to -inf, so the slab stays at simulate's room-height fractions (the code before this change).")
    j, p = res.write()
    print(f"wrote {j} and {p}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
