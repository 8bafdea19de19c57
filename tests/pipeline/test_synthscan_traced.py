"""Path-traced photo mode of the synthetic scan generator (pipeline/synthscan/render.py, trace/fullframe.py)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import UserError
from pipeline.seeding import item_rng
from pipeline.synthscan.render import (TracedPhotoRenderer, render_traced_view, room_trace_scene,
                                       traced_room_from_scan)
from pipeline.synthscan.room import make_room
from pipeline.synthscan.trajectory import look_at
from pipeline.tolerances import SYNTHSCAN_TRACED_RASTER_MEAN_RATIO


@pytest.fixture(scope="module")
def room():
    return make_room(item_rng(0, "synthscan", "room"))


def _table_view(room):
    """A low camera 2.1 m from the table, looking at the floor under the table top's centre.

    Returns (T_c2w, K, width, height, floor point under the table, unit horizontal direction to the camera).
    """
    q = next(i for i, p in enumerate(room.parts) if p.name == "table_top")
    part = room.parts[q]
    sl = slice(part.quad_start, part.quad_stop)
    c = (room.quad_origin[sl] + 0.5 * (room.quad_a[sl] + room.quad_b[sl])).mean(0)
    d = np.array([1.0, 0.0, 0.0]) if c[0] < room.size[0] / 2 else np.array([-1.0, 0.0, 0.0])
    floor = np.array([c[0], c[1], 0.0])
    T = look_at(floor + 2.1 * d + np.array([0.0, 0.0, 0.5]), floor)
    K = np.array([[46.0, 0.0, 31.5], [0.0, 46.0, 23.5], [0.0, 0.0, 1.0]])
    return T, K, 64, 48, floor, d


def _pixel(T, K, X):
    Tw = np.linalg.inv(T)
    p = Tw[:3, :3] @ X + Tw[:3, 3]
    return int(round(K[1, 1] * p[1] / p[2] + K[1, 2])), int(round(K[0, 0] * p[0] / p[2] + K[0, 2]))


def _shading(view):
    """Radiance over albedo (removes the floor texture): proportional to irradiance on a diffuse floor."""
    return view.radiance.mean(axis=2) / np.maximum(view.albedo.mean(axis=2), 1e-3)


def test_same_seed_same_bytes_other_seed_other_noise(room):
    T, K, w, h, _, _ = _table_view(room)
    a = render_traced_view(room, T, K, 24, 18, exposure=1.0, spp=2, seed=3)
    b = render_traced_view(room, T, K, 24, 18, exposure=1.0, spp=2, seed=3)
    c = render_traced_view(room, T, K, 24, 18, exposure=1.0, spp=2, seed=4)
    assert a.radiance.tobytes() == b.radiance.tobytes()
    assert a.radiance.tobytes() != c.radiance.tobytes()
    assert np.isfinite(a.radiance).all() and (a.radiance >= 0).all()


def test_soft_shadow_under_the_table(room):
    """Floor irradiance: in the open > at the table's edge (penumbra) > under the top (umbra, GI-lit)."""
    T, K, w, h, floor, d = _table_view(room)
    v = render_traced_view(room, T, K, w, h, exposure=1.0, spp=16, seed=1)
    s = _shading(v)

    def at(X):
        r, c = _pixel(T, K, X)
        return float(s[r - 1:r + 2, c - 1:c + 2].mean())

    under, edge, open_ = at(floor), at(floor + 0.45 * d), at(floor + 1.0 * d)
    assert under < 0.6 * open_, (under, edge, open_)      # a shadow
    assert under > 0.1 * open_, (under, open_)            # not black: light reaches it by bounces
    assert under < edge < open_, (under, edge, open_)     # soft: a penumbra between umbra and open floor


def test_brighter_where_the_lights_shine(room):
    """Pixels whose points get the most direct light (analytic, Lambert's polygon formula) are brighter."""
    from pipeline.synthscan.lighting import direct_irradiance
    from pipeline.camera import Camera

    T = look_at(np.array([0.8, 0.8, 1.5]), np.array([room.size[0] - 0.5, room.size[1] - 0.5, 1.0]))
    K = np.array([[40.0, 0.0, 31.5], [0.0, 40.0, 23.5], [0.0, 0.0, 1.0]])
    v = render_traced_view(room, T, K, 64, 48, exposure=1.0, spp=16, seed=2)
    scene = room_trace_scene(room, 1.0)
    pix = np.arange(64 * 48)
    o, dirs = Camera(K, T, 64, 48).rays(pix, np.full((pix.size, 2), 0.5, np.float32))
    hits = scene.intersector.intersect(o, dirs)
    ok = hits.hit & ~scene.tri_emits[np.maximum(hits.prim, 0)]
    p = (o + hits.t[:, None] * dirs)[ok].astype(np.float64)
    n = scene.tri_normal[hits.prim[ok]].astype(np.float64)
    E = direct_irradiance(p, n, room.lights).mean(axis=1)
    s = _shading(v).reshape(-1)[ok]
    lo, hi = np.quantile(E, [0.25, 0.75])
    assert s[E >= hi].mean() > 1.5 * s[E <= lo].mean()
    # the emitters themselves are the brightest pixels: seen directly at their radiance
    lamp_px = ~ok & hits.hit
    assert lamp_px.any() and v.radiance.reshape(-1, 3)[lamp_px].mean() > 5 * v.radiance.mean()


def _cube(centre, size, albedo=(0.7, 0.2, 0.2)):
    from pipeline.trace.scene import ObjectInstance, vertex_normals

    c = np.asarray(centre, float)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * size / 2 + c
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return ObjectInstance(vertices=corners, faces=faces, normals=vertex_normals(corners, faces),
                          albedo=np.tile(np.asarray(albedo, np.float32), (8, 1)), roughness=0.6)


def test_inserted_object_changes_only_pixels_near_it(room):
    """Same seed with and without a cube: correlated paths, so the far room keeps its values exactly."""
    from scipy.ndimage import binary_dilation

    T, K, w, h, floor, d = _table_view(room)
    cube = _cube(floor + 1.0 * d + np.array([0.0, 0.0, 0.1]), 0.2)
    a = render_traced_view(room, T, K, w, h, exposure=1.0, spp=8, seed=5)
    b = render_traced_view(room, T, K, w, h, exposure=1.0, spp=8, seed=5, extra_meshes=[cube])
    assert a.object_coverage.max() == 0.0
    mask = b.object_coverage > 0
    assert 20 < mask.sum() < 0.3 * w * h
    diff = np.abs(b.radiance - a.radiance).mean(axis=2)
    near = binary_dilation(mask, iterations=8) & ~mask
    far = ~binary_dilation(mask, iterations=16)
    assert (diff[far] == 0).mean() > 0.5                   # most far paths never meet the cube
    assert diff[far].mean() < 0.02 * a.radiance.mean()
    assert (b.radiance - a.radiance).mean(axis=2)[near].mean() < 0        # the cube shades the floor
    assert diff[near].mean() > 3 * diff[far].mean()


def test_world_frame_of_a_scan_is_honoured(tmp_path, room):
    """Views and objects given in the scan's world frame (7-Scenes: the first camera) match canonical ones."""
    from dataclasses import replace

    from pipeline.synthscan import make_scan

    out = make_scan(tmp_path / "s", layout="7scenes", seed=0, width=32, height=24, frames=1)
    tr = traced_room_from_scan(out)
    assert tr.seed == 0 and tr.exposure > 0
    T, K, _, _, floor, d = _table_view(room)
    Twc = tr.T_world_from_canonical
    cube = _cube(floor + d, 0.2)
    cube_w = replace(cube, vertices=cube.vertices @ Twc[:3, :3].T + Twc[:3, 3],
                     normals=(cube.normals @ Twc[:3, :3].T).astype(np.float32))
    a = render_traced_view(tr.room, T, K, 32, 24, exposure=tr.exposure, spp=16, seed=1, extra_meshes=[cube])
    b = render_traced_view(tr.room, Twc @ T, K, 32, 24, exposure=tr.exposure, spp=16, seed=1,
                           extra_meshes=[cube_w], T_world_from_canonical=Twc)
    assert np.abs(a.object_coverage - b.object_coverage).max() <= 0.5
    assert abs(float(a.radiance.mean()) - float(b.radiance.mean())) < 0.02 * float(a.radiance.mean())
    with pytest.raises(Exception, match="scan.json"):
        traced_room_from_scan(tmp_path / "nothing")


@pytest.mark.slow
def test_tiny_scan_in_traced_mode_is_deterministic_and_as_bright_as_raster(tmp_path):
    from pipeline.io import read_json
    from pipeline.synthscan import make_scan
    import cv2

    args = dict(layout="7scenes", seed=1, width=48, height=36, frames=2)
    a = make_scan(tmp_path / "a", photo_mode="traced", **args)
    b = make_scan(tmp_path / "b", photo_mode="traced", **args)
    r = make_scan(tmp_path / "r", photo_mode="raster", **args)
    files = read_json(a / "ground_truth" / "scan.json")["files"]
    assert read_json(a / "ground_truth" / "scan.json")["photo_mode"] == "traced"
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    colour = [f for f in files if f.endswith(".color.png")]
    assert len(colour) == 2

    def lin(p):
        x = cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB).astype(np.float64) / 255.0
        return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)

    lo, hi = SYNTHSCAN_TRACED_RASTER_MEAN_RATIO
    for rel in colour:
        ratio = lin(a / rel).mean() / lin(r / rel).mean()
        assert lo <= ratio <= hi, (rel, ratio)
    # depth does not depend on the photo mode
    for rel in files:
        if "depth" in rel:
            assert (a / rel).read_bytes() == (r / rel).read_bytes(), rel


def test_bad_traced_settings_are_user_errors(room):
    from pipeline.synthscan.room import tessellate

    mesh = tessellate(room, 1.0)
    vr = np.ones((len(mesh.vertices), 3), np.float32)
    with pytest.raises(UserError, match="spp"):
        TracedPhotoRenderer(room, mesh, vr, exposure=1.0, spp=0)
    with pytest.raises(UserError, match="denoise"):
        TracedPhotoRenderer(room, mesh, vr, exposure=1.0, denoise="magic")


# --------------------------------------------------------------------------------------------------
# Camera model (degrade.CameraModel / camera_photo): the same camera on the photo and on the truth
# --------------------------------------------------------------------------------------------------

def test_camera_photo_without_a_model_is_the_default_encode_byte_for_byte():
    from pipeline.synthscan.degrade import CameraModel, camera_photo, encode_photo

    x = np.random.default_rng(0).uniform(0, 1.2, (20, 30, 3)).astype(np.float32)
    ref = encode_photo(x, np.random.default_rng(5))
    assert np.array_equal(camera_photo(x, None, np.random.default_rng(5)), ref)
    assert np.array_equal(camera_photo(x, CameraModel(), np.random.default_rng(5)), ref)


@pytest.mark.parametrize("sigma", [0.8, 1.5])
def test_camera_psf_keeps_energy_and_blurs_a_step_by_its_sigma(sigma):
    from pipeline.synthscan.degrade import CameraModel, camera_psf

    flat = np.full((30, 40, 3), 0.37, np.float32)
    np.testing.assert_allclose(camera_psf(flat, CameraModel(blur_sigma=sigma, defocus_radius=1.5)), 0.37, rtol=1e-5)
    step = np.zeros((30, 64, 3), np.float32)
    step[:, 32:] = 1.0
    g = np.diff(camera_psf(step, CameraModel(blur_sigma=sigma))[15, :, 0].astype(np.float64))
    x = np.arange(g.size) + 0.5
    mu = (g * x).sum() / g.sum()
    assert g.sum() == pytest.approx(1.0, abs=1e-4)
    assert np.sqrt((g * (x - mu) ** 2).sum() / g.sum()) == pytest.approx(sigma, rel=0.05)


def test_camera_exposure_scales_the_linear_image_before_the_sensor():
    from pipeline.synthscan.degrade import CameraModel, camera_photo

    x = np.random.default_rng(0).uniform(0, 0.45, (20, 30, 3)).astype(np.float32)
    a = camera_photo(x, CameraModel(exposure=2.0, blur_sigma=0.7), np.random.default_rng(3))
    b = camera_photo(x * 2.0, CameraModel(blur_sigma=0.7), np.random.default_rng(3))
    assert np.array_equal(a, b)


def test_camera_model_is_for_traced_photos_only(tmp_path):
    from pipeline.synthscan import make_scan
    from pipeline.synthscan.degrade import CameraModel

    with pytest.raises(UserError, match="traced"):
        make_scan(tmp_path / "r", layout="7scenes", seed=1, width=48, height=36, frames=1,
                  camera=CameraModel(blur_sigma=1.0))


@pytest.mark.slow
def test_traced_scan_through_a_soft_camera_is_recorded_and_softer(tmp_path):
    import cv2

    from pipeline.io import read_json
    from pipeline.synthscan import make_scan
    from pipeline.synthscan.degrade import CameraModel

    args = dict(layout="7scenes", seed=1, width=64, height=48, frames=1, photo_mode="traced")
    cam = CameraModel(blur_sigma=1.5, read_noise=0.0, shot_noise=0.0)
    a = make_scan(tmp_path / "a", **args)
    b = make_scan(tmp_path / "b", camera=cam, **args)
    doc = read_json(b / "ground_truth" / "scan.json")
    assert doc["camera"] == cam.to_dict() and "camera" not in read_json(a / "ground_truth" / "scan.json")
    rel = next(f for f in doc["files"] if f.endswith(".color.png"))

    def sharpness(p):
        g = cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2GRAY).astype(np.float64)
        return np.abs(cv2.Laplacian(g, cv2.CV_64F)).mean()

    assert sharpness(b / rel) < 0.6 * sharpness(a / rel)
    for f in doc["files"]:   # depth is the camera's geometry, not its optics
        if "depth" in f:
            assert (a / f).read_bytes() == (b / f).read_bytes(), f
