"""The command line: exit codes, one-line errors for user mistakes, help, run-folder checks."""

from __future__ import annotations

import subprocess
import sys

import pytest

from pipeline.cli import CONFIG_NAME, META_NAME, main
from pipeline.config import load_config
from pipeline.stages import STAGE_ORDER


def _run(args, capsys):
    code = main([str(a) for a in args])
    err = capsys.readouterr().err
    return code, err


def _cfg(tmp_path, text):
    p = tmp_path / "c.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("text, words", [
    ("[run]\nsed = 1\n", ["run.sed", "valid keys"]),
    ("[run]\nseed = 'one'\n", ["run.seed", "integer"]),
    ("[simulate]\ndrops = -2\n", ["simulate.drops", ">= 0"]),
    ("[scan]\npaths = ['no/such/scan']\n", ["scan.paths", "does not exist"]),
    ("[objects]\npaths = ['missing.ply']\n", ["objects.paths", "does not exist"]),
])
def test_bad_configs_exit_2_with_one_line(tmp_path, capsys, text, words):
    code, err = _run(["run", _cfg(tmp_path, text), "--out", tmp_path / "out"], capsys)
    _assert_one_line_error(code, err, words, tmp_path / "out")


def _assert_one_line_error(code, err, words, out):
    """Exit 2, one line ``scansynth: error: ...`` holding ``words``, and no run folder made."""
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("scansynth: error:"), err
    for w in words:
        assert w in err
    assert not out.exists()


def test_missing_config_file_and_bad_override(tmp_path, capsys):
    code, err = _run(["run", tmp_path / "nope.toml", "--out", tmp_path / "o"], capsys)
    assert code == 2 and "does not exist" in err
    code, err = _run(["run", _cfg(tmp_path, ""), "--out", tmp_path / "o", "--set", "seed5"], capsys)
    assert code == 2 and "table.key=value" in err


def test_usage_errors_exit_2():
    with pytest.raises(SystemExit) as e:
        main([])
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        main(["run"])
    assert e.value.code == 2


@pytest.mark.parametrize("cmd", ["run", *STAGE_ORDER, "make-scan"])
def test_help_on_every_command(cmd, capsys):
    with pytest.raises(SystemExit) as e:
        main([cmd, "--help"])
    assert e.value.code == 0
    assert "usage:" in capsys.readouterr().out


def test_run_folder_records_config_seed_versions_and_refuses_other_configs(tmp_path, capsys):
    out = tmp_path / "out"
    cfg = _cfg(tmp_path, "[run]\nseed = 4\n[scan]\npaths = []\n[objects]\npaths = [\"builtin:shapes\"]\n")
    code, _ = _run(["run", cfg, "--out", out, "--to", "ingest", "-q"], capsys)
    assert code == 0
    assert load_config(out / CONFIG_NAME).run.seed == 4
    meta = (out / META_NAME).read_text()
    assert '"seed": 4' in meta and '"numpy"' in meta
    # Resuming with workers changed is fine; with another seed it is refused.
    code, _ = _run(["run", cfg, "--out", out, "--to", "ingest", "-q", "--set", "run.workers=2"], capsys)
    assert code == 0
    code, err = _run(["run", cfg, "--out", out, "--set", "run.seed=5"], capsys)
    assert code == 2 and "different config" in err and "run.seed" in err


def test_stage_command_needs_a_run_folder(tmp_path, capsys):
    code, err = _run(["ingest", tmp_path / "empty"], capsys)
    assert code == 2 and "not a run folder" in err


def test_refuses_a_foreign_nonempty_folder(tmp_path, capsys):
    (tmp_path / "stuff").mkdir()
    (tmp_path / "stuff" / "important.txt").write_text("x")
    code, err = _run(["run", _cfg(tmp_path, ""), "--out", tmp_path / "stuff"], capsys)
    assert code == 2 and "not a scansynth run folder" in err


def test_no_traceback_from_the_real_entry_point(tmp_path):
    p = _cfg(tmp_path, "[run]\nworkers = -1\n")
    r = subprocess.run([sys.executable, "-m", "pipeline", "run", str(p), "--out", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and "run.workers" in r.stderr


@pytest.mark.parametrize("content, words", [
    (None, ["trace.lights_file", "does not exist"]),
    ('{"corners": []}', ["trace.lights_file", "lamps.json", "JSON list"]),
    ('[{"corners": [[0, 0, 2], [1, 0, 2], [1, 1, 2]], "radiance": [1, 1, 1]}]',
     ["trace.lights_file", "lamps.json", "emitter 0", "4 x 3"]),
    ('[{"corners": [[0, 0, 2], [1, 0, 2], [1, 1, 2], [0, 1, 2]], "radiance": [1, -1, 1]}]',
     ["lamps.json", "emitter 0", ">= 0"]),
])
def test_bad_lights_file_is_a_config_error(tmp_path, capsys, content, words):
    """A lights file is read when the config loads (relative to the config's folder): a bad one stops the
    run before any stage, in one line naming the file and the entry."""
    if content is not None:
        (tmp_path / "lamps.json").write_text(content)
    code, err = _run(["run", _cfg(tmp_path, "[trace]\nlights_file = 'lamps.json'\n"), "--out", tmp_path / "out"],
                     capsys)
    _assert_one_line_error(code, err, words, tmp_path / "out")


def test_lights_complete_without_a_lights_file_is_a_config_error(tmp_path, capsys):
    """trace.lights_complete says the lights file holds every light: without one it is a one-line error naming
    the key, the file it is in and the fix; with one it loads."""
    code, err = _run(["run", _cfg(tmp_path, "[trace]\nlights_complete = true\n"), "--out", tmp_path / "out"], capsys)
    _assert_one_line_error(code, err, ["c.toml", "trace.lights_complete", "lights_file"], tmp_path / "out")
    (tmp_path / "lamps.json").write_text('[{"corners": [[0, 0, 2], [1, 0, 2], [1, 1, 2], [0, 1, 2]], '
                                         '"radiance": [3, 3, 3]}]')
    cfg = load_config(_cfg(tmp_path, "[trace]\nlights_complete = true\nlights_file = 'lamps.json'\n"))
    assert cfg.trace.lights_complete


def test_good_lights_file_is_resolved_from_the_config_folder(tmp_path):
    (tmp_path / "lamps.json").write_text('[{"corners": [[0, 0, 2], [1, 0, 2], [1, 1, 2], [0, 1, 2]], '
                                         '"radiance": [3, 3, 3]}]')
    cfg = load_config(_cfg(tmp_path, "[trace]\nlights_file = 'lamps.json'\n"))
    assert cfg.trace.lights_file == str((tmp_path / "lamps.json").resolve())
