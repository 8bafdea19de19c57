"""Running a stage: items, done markers, resumable execution.

The contract's types (:class:`~pipeline.stages.Stage`, :class:`~pipeline.stages.Item`,
:class:`~pipeline.stages.StageContext`) live in :mod:`pipeline.stages`, below this module and the stages.
A stage splits its work into :class:`Item` s (a scene, a drop, a frame). ``plan`` lists them from
what earlier stages wrote; ``run_item`` does one, writing every output atomically under the stage's
folder and returning a small JSON-able summary. When ``run_item`` returns, the runner writes the
item's *done marker* (``RUN/<stage>/_items/<key>.done.json``, atomically, after the outputs). An item
with a done marker is never run again, so a run killed at any moment resumes where it stopped and
loses nothing it had finished. Items must be deterministic functions of the config, the seed and
earlier stages' outputs: redoing an item whose marker was not yet written gives the same bytes.

A failing item is recorded (``<key>.failed.json``: the cause, one line for a
:class:`~pipeline.errors.UserError`, the traceback otherwise), the stage goes on with the other items,
and the run ends with exit code 1. Failed items are retried when the run is started again.

An item that finishes but had to leave out part of its input (a corrupt frame of a scan, an unreadable
model in an object library) lists each omission, naming the file and the cause, under
``result[INPUT_PROBLEMS]``. Its outputs are kept (the done marker is written, and the problems also go
to ``<key>.problems.json`` beside it, so listing them needs no read of every marker); they are reported
in run.json and on the console by every invocation that covers the stage, and the run exits 1: the
dataset is complete for what could be read, and the user is told what could not.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import multiprocessing
import os
import time
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline.config import Config, build_config, config_to_dict
from pipeline.errors import ConfigError, UserError
from pipeline.io import atomic_write_json, read_json
from pipeline.stages import INPUT_PROBLEMS, Item, Stage, StageContext, get_stage

log = logging.getLogger(__name__)

ITEMS_DIR = "_items"
PLAN_FAILED = "_plan.failed.json"  # written when a stage cannot list its items


@dataclass
class StageReport:
    """What happened in one stage of one invocation."""

    stage: str
    total: int = 0
    done: int = 0        # items run to completion now
    skipped: int = 0     # items already finished by an earlier invocation
    failed: int = 0
    seconds: float = 0.0
    item_seconds: list[float] = field(default_factory=list)
    failures: dict[str, str] = field(default_factory=dict)
    problems: dict[str, list[str]] = field(default_factory=dict)  # finished items that left out inputs
    placeholder: str = ""

    def as_dict(self) -> dict:
        per = float(np.mean(self.item_seconds)) if self.item_seconds else 0.0
        return {"stage": self.stage, "total": self.total, "done": self.done, "skipped": self.skipped,
                "failed": self.failed, "seconds": round(self.seconds, 3),
                "seconds_per_item": round(per, 4), "failures": self.failures,
                "input_problems": self.problems, "placeholder": self.placeholder}


def _marker(run_dir: Path, stage: str, key: str, kind: str) -> Path:
    return run_dir / stage / ITEMS_DIR / f"{key}.{kind}.json"


def is_done(run_dir: Path, stage: str, key: str) -> bool:
    return _marker(run_dir, stage, key, "done").is_file()


def item_results(run_dir: Path, stage: str) -> dict[str, dict]:
    """Summaries returned by ``run_item`` for every finished item of ``stage``, by key."""
    root = Path(run_dir) / stage / ITEMS_DIR
    out = {}
    if root.is_dir():
        for p in sorted(root.rglob("*.done.json")):
            out[str(p.relative_to(root))[: -len(".done.json")]] = read_json(p)
    return out


def log_warnings() -> None:
    """Show Python warnings (e.g. an IngestWarning about skipped frames) as one log line each, without
    the source file and code line the default display adds: they are messages for users, not bugs.
    Called by the CLI and in every worker process."""
    def show(message, category, filename, lineno, file=None, line=None):
        logging.getLogger("scansynth").warning("%s: %s", category.__name__, message)

    warnings.showwarning = show


def item_problems(run_dir: Path, stage: str, keys: set[str]) -> dict[str, list[str]]:
    """Inputs that the finished items among ``keys`` left out (their ``<key>.problems.json``), by key."""
    root = Path(run_dir) / stage / ITEMS_DIR
    out = {}
    if root.is_dir():
        for p in sorted(root.rglob("*.problems.json")):
            key = str(p.relative_to(root))[: -len(".problems.json")]
            if key in keys and is_done(run_dir, stage, key):
                out[key] = read_json(p)
    return out


def execute_item(run_dir: str, cfg_dict: dict, stage_ref: str, item: Item) -> tuple[str, str | None, float]:
    """Run one item and write its marker; return ``(key, error or None, seconds)``.

    Module-level so a worker process can run it (pickled by reference). ``stage_ref`` is a registry
    name or ``"module:attribute"``.
    """
    t0 = time.perf_counter()
    log_warnings()
    run = Path(run_dir)
    cfg = build_config(cfg_dict, base_dir=run)
    stage = get_stage(stage_ref)
    stage_name = stage.name
    ctx = StageContext(run_dir=run, cfg=cfg, stage=stage_name)
    failed = _marker(run, stage_name, item.key, "failed")
    try:
        result = stage.run_item(ctx, item) or {}
    except UserError as e:
        msg = str(e)
        atomic_write_json(failed, {"key": item.key, "error": msg, "user_error": True})
        return item.key, msg, time.perf_counter() - t0
    except Exception as e:  # noqa: BLE001 - any bug in one item must not lose the others' work
        tb = traceback.format_exc()
        atomic_write_json(failed, {"key": item.key, "error": f"{type(e).__name__}: {e}",
                                   "traceback": tb, "user_error": False})
        log.debug("item %s/%s failed:\n%s", stage_name, item.key, tb)
        return item.key, f"{type(e).__name__}: {e} (bug; traceback in {failed})", time.perf_counter() - t0
    problems = _marker(run, stage_name, item.key, "problems")
    if result.get(INPUT_PROBLEMS):   # beside the done marker, so a run lists them without reading every marker
        atomic_write_json(problems, [str(p) for p in result[INPUT_PROBLEMS]])
    else:
        problems.unlink(missing_ok=True)
    atomic_write_json(_marker(run, stage_name, item.key, "done"), result)
    failed.unlink(missing_ok=True)
    return item.key, None, time.perf_counter() - t0


def warm_worker(run_dir: str, cfg_dict: dict, stage_ref: str) -> None:
    """A stage's ``warm`` in a worker process (module-level so the pool can pickle it)."""
    try:
        stage = get_stage(stage_ref)
        if stage.warm is not None:
            stage.warm(StageContext(run_dir=Path(run_dir), cfg=build_config(cfg_dict, base_dir=Path(run_dir)),
                                    stage=stage.name))
    except Exception as e:  # noqa: BLE001 - start-up is an optimisation; the items do the real work and say
        log.debug("%s: worker start-up failed (%s: %s); the items will redo it", stage_ref, type(e).__name__, e)


def _started() -> None:
    """A task that only makes the pool start a worker process (which runs the pool's initializer first)."""


def _process_pool(n_workers: int, warm: tuple | None = None) -> cf.ProcessPoolExecutor:
    """``n_workers`` worker processes; ``warm``: ``warm_worker``'s arguments, run once in each as it starts."""
    # spawn, not fork: OpenGL/Embree state must never be shared with a forked child.
    return cf.ProcessPoolExecutor(max_workers=n_workers, mp_context=multiprocessing.get_context("spawn"),
                                  initializer=warm_worker if warm else None, initargs=warm or ())


def _warm_pool(run_dir: Path, cfg: Config, stage: Stage, stage_ref: str,
               cfg_dict: dict) -> cf.ProcessPoolExecutor | None:
    """The worker processes of a stage with a ``warm`` step, started now and warming while the main process
    plans; None where the stage has none or runs its items elsewhere (Ray, one worker). The warm step is the
    pool's initializer, so every process runs it once, whichever tasks it later takes."""
    n = worker_count(cfg)
    if stage.warm is None or cfg.run.executor == "ray" or n <= 1:
        return None
    pool = _process_pool(n, (str(run_dir), cfg_dict, stage_ref))
    for _ in range(n):   # a process per submission (no idle one yet): all n start now
        pool.submit(_started)
    return pool


def _ray():
    try:
        import ray
    except ImportError:
        raise ConfigError("run.executor = 'ray' needs Ray: install the extra with "
                          "'.venv/bin/pip install \"scansynth[ray]\"' (or set run.executor = 'local')") from None
    return ray


def _run_on_ray(cfg: Config, run_dir: str, cfg_dict: dict, stage_ref: str, todo: list[Item]):
    """Run items as Ray tasks; yield ``execute_item`` results as they complete.

    Joins ``run.ray_address`` when given, else starts (or reuses) a local Ray instance. Items are
    idempotent and write their own outputs and markers, so a task Ray retries after losing a worker
    only redoes that item. The run folder must be on a filesystem every node sees.
    """
    ray = _ray()
    if not ray.is_initialized():
        try:
            ray.init(address=cfg.run.ray_address or None, include_dashboard=False, log_to_driver=False,
                     configure_logging=False)
        except ConnectionError as e:
            raise ConfigError(f"run.ray_address = {cfg.run.ray_address!r}: cannot join a Ray cluster there "
                              f"({e}); start one with 'ray start --head' or leave the address empty") from None
    task = ray.remote(max_retries=3)(execute_item)
    pending = [task.remote(run_dir, cfg_dict, stage_ref, it) for it in todo]
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        yield ray.get(done[0])


def _terminate_workers(pool: cf.ProcessPoolExecutor) -> None:
    # ProcessPoolExecutor has no public way to stop running tasks; its worker processes are in the
    # private ``_processes`` (stable since Python 3.2).
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(timeout=10)


def worker_count(cfg: Config) -> int:
    """Worker processes a stage runs on (``run.workers``; 0 = one per core)."""
    n = cfg.run.workers
    return (os.cpu_count() or 1) if n == 0 else n


def run_stage(run_dir: Path, cfg: Config, stage: Stage,
              on_progress: Callable[[int, int, float], None] | None = None,
              stage_ref: str | None = None) -> StageReport:
    """Run every unfinished item of ``stage``; skip finished ones; record failures.

    ``on_progress(finished, total, elapsed_seconds)`` is called after each item (the CLI draws a bar).
    ``stage_ref`` tells worker processes where to find the stage (default: its registry name).
    """
    stage_ref = stage_ref or stage.name
    report = StageReport(stage=stage.name, placeholder=stage.placeholder)
    t0 = time.perf_counter()
    if stage.placeholder:
        log.warning("stage %s is a PLACEHOLDER and did nothing: %s", stage.name, stage.placeholder)
        return report
    ctx = StageContext(run_dir=run_dir, cfg=cfg, stage=stage.name)
    cfg_dict = config_to_dict(cfg)
    pool = _warm_pool(run_dir, cfg, stage, stage_ref, cfg_dict)   # the stage's workers, where they warm up
    try:
        try:
            items = stage.plan(ctx)
        except Exception as e:  # noqa: BLE001 - a stage that cannot plan fails alone; the run reports it
            user = isinstance(e, UserError)
            msg = str(e) if user else f"{type(e).__name__}: {e} (bug; traceback in {PLAN_FAILED})"
            atomic_write_json(run_dir / stage.name / ITEMS_DIR / PLAN_FAILED,
                              {"error": msg, "user_error": user,
                               "traceback": "" if user else traceback.format_exc()})
            log.error("%s could not list its work: %s", stage.name, msg)
            report.failed, report.failures = 1, {"(plan)": msg}
            report.seconds = time.perf_counter() - t0
            if pool is not None:
                _terminate_workers(pool)
            return report
        (run_dir / stage.name / ITEMS_DIR / PLAN_FAILED).unlink(missing_ok=True)
        keys = [it.key for it in items]
        if len(set(keys)) != len(keys):
            raise RuntimeError(f"stage {stage.name} planned duplicate item keys")
        report.total = len(items)
        todo = [it for it in items if not is_done(run_dir, stage.name, it.key)]
        report.skipped = report.total - len(todo)
        finished = report.skipped
        if on_progress:
            on_progress(finished, report.total, 0.0)

        def record(key: str, err: str | None, sec: float) -> None:
            nonlocal finished
            finished += 1
            if err is None:
                report.done += 1
                report.item_seconds.append(sec)
            else:
                report.failed += 1
                report.failures[key] = err
                log.error("%s %s failed: %s", stage.name, key, err)
            if on_progress:
                on_progress(finished, report.total, time.perf_counter() - t0)

        n_workers = min(worker_count(cfg), max(1, len(todo)))
        if pool is not None and not todo:
            _terminate_workers(pool)   # warm, but nothing left to do
        elif cfg.run.executor == "ray" and todo:
            for res in _run_on_ray(cfg, str(run_dir), cfg_dict, stage_ref, todo):
                record(*res)
        elif n_workers <= 1 and pool is None:
            for it in todo:
                record(*execute_item(str(run_dir), cfg_dict, stage_ref, it))
        else:
            if pool is not None and getattr(pool, "_broken", False):
                # a warm process died (killed, or a crash in native code): the items get a fresh pool, and say
                # themselves what goes wrong if it was not the warm step alone
                log.warning("%s: a worker process died while warming up (%s); starting the workers again",
                            stage.name, pool._broken)
                _terminate_workers(pool)
                pool = None
            pool = pool or _process_pool(n_workers)
            futs = [pool.submit(execute_item, str(run_dir), cfg_dict, stage_ref, it) for it in todo]
            for fut in cf.as_completed(futs):
                record(*fut.result())
            pool.shutdown(wait=True)
        report.problems = item_problems(run_dir, stage.name, set(keys))
        if stage.finish is not None:  # also after failures: finish what can be finished
            stage.finish(ctx, item_results(run_dir, stage.name))
        report.seconds = time.perf_counter() - t0
        return report
    except BaseException:
        # Interrupted (Ctrl-C, SIGTERM) or failed: stop the workers now instead of letting them
        # finish their items in the background. Finished items are kept; the ones cut short
        # left only temp files, which the next run removes and redoes.
        if pool is not None:
            _terminate_workers(pool)
        raise
