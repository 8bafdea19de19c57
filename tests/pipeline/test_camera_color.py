"""pipeline/camera.py and pipeline/color.py against references we did not write: OpenCV's projection and
undistortion, scikit-image's sRGB conversion, and the documented module examples."""

from __future__ import annotations

import doctest

import cv2
import numpy as np
import pytest

from pipeline import camera, color
from pipeline.camera import Camera, RGBDRig

K = np.array([[525.0, 0.0, 319.3], [0.0, 530.0, 241.7], [0.0, 0.0, 1.0]])


def _pose(rng) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.normal(size=3)
    return T


def test_module_examples():
    for mod in (camera, color):
        res = doctest.testmod(mod)
        assert res.attempted > 0 and res.failed == 0, mod.__name__


def test_project_matches_opencv_projectpoints():
    rng = np.random.default_rng(0)
    T_c2w = _pose(rng)
    cam = Camera(K=K, T_c2w=T_c2w, width=640, height=480)
    pts_c = np.column_stack([rng.uniform(-1, 1, 200), rng.uniform(-1, 1, 200), rng.uniform(0.5, 4, 200)])
    pts_w = pts_c @ T_c2w[:3, :3].T + T_c2w[:3, 3]
    uv, z = cam.project(pts_w)
    T_w2c = np.linalg.inv(T_c2w)
    ref, _ = cv2.projectPoints(pts_w, cv2.Rodrigues(T_w2c[:3, :3])[0], T_w2c[:3, 3], K, None)
    np.testing.assert_allclose(uv, ref[:, 0], atol=1e-6)
    np.testing.assert_allclose(z, pts_c[:, 2], atol=1e-9)


def test_unproject_matches_opencv_undistortpoints_and_round_trips():
    rng = np.random.default_rng(1)
    u, v, z = rng.uniform(0, 640, 100), rng.uniform(0, 480, 100), rng.uniform(0.3, 5, 100)
    p = camera.unproject_points(K, u, v, z)
    norm = cv2.undistortPoints(np.column_stack([u, v])[:, None], K, None)[:, 0]   # x/z, y/z
    np.testing.assert_allclose(p[:, :2] / p[:, 2:], norm, atol=1e-9)
    uv, zz = camera.project_points(K, p)
    np.testing.assert_allclose(uv, np.column_stack([u, v]), atol=1e-9)
    np.testing.assert_allclose(zz, z)


def test_rays_pass_through_pixel_centres_and_image_plane_agrees():
    cam = Camera(K=K, T_c2w=_pose(np.random.default_rng(2)), width=64, height=48)
    pix = np.arange(64 * 48)
    o, d = cam.rays(pix, np.full((pix.size, 2), 0.5))
    uv, z = cam.project(o.astype(np.float64) + 2.0 * d.astype(np.float64))
    assert (z > 0).all()
    np.testing.assert_allclose(uv[:, 0], pix % 64, atol=2e-3)      # float32 rays
    np.testing.assert_allclose(uv[:, 1], pix // 64, atol=2e-3)
    x, y = camera.image_plane(K, 64, 48)
    np.testing.assert_allclose(camera.project_points(K, np.column_stack([x, np.zeros(64), np.ones(64)]))[0][:, 0],
                               np.arange(64), atol=1e-9)
    assert camera.image_plane(K, 4, 3, np.float32)[1].dtype == np.float32


def test_scaled_keeps_pixel_centres_and_gl_camera_flips_axes():
    cam = Camera(K=K, T_c2w=np.eye(4), width=640, height=480).scaled(0.5)
    assert (cam.width, cam.height) == (320, 240)
    # the centre of pixel block [2c, 2c+1] at full size is pixel c at half size
    uv, _ = cam.project_cam(camera.unproject_points(K, np.array([10.5]), np.array([20.5]), np.array([2.0])))
    np.testing.assert_allclose(uv[0], [5.0, 10.0], atol=1e-9)
    G = cam.gl_pose()
    np.testing.assert_array_equal(G[:3, 1], -cam.T_c2w[:3, 1])   # OpenGL y up = -OpenCV y
    np.testing.assert_array_equal(G[:3, 2], -cam.T_c2w[:3, 2])   # OpenGL looks down -z
    assert cam.gl_intrinsics(3, 4)[2:] == (cam.K[0, 2] - 3 + 0.5, cam.K[1, 2] - 4 + 0.5)


def test_rig_places_the_depth_camera_by_its_offset():
    T_d2c = np.eye(4)
    T_d2c[:3, 3] = [0.025, 0.0, 0.0]
    rig = RGBDRig(color_K=K, color_width=640, color_height=480, depth_K=K * [[1.1], [1.1], [1]],
                  depth_width=640, depth_height=480, T_d2c=T_d2c)
    assert not rig.registered
    T = _pose(np.random.default_rng(3))
    np.testing.assert_allclose(rig.depth(T).center, T[:3, :3] @ [0.025, 0, 0] + T[:3, 3])
    assert RGBDRig(K, 640, 480, K, 640, 480).registered


def test_srgb_matches_scikit_image_and_round_trips_every_code():
    from skimage.color import rgb2gray

    codes = np.arange(256, dtype=np.uint8)
    lin = color.decode_u8(codes)
    # IEC 61966-2-1 as published: 0.04045 threshold, 2.4 exponent (scikit-image's rgb2xyz uses the same curve)
    ref = np.where(codes / 255.0 <= 0.04045, codes / 255.0 / 12.92, ((codes / 255.0 + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(lin, ref, rtol=1e-6, atol=1e-7)
    assert np.array_equal(color.encode_u8(lin), codes)
    # luminance of linear RGB: scikit-image's rgb2gray uses Rec. 709 weights rounded differently
    # (0.2125, 0.7154, 0.0721): agreement to 1e-3, not to the last bit
    rgb = np.random.default_rng(4).random((10, 3)).astype(np.float32)
    np.testing.assert_allclose(rgb @ color.LUMINANCE, rgb2gray(rgb[None])[0], rtol=1e-3)
    assert color.LUMINANCE.dtype == np.float32 and np.array_equal(color.LUMINANCE, color.LUMINANCE_F64.astype(np.float32))


def test_uint8_decoding_is_the_float_curve_and_a_fresh_array():
    """uint8 images decode by a table of the 256 codes: the same float32 values as the curve on code / 255,
    in an array of the image's shape the caller may write to (the table itself stays untouched)."""
    img = np.random.default_rng(5).integers(0, 256, (7, 9, 3), dtype=np.uint8)
    lin = color.decode_u8(img)
    assert lin.shape == img.shape and lin.dtype == np.float32
    assert np.array_equal(lin, color.srgb_to_linear(img.astype(np.float32) / np.float32(255.0)))
    lin[:] = -1.0
    assert np.array_equal(color.decode_u8(img[:1, :1]), color.srgb_to_linear(img[:1, :1].astype(np.float32) / 255))
    zero_d = color.srgb_to_linear(np.uint8(255))
    assert isinstance(zero_d, np.ndarray) and zero_d.shape == () and zero_d == np.float32(1.0)


def test_linear_to_srgb_clips_bad_values_and_keeps_precision():
    x = np.array([-1.0, np.nan, np.inf, 2.0, 0.0031308, 0.18], np.float64)
    y = color.linear_to_srgb(x)
    assert y.dtype == np.float64 and y[0] == 0 and y[1] == 0
    assert y[2] == pytest.approx(1.0, abs=1e-12) and y[3] == pytest.approx(1.0, abs=1e-12)
    assert y[5] == pytest.approx(0.4613, abs=1e-3)
    assert color.linear_to_srgb(x.astype(np.float32)).dtype == np.float32


def test_exposure_ratio_is_the_median_ratio_over_bright_points():
    ref = np.linspace(0.05, 1.0, 101)
    photo = 0.7 * ref
    photo[:5] = 10.0   # a few outliers (clipped highlights) do not move the median
    assert color.exposure_ratio(photo, ref) == pytest.approx(0.7, rel=1e-9)
    assert color.exposure_ratio(np.zeros(5), np.ones(5)) is None
