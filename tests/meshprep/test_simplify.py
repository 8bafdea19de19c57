"""meshprep.simplify: face targets, error bounds, colours/UVs and boundaries kept."""

from __future__ import annotations

import json

import numpy as np
import pytest

from meshprep import stress
from meshprep.errors import InputError
from meshprep.inspect import edge_topology, inspect
from meshprep.io import load_arrays, meshset_from_arrays
from meshprep.simplify import simplify


@pytest.fixture(scope="module")
def coloured_terrain(tmp_path_factory):
    v, f = stress.terrain(100, defects=False)
    col = np.column_stack([(v[:, 0] * 60) % 255, (v[:, 1] * 60) % 255, np.full(len(v), 128)])
    p = tmp_path_factory.mktemp("s") / "t.ply"
    meshset_from_arrays(v, f, vertex_colors=col.astype(np.uint8)).save_current_mesh(str(p))
    return p


def _border_vertices(v, f):
    t = edge_topology(f, len(v))
    return v[np.unique(t["edges"][t["counts"] == 1])]


def test_target_faces_colours_and_border(coloured_terrain, tmp_path):
    out = tmp_path / "s.ply"
    rep = simplify(coloured_terrain, out, target_faces=2000)
    assert rep["after"]["faces"] <= 2000 and rep["reduction"] > 9
    assert inspect(out)["vertex_colors"]
    d = rep["deviation"]
    assert 0 < d["mean"] <= d["p95"] <= d["max"] and d["p95_rel"] < 0.01
    # The open border stays in place: every simplified border vertex lies on the original border
    # (the 4 m square's sides), within 1 cm (a quarter grid step) when weighted, exactly when locked.
    v0, f0 = load_arrays(coloured_terrain)
    for mode, tol in (("weighted", 1e-2), ("locked", 1e-9)):
        if mode == "locked":
            simplify(coloured_terrain, out, target_faces=2000, boundary=mode, samples=2000)
        v1, f1 = load_arrays(out)
        b1 = _border_vertices(v1, f1)
        side = np.minimum(np.minimum(np.abs(b1[:, 0]), np.abs(b1[:, 0] - 4)),
                          np.minimum(np.abs(b1[:, 1]), np.abs(b1[:, 1] - 4)))
        assert side.max() <= tol and len(b1) > 20, mode
    with pytest.raises(InputError, match="boundary"):
        simplify(coloured_terrain, out, target_faces=2000, boundary="sticky")
    assert json.loads((tmp_path / "s.ply.report.json").read_text())["after"]["faces"] == rep["after"]["faces"]


def test_max_error_is_met_and_smaller_than_input(coloured_terrain, tmp_path):
    v0, _ = load_arrays(coloured_terrain)
    bound = 0.002
    rep = simplify(coloured_terrain, tmp_path / "e.ply", max_error=bound, error_stat="p95", samples=8000)
    assert rep["deviation"]["p95"] <= bound
    assert rep["after"]["faces"] < rep["before"]["faces"] / 2
    assert any(not t["ok"] for t in rep["tries"])          # the search found the edge
    tighter = simplify(coloured_terrain, tmp_path / "e2.ply", max_error=bound / 4, error_stat="p95",
                       samples=8000)
    assert tighter["after"]["faces"] > rep["after"]["faces"]


def test_relative_bound_and_usage_errors(coloured_terrain, tmp_path):
    rep = simplify(coloured_terrain, tmp_path / "r.ply", max_error=0.001, relative=True, samples=5000)
    assert rep["deviation"]["max_rel"] <= 0.001
    with pytest.raises(InputError, match="exactly one"):
        simplify(coloured_terrain, tmp_path / "x.ply")
    with pytest.raises(InputError, match="exactly one"):
        simplify(coloured_terrain, tmp_path / "x.ply", target_faces=10, max_error=1.0)
    with pytest.raises(InputError, match="positive"):
        simplify(coloured_terrain, tmp_path / "x.ply", target_faces=0)
    with pytest.raises(InputError, match="xyz"):
        simplify(coloured_terrain, tmp_path / "x.xyz", target_faces=10)


@pytest.mark.shared_data
def test_textured_model_keeps_uvs_and_texture(shared_data, tmp_path):
    src = shared_data / "objects/ycb-textured/003_cracker_box_textured.gltf"
    out = tmp_path / "box.obj"
    rep = simplify(src, out, target_faces=4000, samples=20000)
    st = inspect(out)
    assert st["uvs"] and st["textures"] == 1 and rep["after"]["faces"] <= 4000
    assert (tmp_path / "003_cracker_box_textured.png").is_file()


@pytest.mark.slow
def test_parallel_slabs_weld_back(coloured_terrain, tmp_path):
    one = simplify(coloured_terrain, tmp_path / "1.ply", target_faces=3000, workers=1, samples=5000)
    two = simplify(coloured_terrain, tmp_path / "2.ply", target_faces=3000, workers=2, samples=5000)
    s1, s2 = inspect(tmp_path / "1.ply"), inspect(tmp_path / "2.ply")
    assert s2["components"] == 1 and s2["manifold"] and s2["vertex_colors"]
    assert s2["holes"] == s1["holes"] == 1                    # the seam is welded: only the outer border
    assert abs(two["after"]["faces"] - 3000) < 300
    assert two["deviation"]["p95"] < 2 * one["deviation"]["p95"] + 1e-4
