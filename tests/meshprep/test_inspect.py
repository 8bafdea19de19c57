"""meshprep.inspect: counts and defect detection on meshes with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from meshprep import stress
from meshprep.creation import box, sphere
from meshprep.inspect import guess_units, inspect, inspect_arrays


def test_closed_sphere_is_watertight_with_volume():
    v, f = sphere(1.0, stacks=16, slices=32)
    r = inspect_arrays(v, f)
    assert r["watertight"] and r["manifold"] and r["oriented"]
    assert r["holes"] == 0 and r["boundary_edges"] == 0 and r["components"] == 1
    assert r["volume"] == pytest.approx(4 / 3 * np.pi, rel=0.05)
    assert r["self_intersecting_faces"] == 0
    assert r["edges"] - r["vertices"] - r["faces"] == 0 or r["vertices"] - r["edges"] + r["faces"] == 2


def test_holes_are_counted():
    v, f = box()
    r = inspect_arrays(v, f[2:])          # one side (two triangles) removed: one 4-edge hole
    assert not r["watertight"] and r["manifold"] and r["volume"] is None
    assert r["holes"] == 1 and r["largest_hole_edges"] == 4 and r["boundary_edges"] == 4
    r = inspect_arrays(v, f[4:])          # the -x and +x sides removed: two 4-edge holes
    assert r["holes"] == 2 and r["largest_hole_edges"] == 4 and r["components"] == 1
    r = inspect_arrays(*stress.holes())
    assert r["holes"] >= 4 and not r["watertight"]


def test_bowtie_vertex_and_fan_edge():
    r = inspect_arrays(*stress.bowtie())
    assert r["non_manifold_vertices"] == 1 and r["non_manifold_edges"] == 0 and not r["manifold"]
    r = inspect_arrays(*stress.nonmanifold_fan())
    assert r["non_manifold_edges"] == 1 and not r["manifold"]


def test_defect_counts():
    r = inspect_arrays(*stress.duplicates())
    assert r["duplicate_vertices"] > 0 and r["duplicate_faces"] == len(stress._ball()[1][::10])
    r = inspect_arrays(*stress.degenerate())
    assert r["degenerate_faces"] == 3 and r["sliver_faces"] >= 1   # 2 repeated-index, 1 collinear
    r = inspect_arrays(*stress.non_finite())
    assert r["non_finite_vertices"] == 3 and r["non_finite_faces"] > 0
    assert np.isfinite(np.array(r["bounds"])).all()
    r = inspect_arrays(*stress.isolated())
    assert r["unreferenced_vertices"] == 100
    r = inspect_arrays(*stress.flipped())
    assert r["inconsistent_orientation_edges"] > 0 and not r["oriented"]
    r = inspect_arrays(*stress.self_intersecting())
    assert r["self_intersecting_faces"] > 0 and r["components"] == 2


def test_empty_arrays():
    r = inspect_arrays(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32))
    assert r["faces"] == 0 and not r["watertight"] and r["bounds"] is None


@pytest.mark.parametrize("diag,unit", [(0.2, "metres"), (7.5, "metres"), (142.0, "millimetres"),
                                       (1e-5, "unknown"), (1e7, "unknown"), (float("nan"), "unknown")])
def test_units_guess(diag, unit):
    assert guess_units(diag) == unit


def test_inspect_file_reports_colours(tmp_path):
    from meshprep.io import meshset_from_arrays

    v, f = box()
    ms = meshset_from_arrays(v, f, vertex_colors=np.full((8, 3), 200, np.uint8))
    ms.save_current_mesh(str(tmp_path / "b.ply"))
    r = inspect(tmp_path / "b.ply")
    assert r["vertex_colors"] and r["volume"] == pytest.approx(1.0) and r["file"].endswith("b.ply")
