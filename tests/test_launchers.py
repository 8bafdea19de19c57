"""The launchers in bin/, run the way the README shows them: from the repository root, as commands.

Each test runs the real script in a subprocess (bash, the project's .venv), not the Python entry point
it ends in, so a launcher that points at a module without ``__main__`` or at a missing interpreter fails.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from meshprep import stress
from meshprep.creation import box

ROOT = Path(__file__).resolve().parents[1]


def _run(args: list[str], cwd: Path = ROOT, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=timeout)


def test_bin_scansynth_help():
    r = _run(["bin/scansynth", "--help"])
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("usage: scansynth")
    for cmd in ("run", "ingest", "export", "preview", "make-scan"):
        assert cmd in r.stdout


def test_bin_meshprep_inspect_and_repair(tmp_path):
    src = stress.write_mesh(tmp_path / "box.ply", *box())
    r = _run(["bin/meshprep", "inspect", str(src), "--json"])
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["watertight"] is True
    out = tmp_path / "fixed.ply"
    r = _run(["bin/meshprep", "repair", str(src), str(out)])
    assert r.returncode == 0, r.stderr
    assert out.is_file() and r.stdout.startswith(f"{out}: 12 faces")
    assert json.loads((tmp_path / "fixed.ply.report.json").read_text())["ok"] is True


def test_bin_meshprep_names_a_face_that_points_at_a_missing_vertex(tmp_path):
    """OBJ ``f 1 2 9`` with three vertices: PyMeshLab drops the face; the console and report say so."""
    src = tmp_path / "tri.obj"
    src.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 9\n")
    out = tmp_path / "tri_fixed.ply"
    r = _run(["bin/meshprep", "repair", str(src), str(out)])
    assert r.returncode == 0, r.stderr
    assert "1 changes" in r.stdout
    assert "dropped 1 face that points at a missing vertex" in r.stderr
    assert "line 5: f 1 2 9 (vertex 9 of 3)" in r.stderr
    changes = json.loads((tmp_path / "tri_fixed.ply.report.json").read_text())["changes"]
    assert changes[0]["faces"] == -1 and changes[0]["examples"] == ["line 5: f 1 2 9 (vertex 9 of 3)"]
    # A clean file says nothing of the kind.
    clean = tmp_path / "clean.obj"
    clean.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf -3 -2 -1\n")
    r = _run(["bin/meshprep", "inspect", str(clean)])
    assert r.returncode == 0 and "missing vertex" not in r.stderr


@pytest.mark.parametrize("name", ["scansynth", "meshprep"])
def test_launcher_before_setup_says_what_to_run(tmp_path, name):
    """A fresh clone without .venv: one line naming bin/setup, exit 2 (not the shell's error)."""
    (tmp_path / "bin").mkdir()
    shutil.copy2(ROOT / "bin" / name, tmp_path / "bin" / name)
    r = _run([str(tmp_path / "bin" / name), "--help"], cwd=tmp_path)
    assert r.returncode == 2
    assert r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith(f"{name}: not set up yet") and "bin/setup" in lines[0]


def test_bin_scansynth_run_with_one_non_rigid_pose_among_12_frames(tmp_path):
    """The issue's case through the launcher: 11 frames are ingested, the one bad pose is left out and
    reported on the console and in run.json (exit 1: an input was left out; everything else is kept)."""
    from tests.pipeline.test_scanformats import trajectory, write_7scenes, write_mat

    scan = tmp_path / "scan"
    write_7scenes(scan, n=12)
    T = trajectory(12)[5]
    T[:3, :3] *= 1.1  # |R^T R - I| = 0.21
    write_mat(scan / "frame-000005.pose.txt", T)
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[scan]\npaths = ["{scan}"]\n[ingest]\ntsdf_voxel = 0.08\ntsdf_trunc = 0.3\n'
                   f'depth_max = 5.0\n[objects]\npaths = ["builtin:shapes"]\n')
    out = tmp_path / "run"
    r = _run(["bin/scansynth", "run", str(cfg), "--out", str(out), "--to", "ingest"])
    assert r.returncode == 1, r.stderr
    assert "Traceback" not in r.stderr
    line = next(ln for ln in r.stderr.splitlines() if ln.startswith("LEFT OUT ingest scan: "))
    assert "skipped 1 of 12 frame(s) that have a malformed pose or one that is not a rigid transform" in line
    assert (f"{scan}/frame-000005.pose.txt: pose is not a rigid transform (det R = 1.3310, "
            f"|R^T R - I| = 2.10e-01") in line
    meta = json.loads((out / "ingest" / "scan" / "scan.json").read_text())
    assert meta["num_frames"] == 11 and meta["meta"]["skipped"]["bad_pose"] == 1
    report = json.loads((out / "run.json").read_text())
    assert report["input_problems"] == 1 and report["failed"] == 0
