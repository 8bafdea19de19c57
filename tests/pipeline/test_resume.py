"""Kill a real run with SIGKILL in the middle of a stage, resume it, and get the same bytes.

The run uses the built-in tiny synthetic scan and the built-in shapes, so it needs nothing outside the
repository. The uninterrupted run tells which stage has the most items; the interrupted run is killed
as soon as that stage has finished some but not all of them.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.runner import ITEMS_DIR

# Files whose content legitimately differs between runs: timings and the log of the last invocation.
VOLATILE = {"run.json", "report.html"}  # timings of the last invocation

CONFIG = """
[run]
seed = 3
[scan]
paths = ["builtin:tiny"]
[objects]
paths = ["builtin:shapes"]
[simulate]
drops = 2
objects_per_drop = 3
"""


def _cmd(cfg: Path, out: Path) -> list[str]:
    return [sys.executable, "-m", "pipeline", "run", str(cfg), "--out", str(out), "-q", "--progress", "off"]


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name not in VOLATILE}


def _markers(stage_dir: Path) -> int:
    d = stage_dir / ITEMS_DIR
    return len(list(d.rglob("*.done.json"))) if d.is_dir() else 0


@pytest.mark.slow
def test_sigkill_mid_stage_then_resume_is_byte_identical(tmp_path):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(CONFIG)
    ref = tmp_path / "ref"
    r = subprocess.run(_cmd(cfg, ref), capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    counts = {d.name: _markers(d) for d in ref.iterdir() if d.is_dir()}
    stage, n = max(counts.items(), key=lambda kv: kv[1])
    assert n >= 2, f"no stage with several items to interrupt: {counts}"

    out = tmp_path / "killed"
    proc = subprocess.Popen(_cmd(cfg, out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    deadline = time.monotonic() + 600
    killed_mid_stage = False
    while proc.poll() is None and time.monotonic() < deadline:
        k = _markers(out / stage)
        if 1 <= k < n:
            os.killpg(proc.pid, signal.SIGKILL)
            killed_mid_stage = True
            break
        time.sleep(0.005)
    proc.wait(timeout=60)
    assert killed_mid_stage, f"stage {stage} finished before it could be interrupted"
    assert _markers(out / stage) < n

    r = subprocess.run(_cmd(cfg, out), capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    a, b = _snapshot(ref), _snapshot(out)
    assert sorted(a) == sorted(b)
    different = [k for k in a if a[k] != b[k]]
    assert not different, f"files differ after resume: {different[:10]}"
