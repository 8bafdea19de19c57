"""meshprep.proxy: room distance grids against analytic planes; object proxies."""

from __future__ import annotations

import numpy as np
import pytest

from meshprep import stress
from meshprep.creation import box
from meshprep.errors import InputError
from meshprep.io import load_npz, meshset_from_arrays
from meshprep.proxy import object_parts, proxy, room_distance_grid


def _floor(n=40, z=0.5, size=2.0):
    v, f = stress.terrain(n, defects=False)
    v = v * (size / 4.0)
    v[:, 2] = z                      # flat floor at height z, normals +z
    return v, f


def test_room_udf_of_a_plane_is_height_and_clipped():
    v, f = _floor()
    g = room_distance_grid(v, f, spacing=0.05, max_distance=0.2, band_voxels=2)
    u = g["udf"]
    assert u.dtype == np.float32 and g["origin"].shape == (3,) and float(g["spacing"]) == 0.05
    ii, jj, kk = np.meshgrid(*(np.arange(s) for s in u.shape), indexing="ij")
    p = g["origin"] + 0.05 * np.stack([ii, jj, kk], -1)
    inside = (p[..., 0] >= 0) & (p[..., 0] <= 2) & (p[..., 1] >= 0) & (p[..., 1] <= 2)
    truth = np.minimum(np.abs(p[..., 2] - 0.5), 0.2)
    near = inside & (np.abs(p[..., 2] - 0.5) <= 0.1 + 1e-9)
    assert np.allclose(u[near], truth[near], atol=1e-5)          # exact band
    # Beyond the band: grid distance, within sqrt(3)/2 voxel of the truth, never above the clip.
    assert np.abs(u[inside] - truth[inside]).max() <= 0.5 * np.sqrt(3) * 0.05 + 1e-6
    assert u.max() <= 0.2 + 1e-7
    exact = room_distance_grid(v, f, spacing=0.05, max_distance=0.2, band_voxels=0)["udf"]
    assert np.allclose(exact[inside], truth[inside], atol=1e-5)


def test_room_sdf_sign_from_cameras():
    v, f = _floor()
    g = room_distance_grid(v, f[:, ::-1], spacing=0.05, max_distance=0.2,
                           cameras=np.array([[1.0, 1.0, 1.6]]))
    sdf, ok = g["sdf"], g["sdf_valid"]
    z = g["origin"][2] + 0.05 * np.arange(sdf.shape[2])
    mid = sdf[sdf.shape[0] // 2, sdf.shape[1] // 2]
    okm = ok[sdf.shape[0] // 2, sdf.shape[1] // 2]
    above, below = (z > 0.52) & (z < 0.65), (z < 0.48) & (z > 0.35)
    assert (mid[above] > 0).all() and (mid[below] < 0).all()
    assert okm[above].all() and okm[below].all()
    assert np.allclose(np.abs(sdf), g["udf"])


def test_room_grid_size_guard():
    v, f = _floor(size=2000.0)          # a "room" in millimetres
    with pytest.raises(InputError, match="--spacing|--scale"):
        room_distance_grid(v, f, spacing=0.02)


def test_object_proxy_file_is_deterministic(tmp_path):
    v, f = box((0.1, 0.2, 0.3))
    p = tmp_path / "b.ply"
    meshset_from_arrays(v, f).save_current_mesh(str(p))
    rep = proxy(p, tmp_path / "a.npz", samples=500, seed=1)
    proxy(p, tmp_path / "b.npz", samples=500, seed=1)
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    z = load_npz(tmp_path / "a.npz")
    assert rep["kind"] == "object" and float(z["mass"]) == pytest.approx(1000 * 0.006)
    assert z["samples"].shape == (500, 3) and z["sample_normals"].shape == (500, 3)
    assert np.allclose(np.linalg.norm(z["sample_normals"], axis=1), 1.0)
    # Samples on the box surface with outward normals: |coordinate| = half extent along the normal.
    ax = np.abs(z["sample_normals"]).argmax(1)
    half = np.array([0.05, 0.1, 0.15])
    assert np.allclose(np.abs(z["samples"][np.arange(500), ax]), half[ax])
    assert (np.sign(z["samples"][np.arange(500), ax]) == np.sign(z["sample_normals"][np.arange(500), ax])).all()
    assert len(z["parts_face_counts"]) == 0 and object_parts(z) == []
    assert z["inertia"].shape == (3, 3) and z["com"].shape == (3,)


def test_object_proxy_parts_of_a_torus(tmp_path):
    from meshprep.creation import torus

    v, f = torus(0.1, 0.03, major_segments=48, minor_segments=16)
    p = tmp_path / "t.ply"
    meshset_from_arrays(v, f).save_current_mesh(str(p))
    proxy(p, tmp_path / "t.npz", kind="object")
    z = load_npz(tmp_path / "t.npz")
    parts = object_parts(z)
    assert len(parts) >= 2
    for pv, pf in parts:
        assert pf.min() >= 0 and pf.max() < len(pv)


def test_room_proxy_file_and_auto_kind(tmp_path):
    v, f = _floor(n=20)
    p = tmp_path / "floor.ply"
    meshset_from_arrays(v, f).save_current_mesh(str(p))
    rep = proxy(p, tmp_path / "r.npz", spacing=0.1)
    assert rep["kind"] == "room" and not rep["signed"]
    z = load_npz(tmp_path / "r.npz")
    assert set(z) == {"origin", "spacing", "udf", "max_distance"}
    with pytest.raises(InputError, match="npz"):
        proxy(p, tmp_path / "r.ply")
