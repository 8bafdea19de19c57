"""meshprep.cli: help everywhere, exit codes, one-line errors, JSON output."""

from __future__ import annotations

import json

import numpy as np
import pytest

from meshprep import stress
from meshprep.cli import main
from meshprep.creation import box


@pytest.mark.parametrize("cmd", [[], ["inspect"], ["repair"], ["simplify"], ["solid"], ["proxy"]])
def test_help_everywhere(cmd, capsys):
    assert main(cmd + ["--help"]) == 0
    assert "usage: meshprep" in capsys.readouterr().out


@pytest.mark.parametrize("argv", [[], ["frobnicate"], ["repair", "only_one.ply"],
                                  ["simplify", "a.ply", "b.ply"],
                                  ["simplify", "a.ply", "b.ply", "--target-faces", "x"]])
def test_usage_errors_exit_2(argv, capsys):
    assert main(argv) == 2
    assert "usage" in capsys.readouterr().err


def test_missing_input_is_one_line_naming_the_file(tmp_path, capsys):
    assert main(["inspect", str(tmp_path / "nope.ply")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope.ply" in err[0] and "check the path" in err[0]


def test_inspect_json_and_text(tmp_path, capsys):
    p = stress.write_mesh(tmp_path / "b.ply", *box())
    assert main(["inspect", str(p), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["watertight"] and rep["volume"] == pytest.approx(1.0)
    assert main(["inspect", str(p)]) == 0
    assert "watertight" in capsys.readouterr().out


def test_pipeline_of_commands(tmp_path, capsys):
    p = stress.write_mesh(tmp_path / "h.ply", *stress.holes())
    assert main(["repair", str(p), str(tmp_path / "r.ply"), "--report", str(tmp_path / "rep.json")]) == 0
    assert json.loads((tmp_path / "rep.json").read_text())["after"]["watertight"]
    assert main(["simplify", str(tmp_path / "r.ply"), str(tmp_path / "s.ply"), "--target-faces", "500"]) == 0
    assert main(["solid", str(tmp_path / "s.ply"), str(tmp_path / "so.ply"), "--density", "2"]) == 0
    assert main(["proxy", str(tmp_path / "so.ply"), str(tmp_path / "p.npz"), "--samples", "64"]) == 0
    with np.load(tmp_path / "p.npz") as z:
        assert z["samples"].shape == (64, 3)
    capsys.readouterr()


def test_could_not_repair_exits_1(tmp_path, capsys):
    v, f = stress.terrain(30, defects=False)
    p = stress.write_mesh(tmp_path / "t.ply", v, f)
    assert main(["repair", str(p), str(tmp_path / "o.ply"), "--kind", "object",
                 "--max-hole-edges", "10"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "t.ply" in err[0] and "--kind scan" in err[0]
    assert main(["solid", str(p), str(tmp_path / "s.ply")]) in (0, 1)


def test_standalone_no_pipeline_import():
    import subprocess
    import sys

    code = ("import sys, meshprep, meshprep.cli, meshprep.proxy, meshprep.solid, meshprep.stress; "
            "bad = [m for m in sys.modules if m == 'pipeline' or m.startswith('pipeline.')]; "
            "heavy = [m for m in ('pymeshlab', 'open3d', 'manifold3d') if m in sys.modules]; "
            "print(bad, heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[] []"
