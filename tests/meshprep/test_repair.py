"""meshprep.repair on the generated stress corpus: repaired and passing inspect, or a clear error."""

from __future__ import annotations

import json

import numpy as np
import pytest

from meshprep import constants, stress
from meshprep.cli import main
from meshprep.errors import InputError, RepairError
from meshprep.inspect import inspect
from meshprep.io import load_arrays, meshset_from_arrays
from meshprep.repair import repair


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    return stress.write_corpus(tmp_path_factory.mktemp("corpus"))


def _same(a, b):
    return all(x.shape == y.shape and np.array_equal(x, y) for x, y in zip(a, b))


@pytest.mark.parametrize("name", list(stress.generators()) + ["empty", "wrong_extension", "truncated",
                                                               "garbage_obj"])
def test_stress_case(name, corpus, tmp_path, capsys):
    path, expect = corpus[name]
    out = tmp_path / "out.ply"
    rc = main(["repair", str(path), str(out)])
    err = capsys.readouterr().err
    if expect.startswith("error"):
        assert rc == 2
        lines = err.strip().splitlines()
        assert len(lines) == 1 and str(path) in lines[0]
        assert not out.exists()
        return
    assert rc == 0, err
    stats = inspect(out)
    assert stats["manifold"] and stats["oriented"] and stats["non_finite_vertices"] == 0
    assert stats["degenerate_faces"] == 0 and stats["duplicate_faces"] == 0
    assert stats["unreferenced_vertices"] == 0
    if expect == "object":
        assert stats["watertight"] and stats["volume"] > 0
    report = json.loads((tmp_path / "out.ply.report.json").read_text())
    assert report["ok"] and report["kind"] == expect
    assert {"before", "after", "changes", "seconds"} <= report.keys()
    # Idempotent: repairing the output changes nothing.
    out2 = tmp_path / "out2.ply"
    rep2 = repair(out, out2)
    assert rep2["changes"] == []
    assert _same(load_arrays(out), load_arrays(out2))


def test_object_repair_of_open_surface_fails_clearly(tmp_path):
    v, f = stress.terrain(40, defects=False)
    p = tmp_path / "t.ply"
    stress.write_mesh(p, v, f)
    with pytest.raises(RepairError, match="could not repair as object.*--kind scan"):
        repair(p, tmp_path / "o.ply", kind="object", max_hole_edges=20)
    assert not (tmp_path / "o.ply").exists()
    assert json.loads((tmp_path / "o.ply.report.json").read_text())["ok"] is False


def test_only_non_finite_is_nothing_left(tmp_path):
    v = np.full((3, 3), np.nan)
    p = stress.write_mesh(tmp_path / "nan.ply", v, np.array([[0, 1, 2]]))
    assert main(["repair", str(p), str(tmp_path / "o.ply")]) in (1, 2)


def test_far_away_keeps_precision(corpus, tmp_path):
    near = repair(corpus["holes"][0], tmp_path / "n.ply")["after"]
    far = repair(corpus["far_away"][0], tmp_path / "f.ply")["after"]
    assert far["volume"] == pytest.approx(near["volume"], rel=1e-6)
    assert far["faces"] == near["faces"]


def test_holes_closed_by_size_on_scans(tmp_path):
    v, f = stress.terrain(80)
    p = stress.write_mesh(tmp_path / "t.ply", v, f)
    small = repair(p, tmp_path / "a.ply", kind="scan", max_hole_edges=8)["after"]
    big = repair(p, tmp_path / "b.ply", kind="scan", max_hole_edges=200)["after"]
    assert big["holes"] < small["holes"]
    assert big["manifold"] and not big["watertight"]   # the outer border stays open


def test_cameras_orient_a_scan(tmp_path):
    v, f = stress.terrain(30, defects=False)
    p = stress.write_mesh(tmp_path / "down.ply", v, f[:, ::-1])    # normals point down (-z)
    cams = tmp_path / "cams.txt"
    np.savetxt(cams, [[2.0, 2.0, 3.0], [1.0, 1.0, 2.0]])
    rep = repair(p, tmp_path / "up.ply", cameras=cams)
    assert rep["kind"] == "scan"
    vv, ff = load_arrays(tmp_path / "up.ply")
    n = np.cross(vv[ff[:, 1]] - vv[ff[:, 0]], vv[ff[:, 2]] - vv[ff[:, 0]])
    assert (n[:, 2] > 0).all()
    # Poses as 4x4 camera-to-world rows work too; a bad camera file is a usage error.
    T = np.tile(np.eye(4), (2, 1, 1))
    T[:, :3, 3] = [[2.0, 2.0, 3.0], [1.0, 1.0, 2.0]]
    np.save(tmp_path / "poses.npy", T)
    assert repair(p, tmp_path / "up2.ply", cameras=tmp_path / "poses.npy")["kind"] == "scan"
    np.savetxt(tmp_path / "bad.txt", np.ones((2, 5)))
    with pytest.raises(InputError, match="bad.txt"):
        repair(p, tmp_path / "x.ply", cameras=tmp_path / "bad.txt")


def test_colours_survive_repair(tmp_path):
    v, f = stress.holes()
    col = (np.abs(v) * 255).clip(0, 255).astype(np.uint8)
    ms = meshset_from_arrays(v, f, vertex_colors=col)
    ms.save_current_mesh(str(tmp_path / "c.ply"))
    repair(tmp_path / "c.ply", tmp_path / "o.ply")
    assert inspect(tmp_path / "o.ply")["vertex_colors"]


@pytest.mark.slow
def test_200k_face_scan(tmp_path):
    v, f = stress.terrain(335)
    assert len(f) > 200_000
    p = stress.write_mesh(tmp_path / "big.ply", v, f)
    rep = repair(p, tmp_path / "o.ply", self_intersections=False)
    assert rep["ok"] and rep["after"]["manifold"] and rep["kind"] == "scan"


@pytest.mark.shared_data
def test_lmo_model_is_an_object(shared_data, tmp_path):
    for p in sorted((shared_data / "objects/lmo/models").glob("obj_*.ply"))[:1]:
        rep = repair(p, tmp_path / p.name)
        assert rep["kind"] == "object" and rep["after"]["watertight"]
        assert inspect(tmp_path / p.name)["vertex_colors"]


@pytest.mark.parametrize("name", ["holes", "flipped", "bowtie", "duplicates", "junk", "terrain"])
def test_repair_statistics_are_those_of_the_result(name):
    """The repair loop reuses its last topology analysis as the 'after' statistics and skips the
    confirming pass when that analysis proves it a no-op: the statistics must equal a fresh
    inspection of the result, and a further pass must change nothing."""
    from meshprep.inspect import inspect_arrays
    from meshprep.io import arrays_of
    from meshprep.repair import _repair_meshset, repair_meshset

    v, f = stress.terrain(60) if name == "terrain" else stress.generators()[name][0]()
    ms = meshset_from_arrays(v, f)
    info, stats = _repair_meshset(ms, kind="auto", cameras=None, max_hole_edges=None,
                                  junk_diag_rel=constants.JUNK_COMPONENT_DIAG_REL,
                                  junk_faces=constants.JUNK_COMPONENT_FACES)
    result = arrays_of(ms)
    assert stats == inspect_arrays(*result, self_intersections=False)
    again = repair_meshset(ms, kind=info["kind"])
    assert again["changes"] == [] and again["passes"] == 1
    assert _same(result, arrays_of(ms))
