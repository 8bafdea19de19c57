"""SIGTERM stops a run and its worker processes; finished items stay finished."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

SCRIPT = textwrap.dedent("""
    import sys
    from pathlib import Path
    from pipeline.cli import install_sigterm_handler
    from pipeline.config import build_config
    from pipeline.runner import run_stage
    from tests.pipeline.stage_fixtures import ARRAYS
    install_sigterm_handler()
    try:
        run_stage(Path(sys.argv[1]), build_config({"run": {"workers": 2}}), ARRAYS,
                  stage_ref="tests.pipeline.stage_fixtures:ARRAYS")
    except KeyboardInterrupt:
        sys.exit(130)
""")


def _workers(pid: int) -> set[int]:
    """Pool worker processes of ``pid`` (not multiprocessing's resource tracker)."""
    out: set[int] = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        for child in (task / "children").read_text().split():
            try:
                cmd = Path(f"/proc/{child}/cmdline").read_bytes()
            except FileNotFoundError:
                continue
            if b"spawn_main" in cmd and b"resource_tracker" not in cmd:
                out.add(int(child))
    return out


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc to find child processes")
def test_sigterm_stops_workers_and_keeps_finished_items(tmp_path):
    run = tmp_path / "run"
    env = dict(os.environ, SS_TEST_ITEMS="40", SS_TEST_DELAY="0.5", PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, str(run)], env=env)
    items = run / "arrays" / "_items" / "scene"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(list(items.glob("*.done.json"))) < 2:
        time.sleep(0.05)
    workers = _workers(proc.pid)
    assert workers, "the run had no worker processes to stop"
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=60) == 130
    time.sleep(0.5)
    assert not [w for w in workers if _alive(w)], "worker processes outlived the run"
    done = len(list(items.glob("*.done.json")))
    assert 2 <= done < 40
    time.sleep(1.5)  # nothing keeps writing after the run stopped
    assert len(list(items.glob("*.done.json"))) == done
