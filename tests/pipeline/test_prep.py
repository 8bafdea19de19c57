"""prep's object proxies: models that are not closed solids as given are repaired into solids (issue 19).

The volume reference is Open3D's ray-parity occupancy of the model as given (Monte Carlo over its
bounding box), which does not care how the faces are oriented: it is not meshprep's code and not the
signed-tetrahedra volume that meshprep and trimesh both compute.
"""

from __future__ import annotations

import numpy as np
import pytest

from meshprep.creation import box
from pipeline.prep import object_proxy


def _occupancy_volume(v: np.ndarray, f: np.ndarray, n: int = 200_000) -> float:
    from meshprep.metrics import open3d_module

    o3d = open3d_module()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(f.astype(np.uint32)))
    lo, hi = v.min(0), v.max(0)
    p = lo + np.random.default_rng(0).random((n, 3)) * (hi - lo)
    inside = scene.compute_occupancy(o3d.core.Tensor(p.astype(np.float32)), nsamples=3).numpy()
    return float(inside.mean() * np.prod(hi - lo))


def test_closed_solid_is_used_as_given():
    v, f = box((0.1, 0.2, 0.3))
    pr = object_proxy(v, f, 500.0, where="box")
    assert str(pr["repair"]) == "none" and int(pr["fallback_hull"]) == 0
    assert float(pr["mass"]) == pytest.approx(0.1 * 0.2 * 0.3 * 500.0, rel=1e-9)


def test_flipped_faces_are_repaired_into_a_solid_not_a_hull(caplog):
    """Two disjoint boxes (their hull is far larger than they are) with one face flipped in each."""
    a_v, a_f = box((0.2, 0.1, 0.1))
    b_v, b_f = box((0.1, 0.1, 0.1))
    b_v = b_v + [0.05, 0.11, 0.0]         # beside one end of the first box, 1 cm apart
    v = np.vstack([a_v, b_v])
    f = np.vstack([a_f, b_f + len(a_v)])
    f[[1, 13]] = f[[1, 13]][:, ::-1]      # one flipped face in each box
    with caplog.at_level("INFO", logger="pipeline.prep"):
        pr = object_proxy(v, f, 1000.0, where="two boxes")
    assert int(pr["fallback_hull"]) == 0
    assert str(pr["repair"]) == "repaired: orient faces coherently (faces_flipped 2)"
    assert float(pr["volume"]) == pytest.approx(0.2 * 0.1 * 0.1 + 0.1 ** 3, rel=1e-6)
    assert "two boxes: not a closed solid as given" in caplog.text


def test_every_lmo_model_becomes_a_closed_solid(shared_data):
    """All eight LM-O models: mass properties from the shape (two need their orientation repaired)."""
    import trimesh

    models = sorted((shared_data / "objects" / "lmo" / "models").glob("obj_*.ply"))
    assert len(models) == 8
    repaired = {}
    for path in models:
        m = trimesh.load(path, process=False)
        v, f = np.asarray(m.vertices) * 1e-3, np.asarray(m.faces)
        pr = object_proxy(v, f, 1000.0, where=path.name)
        assert int(pr["fallback_hull"]) == 0, (path.name, str(pr["repair"]))
        ref = _occupancy_volume(v, f)
        assert float(pr["volume"]) == pytest.approx(ref, rel=0.02), path.name
        hull = trimesh.Trimesh(v, f).convex_hull.volume
        assert float(pr["volume"]) < 0.99 * hull, path.name  # not the convex hull's
        if str(pr["repair"]) != "none":
            repaired[path.name] = str(pr["repair"])
    assert set(repaired) == {"obj_000005.ply", "obj_000010.ply"}, repaired
    assert all(r.startswith("repaired: orient faces coherently") for r in repaired.values())
