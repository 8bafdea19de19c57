"""meshprep.solid: manifold3d solids, hulls and convex decomposition only where needed."""

from __future__ import annotations

import json

import numpy as np
import pytest

from meshprep import stress
from meshprep.constants import MASS_PROPERTIES_REL_TOL as TOL
from meshprep.creation import box, sphere, torus
from meshprep.errors import RepairError
from meshprep.inspect import inspect
from meshprep.solid import convex_hull, solid, solid_arrays, to_manifold


def test_convex_shapes_need_no_parts():
    for v, f in (box((1, 2, 3)), sphere(1.0, stacks=24, slices=48)):
        s = solid_arrays(v, f)
        assert s["parts"] == [] and s["hull_concavity"] < 1e-9 * s["diagonal"] + 1e-12
        assert s["volume"] == pytest.approx(s["manifold_volume"], rel=1e-9)


def test_torus_is_decomposed_into_pieces_within_tolerance():
    v, f = torus(1.0, 0.25, major_segments=64, minor_segments=24)
    s = solid_arrays(v, f, concavity_tol_rel=0.01)
    assert 2 <= len(s["parts"]) <= 32
    vol_parts = sum(to_manifold(pv, pf).volume() for pv, pf in s["parts"])
    # Convex pieces cover the torus: their volume is at least the torus', far below the hull's.
    hull_vol = to_manifold(s["hull_vertices"], s["hull_faces"]).volume()
    assert s["volume"] * (1 - TOL) <= vol_parts < 0.75 * hull_vol
    # Every piece is within the tolerance of its own hull.
    from meshprep.solid import concavity, convex_decomposition

    tol = 0.01 * s["diagonal"]
    pieces = convex_decomposition(to_manifold(v, f), tolerance=tol)
    assert all(concavity(p) <= tol for p in pieces) and len(pieces) == len(s["parts"])


def test_overlapping_parts_are_united():
    v, f = stress.self_intersecting()
    one = solid_arrays(*stress._ball())["volume"]
    s = solid_arrays(v, f)
    assert one < s["volume"] < 2 * one
    assert inspect_ok(s)


def inspect_ok(s):
    from meshprep.inspect import inspect_arrays

    r = inspect_arrays(s["vertices"], s["faces"], self_intersections=True)
    return r["watertight"] and r["manifold"] and r["self_intersecting_faces"] == 0


def test_open_mesh_is_refused():
    v, f = box()
    with pytest.raises(RepairError, match="not a closed"):
        to_manifold(v, f[2:])


def test_hull_of_points():
    pts = np.random.default_rng(0).normal(size=(500, 3)) + 1e6
    hv, hf = convex_hull(pts)
    assert len(hv) < 500 and np.allclose(hv.mean(0), 1e6, atol=2)
    from meshprep.mass import signed_volume

    assert signed_volume(hv, hf) > 0


def test_solid_file_with_scale_and_density(tmp_path):
    v, f = stress.holes()
    p = stress.write_mesh(tmp_path / "h.ply", v * 1000.0, f)      # millimetres
    out = tmp_path / "s.ply"
    rep = solid(p, out, density=500.0, scale=0.001)
    assert rep["ok"] and rep["volume"] == pytest.approx(4.06, rel=0.02)      # metres^3, holes capped
    assert rep["mass"] == pytest.approx(500.0 * rep["volume"])
    st = inspect(out)
    assert st["watertight"] and st["manifold"] and st["volume"] == pytest.approx(rep["volume"], rel=1e-6)
    assert json.loads((tmp_path / "s.ply.report.json").read_text())["convex_parts"] == 0
    with pytest.raises(Exception, match="density"):
        solid(p, out, density=-1.0)
