"""Small real stages used by the runner tests (importable by worker processes)."""

from __future__ import annotations

import os
import time

import numpy as np

from pipeline.errors import InputError
from pipeline.io import atomic_save_npz
from pipeline.stages import Item, Stage


def _plan(ctx):
    return [Item(key=f"scene/f{i:03d}", data={"i": i}) for i in range(int(os.environ.get("SS_TEST_ITEMS", "6")))]


def _run(ctx, item):
    rng = ctx.rng(item)
    delay = float(os.environ.get("SS_TEST_DELAY", "0"))
    if delay:
        time.sleep(delay)
    arr = rng.random((32, 32)).astype(np.float32)
    atomic_save_npz(ctx.stage_dir / f"{item.key}.npz", a=arr)
    return {"sum": float(arr.sum())}


def _run_failing(ctx, item):
    if item.data["i"] == 2:
        raise InputError(f"frame {item.key}: bad depth file (fix: re-export it)")
    if item.data["i"] == 4:
        raise ValueError("an unexpected bug")
    return _run(ctx, item)


ARRAYS = Stage(name="arrays", plan=_plan, run_item=_run)
FAILING = Stage(name="failing", plan=_plan, run_item=_run_failing)


def _plan_bug(ctx):
    raise KeyError("missing upstream output")


def _plan_user(ctx):
    raise InputError("scan folder /x: no frames found (fix: point scan.paths at the folder with frame-*.png)")


PLAN_BUG = Stage(name="planbug", plan=_plan_bug, run_item=_run)
PLAN_USER = Stage(name="planuser", plan=_plan_user, run_item=_run)


def _warm(ctx):
    """Leaves a file named after the worker's pid (a real stage's warm writes nothing; this one is a probe)."""
    if os.environ.get("SS_TEST_WARM_FAILS"):
        raise RuntimeError("warm-up broke")
    (ctx.run_dir / "warm").mkdir(parents=True, exist_ok=True)
    (ctx.run_dir / "warm" / str(os.getpid())).write_text("")


def _plan_waiting_for_warm(ctx):
    """A slow plan (trace's light fit): returns once every worker has warmed, or after 60 s."""
    want = ctx.cfg.run.workers if ctx.cfg.run.workers > 1 else 0   # one worker: no pool, nothing warms
    t0 = time.monotonic()
    while time.monotonic() - t0 < 60 and len(list((ctx.run_dir / "warm").glob("*"))) < want:
        time.sleep(0.05)
    return _plan(ctx)


def _run_noting_pid(ctx, item):
    out = _run(ctx, item)
    out["pid"] = os.getpid()
    return out


WARMED = Stage(name="warmed", plan=_plan_waiting_for_warm, run_item=_run_noting_pid, warm=_warm)


def _warm_dies(ctx):
    """A worker killed while warming up (out of memory, a crash in native code): leaves a mark, then exits."""
    (ctx.run_dir / "died").mkdir(parents=True, exist_ok=True)
    (ctx.run_dir / "died" / str(os.getpid())).write_text("")
    os._exit(3)


def _plan_after_a_death(ctx):
    t0 = time.monotonic()
    while time.monotonic() - t0 < 60 and not list((ctx.run_dir / "died").glob("*")):
        time.sleep(0.05)
    time.sleep(2.0)   # the pool notices its dead worker
    return _plan(ctx)


WARM_DIES = Stage(name="warmdies", plan=_plan_after_a_death, run_item=_run, warm=_warm_dies)
