"""The stage contract: done markers, resume, failures, determinism across worker counts."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.config import build_config
from pipeline.runner import is_done, item_results, run_stage
from tests.pipeline.stage_fixtures import ARRAYS, FAILING

REF = "tests.pipeline.stage_fixtures:ARRAYS"


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_runs_every_item_and_writes_markers(tmp_path):
    cfg = build_config({})
    rep = run_stage(tmp_path, cfg, ARRAYS, stage_ref=REF)
    assert (rep.total, rep.done, rep.skipped, rep.failed) == (6, 6, 0, 0)
    assert all(is_done(tmp_path, "arrays", f"scene/f{i:03d}") for i in range(6))
    assert len(item_results(tmp_path, "arrays")) == 6


def test_finished_items_are_skipped_on_resume(tmp_path):
    cfg = build_config({})
    run_stage(tmp_path, cfg, ARRAYS, stage_ref=REF)
    # Lose one item's output and marker, as if the run had been killed before finishing it.
    (tmp_path / "arrays" / "scene" / "f003.npz").unlink()
    (tmp_path / "arrays" / "_items" / "scene" / "f003.done.json").unlink()
    before = (tmp_path / "arrays" / "scene" / "f001.npz").stat().st_mtime_ns
    rep = run_stage(tmp_path, cfg, ARRAYS, stage_ref=REF)
    assert (rep.done, rep.skipped) == (1, 5)
    assert (tmp_path / "arrays" / "scene" / "f003.npz").is_file()
    assert (tmp_path / "arrays" / "scene" / "f001.npz").stat().st_mtime_ns == before


def test_same_seed_same_bytes_whatever_the_workers(tmp_path):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    run_stage(a, build_config({"run": {"seed": 7}}), ARRAYS, stage_ref=REF)
    run_stage(b, build_config({"run": {"seed": 7, "workers": 2}}), ARRAYS, stage_ref=REF)
    run_stage(c, build_config({"run": {"seed": 8}}), ARRAYS, stage_ref=REF)
    assert _files(a) == _files(b)
    assert _files(a)["arrays/scene/f000.npz"] != _files(c)["arrays/scene/f000.npz"]


def test_seed_zero_is_a_seed(tmp_path):
    run_stage(tmp_path / "x", build_config({"run": {"seed": 0}}), ARRAYS, stage_ref=REF)
    run_stage(tmp_path / "y", build_config({"run": {"seed": 0}}), ARRAYS, stage_ref=REF)
    assert _files(tmp_path / "x") == _files(tmp_path / "y")


def test_failures_are_recorded_and_others_finish(tmp_path):
    ref = "tests.pipeline.stage_fixtures:FAILING"
    rep = run_stage(tmp_path, build_config({}), FAILING, stage_ref=ref)
    assert (rep.done, rep.failed) == (4, 2)
    user = rep.failures["scene/f002"]
    assert "bad depth file" in user and "Traceback" not in user
    bug = rep.failures["scene/f004"]
    assert "ValueError" in bug and "failed.json" in bug
    assert (tmp_path / "failing" / "_items" / "scene" / "f004.failed.json").is_file()
    # Failed items are retried on the next invocation; finished ones are not.
    rep2 = run_stage(tmp_path, build_config({}), FAILING, stage_ref=ref)
    assert (rep2.skipped, rep2.failed) == (4, 2)


def test_duplicate_item_keys_are_a_bug(tmp_path, monkeypatch):
    from pipeline.stages import Item, Stage

    dup = Stage(name="dup", plan=lambda ctx: [Item("a"), Item("a")], run_item=lambda c, i: None)
    with pytest.raises(RuntimeError, match="duplicate"):
        run_stage(tmp_path, build_config({}), dup)


def test_a_stage_that_cannot_plan_is_reported_not_raised(tmp_path):
    from tests.pipeline.stage_fixtures import PLAN_BUG, PLAN_USER

    rep = run_stage(tmp_path, build_config({}), PLAN_BUG)
    assert rep.failed == 1 and "KeyError" in rep.failures["(plan)"]
    assert (tmp_path / "planbug" / "_items" / "_plan.failed.json").is_file()
    rep = run_stage(tmp_path, build_config({}), PLAN_USER)
    assert rep.failed == 1 and rep.failures["(plan)"].startswith("scan folder /x")


def test_workers_warm_up_while_the_plan_runs_and_then_do_the_items(tmp_path, monkeypatch):
    """A stage with a ``warm`` step (trace: imports and the room mesh while the main process fits the lights)
    starts its workers before planning: the plan here returns only once both workers have warmed (it would
    wait 60 s and leave no warm files if they started after it), and those same processes do the items.
    The bytes are those of a run without the warm step; a warm step that fails costs nothing."""
    from tests.pipeline.stage_fixtures import WARMED

    ref = "tests.pipeline.stage_fixtures:WARMED"
    cfg = build_config({"run": {"workers": 2, "seed": 3}})
    run = tmp_path / "warm_run"
    rep = run_stage(run, cfg, WARMED, stage_ref=ref)
    assert (rep.done, rep.failed) == (6, 0)
    warmed = {int(p.name) for p in (run / "warm").iterdir()}
    assert len(warmed) == 2
    assert {r["pid"] for r in item_results(run, "warmed").values()} <= warmed
    plain = tmp_path / "plain"
    run_stage(plain, build_config({"run": {"workers": 1, "seed": 3}}), WARMED, stage_ref=ref)  # no pool, no warm
    assert not (plain / "warm").exists()
    npz = sorted((run / "warmed" / "scene").glob("*.npz"))
    assert [p.read_bytes() for p in npz] == [(plain / "warmed" / "scene" / p.name).read_bytes() for p in npz]

    monkeypatch.setenv("SS_TEST_WARM_FAILS", "1")
    broken = tmp_path / "broken"
    (broken / "warm").mkdir(parents=True)
    for fake in ("1", "2"):   # lets the plan go on (the warm step leaves nothing)
        (broken / "warm" / fake).write_text("")
    rep = run_stage(broken, cfg, WARMED, stage_ref=ref)
    assert (rep.done, rep.failed) == (6, 0)
    assert {p.name for p in (broken / "warm").iterdir()} == {"1", "2"}


def test_a_worker_that_dies_warming_up_costs_only_its_warm_up(tmp_path):
    """A warm worker killed during the plan (out of memory, a crash in native code) breaks the pool it was in:
    the items run on fresh workers instead of the stage ending in a traceback."""
    from tests.pipeline.stage_fixtures import WARM_DIES

    run = tmp_path / "run"
    rep = run_stage(run, build_config({"run": {"workers": 2}}), WARM_DIES,
                    stage_ref="tests.pipeline.stage_fixtures:WARM_DIES")
    assert any((run / "died").iterdir())
    assert (rep.done, rep.failed) == (6, 0)
