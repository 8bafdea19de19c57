"""BLAS on one thread inside the pipeline's work (pipeline/threads.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CHECK = """
from threadpoolctl import threadpool_info
from pipeline.threads import one_blas_thread
with one_blas_thread():
    import scipy.optimize  # scipy's own OpenBLAS loads here, inside the block
    inside = {i["filepath"]: i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}
print(len(inside), max(inside.values()))
"""


def test_every_blas_is_on_one_thread_inside_even_one_loaded_there():
    """numpy's and scipy's OpenBLAS (scipy's loads on its first import, which may come inside the block,
    as the light fit's does) both run one thread inside ``one_blas_thread``; a fresh process, so that
    nothing loaded scipy before."""
    r = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, timeout=120, cwd=ROOT,
                       env={"OPENBLAS_NUM_THREADS": "2", "PATH": ""})
    assert r.returncode == 0, r.stderr[-2000:]
    libs, most = (int(x) for x in r.stdout.split())
    assert libs >= 2 and most == 1, r.stdout
