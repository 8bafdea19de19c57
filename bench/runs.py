"""Timed ``scansynth run`` processes for the end-to-end benchmarks (bench/e2e.py, bench/scaling.py).

A :class:`Tree` is the checkout whose code runs: the process starts with ``PYTHONPATH`` and the working
folder set to its root, so the same measurement runs today's code and another checkout's (a clone of
main, the baseline) alike. :func:`run_timed` starts one process and gives its wall seconds, its CPU
seconds and peak memory with every process it started (``os.wait4``'s resource usage: user + system time
and the largest resident set of any one process of the tree; the tree's summed resident set is polled
beside it), and its stderr lines stamped with the time they came.

:func:`measure_run` runs the whole pipeline on a config into a fresh run folder, as one process
(``mode="whole"``: what a user's ``scansynth run`` costs) or one process per stage (``mode="stages"``:
the CPU seconds of each stage, each process's start-up on top). Both report the fixed per-scan costs
apart: the ingest, select and prep stages, and the room's light fit, which the trace stage runs in its
plan before its items; the fit's wall seconds are the time from the trace stage's first log line to the
fit's summary line, its CPU seconds are the ones that line gives.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STAGES = ("ingest", "select", "prep", "simulate", "raster", "trace", "composite", "export")
FIXED_STAGES = ("ingest", "select", "prep")       # once per scan: their cost does not grow with the images
POLL_S = 0.25                                     # how often the tree's summed resident memory is read
_FIT_LINE = re.compile(r"light fit of (\S+): \d+ points.*, ([0-9.]+) s$")


@dataclass(frozen=True)
class Tree:
    """A checkout whose code a measurement runs: ``name`` ("ours", "baseline") and its root folder."""

    name: str
    root: Path

    def env(self) -> dict[str, str]:
        """The environment of its processes: its own packages first; Open3D's OpenMP threads wait passively
        (spinning ones slow a 2-core machine many times over)."""
        return dict(os.environ, PYTHONPATH=str(self.root), OMP_WAIT_POLICY="PASSIVE")

    def version(self) -> str | None:
        """Its commit (``+`` when tracked files other than bench/results differ from it); None outside git."""
        try:
            head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=self.root, capture_output=True,
                                  text=True, check=True).stdout.strip()
            dirty = subprocess.run(["git", "diff", "--quiet", "HEAD", "--", ".", ":(exclude)bench/results"],
                                   cwd=self.root).returncode != 0
        except (OSError, subprocess.CalledProcessError):
            return None
        return head + ("+" if dirty else "")


@dataclass(frozen=True)
class Timed:
    """One finished process: its exit code, wall and CPU seconds (with its children), peak memory and the
    stderr lines as ``(seconds since the start, text)``."""

    rc: int
    wall_s: float
    cpu_s: float
    peak_rss_mb: float        # largest resident set of any one process of the tree
    peak_tree_rss_mb: float   # largest sum of the tree's resident sets, polled every POLL_S
    lines: tuple[tuple[float, str], ...]

    def tail(self, n: int = 40) -> str:
        return "\n".join(t for _, t in self.lines[-n:])


def _tree_rss(pid: int) -> int:
    """Summed resident bytes of process ``pid`` and its descendants (0 once it is gone)."""
    import psutil

    try:
        p = psutil.Process(pid)
        procs = [p, *p.children(recursive=True)]
    except psutil.Error:
        return 0
    total = 0
    for q in procs:
        try:
            total += q.memory_info().rss
        except psutil.Error:
            pass
    return total


def run_timed(cmd: list[str], tree: Tree) -> Timed:
    """Run ``cmd`` in ``tree`` (cwd and ``PYTHONPATH`` its root), stderr captured line by line."""
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, cwd=tree.root, env=tree.env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         text=True, bufsize=1)
    lines: list[tuple[float, str]] = []
    done = threading.Event()
    peak = [0]

    def read() -> None:
        for line in p.stderr:
            lines.append((time.perf_counter() - t0, line.rstrip("\n")))

    def poll() -> None:
        while not done.wait(POLL_S):
            peak[0] = max(peak[0], _tree_rss(p.pid))

    reader, poller = threading.Thread(target=read, daemon=True), threading.Thread(target=poll, daemon=True)
    reader.start()
    poller.start()
    _, status, ru = os.wait4(p.pid, 0)     # the child's own usage and that of every process it waited for
    wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    done.set()
    reader.join()
    poller.join()
    p.stderr.close()
    return Timed(rc=p.returncode, wall_s=wall, cpu_s=ru.ru_utime + ru.ru_stime, peak_rss_mb=ru.ru_maxrss / 1024,
                 peak_tree_rss_mb=peak[0] / 2**20, lines=tuple(lines))


def light_fit(lines) -> dict | None:
    """The light fit's seconds from a trace stage's stderr (``-v``): ``wall_s`` from the stage's first log
    line to the last fit summary line, ``cpu_s`` the summary lines' own (summed over scenes); None when no
    fit ran."""
    start = next((t for t, s in lines if "stage trace:" in s), None)
    fits = [(t, float(m.group(2))) for t, s in lines if (m := _FIT_LINE.search(s))]
    if start is None or not fits:
        return None
    return {"wall_s": round(fits[-1][0] - start, 2), "cpu_s": round(sum(c for _, c in fits), 2), "scenes": len(fits)}


def images(out: Path) -> int:
    """Exported images of a run folder."""
    return sum(1 for p in (out / "export").rglob("rgb/*") if p.suffix in (".jpg", ".png"))


def pipeline_cmd(config: Path, out: Path, sets: list[str], first: str = "", last: str = "") -> list[str]:
    """``python -m pipeline run`` of ``config`` into ``out``, from stage ``first`` to ``last`` (empty: all)."""
    cmd = [sys.executable, "-m", "pipeline", "run", str(config), "--out", str(out), "--progress", "off", "-v"]
    cmd += ["--from", first] if first else []
    cmd += ["--to", last] if last else []
    for s in sets:
        cmd += ["--set", s]
    return cmd


def measure_run(tree: Tree, config: Path, out: Path, sets: list[str], mode: str = "whole") -> dict:
    """The pipeline on ``config`` (with ``--set`` ``sets``) into a fresh ``out``, timed.

    Returns images, wall and CPU seconds, images per hour (wall; and by CPU time over the machine's cores:
    the rate with the machine to itself), peak memory, per stage its wall seconds (run.json's; with
    ``mode="stages"`` also the process's wall and CPU seconds), and ``fixed``: the per-scan costs
    (:data:`FIXED_STAGES` and the light fit) in wall seconds, with the rate of the images without them.
    """
    if mode not in ("whole", "stages"):
        raise ValueError(f"mode {mode!r}: choose 'whole' or 'stages'")
    shutil.rmtree(out, ignore_errors=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    load0 = os.getloadavg()[0]
    procs: dict[str, Timed] = {}
    if mode == "whole":
        procs["run"] = run_timed(pipeline_cmd(config, out, sets), tree)
        stage_docs = run_json_stages(out, procs["run"])
    else:
        stage_docs = {}
        for s in STAGES:
            procs[s] = run_timed(pipeline_cmd(config, out, sets, s, s), tree)
            doc = run_json_stages(out, procs[s])[s]
            stage_docs[s] = dict(doc, process_wall_s=round(procs[s].wall_s, 2), cpu_s=round(procs[s].cpu_s, 2))
    all_lines = [ln for t in procs.values() for ln in t.lines]
    trace_lines = procs["run" if mode == "whole" else "trace"].lines
    fit = light_fit(trace_lines)
    wall = sum(t.wall_s for t in procs.values())
    cpu = sum(t.cpu_s for t in procs.values())
    n = images(out)
    key = "wall_s" if mode == "whole" else "process_wall_s"
    fixed = {s: stage_docs[s][key] for s in FIXED_STAGES if s in stage_docs}
    fixed["light_fit"] = fit["wall_s"] if fit else 0.0
    fixed_total = sum(fixed.values())
    per_image = wall - fixed_total
    cores = os.cpu_count() or 1
    return {
        "tree": tree.name, "mode": mode, "sets": list(sets), "images": n, "wall_s": round(wall, 2),
        "cpu_s": round(cpu, 2),
        "images_per_hour_wall": round(3600 * n / wall, 1) if wall > 0 else 0.0,
        "images_per_hour_cpu": round(3600 * n * cores / cpu, 1) if cpu > 0 else 0.0,
        "peak_rss_mb": round(max(t.peak_rss_mb for t in procs.values()), 1),
        "peak_tree_rss_mb": round(max(t.peak_tree_rss_mb for t in procs.values()), 1),
        "stages": stage_docs, "light_fit": fit,
        "fixed_wall_s": {k: round(v, 2) for k, v in fixed.items()}, "fixed_total_wall_s": round(fixed_total, 2),
        "images_per_hour_wall_without_fixed": round(3600 * n / per_image, 1) if per_image > 0 else 0.0,
        "failed_items": sum(d.get("failed", 0) for d in stage_docs.values()),
        "load_average": [round(load0, 2), round(os.getloadavg()[0], 2)], "cores": cores,
        "warnings": [s for _, s in all_lines if s.startswith(("WARNING", "ERROR"))][:10],
    }


def run_json_stages(out: Path, proc: Timed) -> dict[str, dict]:
    """run.json's stage entries of the invocation that just ended, by stage; a run that wrote none (a
    crash, a bad config) is an error naming the command's last stderr lines."""
    path = out / "run.json"
    if proc.rc not in (0, 1) or not path.is_file():
        raise RuntimeError(f"scansynth exited {proc.rc} writing {out}:\n{proc.tail()}")
    doc = json.loads(path.read_text())
    return {s["stage"]: {"wall_s": s["seconds"], "items": s["done"], "failed": s["failed"]} for s in doc["stages"]}
