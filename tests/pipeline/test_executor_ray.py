"""The Ray executor runs the same items and writes the same bytes as the local one."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.config import build_config
from pipeline.runner import run_stage
from tests.pipeline.stage_fixtures import ARRAYS, FAILING

ray = pytest.importorskip("ray", reason="Ray is an optional extra (scansynth[ray]); not installed")


REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def local_ray():
    # One local instance for the module: ray.init() takes seconds. The test stages live in the
    # repository's tests package, outside the installed distribution: tell the workers where it is
    # (otherwise they see it only when the driver's sys.path happens to start at the repository).
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False,
             runtime_env={"env_vars": {"PYTHONPATH": str(REPO)}})
    yield
    ray.shutdown()


def _files(root):
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_ray_outputs_equal_local_outputs(tmp_path, local_ray):
    ref = "tests.pipeline.stage_fixtures:ARRAYS"
    run_stage(tmp_path / "local", build_config({"run": {"seed": 9}}), ARRAYS, stage_ref=ref)
    rep = run_stage(tmp_path / "ray", build_config({"run": {"seed": 9, "executor": "ray"}}), ARRAYS,
                    stage_ref=ref)
    assert (rep.done, rep.failed) == (6, 0)
    assert _files(tmp_path / "local") == _files(tmp_path / "ray")
    # Resume on Ray: nothing is redone.
    rep = run_stage(tmp_path / "ray", build_config({"run": {"seed": 9, "executor": "ray"}}), ARRAYS,
                    stage_ref=ref)
    assert (rep.done, rep.skipped) == (0, 6)


@pytest.mark.slow
def test_ray_records_item_failures_like_local(tmp_path, local_ray):
    rep = run_stage(tmp_path, build_config({"run": {"executor": "ray"}}), FAILING,
                    stage_ref="tests.pipeline.stage_fixtures:FAILING")
    assert (rep.done, rep.failed) == (4, 2)
    assert "bad depth file" in rep.failures["scene/f002"]
