"""Tests of pipeline/camera_look.py: tone curve, noise estimate, blur matching."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline import camera_look as cl, color
from pipeline.color import srgb_to_linear


def test_encode_is_the_exact_inverse_of_the_tracers_decode_for_every_byte():
    v = np.arange(256, dtype=np.uint8).reshape(16, 16)
    img = np.stack([v, v[::-1], v.T], axis=-1)
    assert np.array_equal(color.encode_u8(srgb_to_linear(img)), img)
    assert np.array_equal(color.encode_u8(color.decode_u8(img)), img)


def test_linear_to_srgb_known_values_and_bad_inputs():
    x = np.array([0.0, 0.0031308, 0.18, 1.0, 2.0, -1.0, np.nan, np.inf], np.float32)
    y = color.linear_to_srgb(x)
    assert y.dtype == np.float32 and np.isfinite(y).all()
    assert y[0] == 0 and y[3] == pytest.approx(1.0) and y[4] == pytest.approx(1.0)  # clips like a sensor
    assert y[1] == pytest.approx(0.0031308 * 12.92, rel=1e-5)
    assert y[2] == pytest.approx(0.4613, abs=1e-3)   # 18 % grey is sRGB 118/255
    assert y[5] == 0 and y[6] == 0 and y[7] == pytest.approx(1.0)


@pytest.mark.parametrize("sigma", [1.0, 3.0, 6.0])
def test_noise_sigma_recovers_added_gaussian_noise_on_a_textured_image(sigma):
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:120, 0:160]
    clean = 120 + 40 * np.sin(xx / 9.0) + 30 * (xx > 80) + 20 * np.cos(yy / 13.0)   # smooth shading + an edge
    img = np.clip(np.round(clean + sigma * rng.standard_normal(clean.shape)), 0, 255).astype(np.uint8)
    est = cl.noise_sigma(img)
    assert est == pytest.approx(sigma, rel=0.2)


def test_noise_sigma_of_flat_clipped_and_tiny_images():
    assert cl.noise_sigma(np.full((50, 50, 3), 80, np.uint8)) == 0.0
    assert cl.noise_sigma(np.full((50, 50, 3), 255, np.uint8)) == 0.0   # clipped: no usable pixel
    assert cl.noise_sigma(np.zeros((2, 2), np.uint8)) == 0.0
    assert cl.noise_sigma(np.full((50, 50), 80, np.uint8), np.zeros((50, 50), bool)) == 0.0


def test_noise_to_add_subtracts_variances():
    assert cl.noise_to_add(5.0, 3.0) == pytest.approx(4.0)
    assert cl.noise_to_add(2.0, 3.0) == 0.0


def _scene(sigma_photo: float) -> tuple[np.ndarray, np.ndarray]:
    """A sharp step-and-texture pattern, and the same blurred by ``sigma_photo`` (the 'photo')."""
    rng = np.random.default_rng(1)
    base = (rng.random((12, 16)) * 200 + 20).astype(np.float32)
    sharp = np.kron(base, np.ones((8, 8), np.float32))   # 96 x 128 blocks with hard edges
    return sharp, cl.gaussian_blur(sharp, sigma_photo)


@pytest.mark.parametrize("sigma_photo", [0.0, 1.0, 2.0])
def test_match_blur_sigma_finds_the_photos_blur(sigma_photo):
    sharp, photo = _scene(sigma_photo)
    s, measured = cl.match_blur_sigma(photo, None, lambda s: cl.gaussian_blur(sharp, s), None)
    assert np.isfinite(measured)
    assert abs(s - sigma_photo) <= 0.3


def test_edge_blur_sigma_grows_with_blur_and_ignores_contrast():
    yy, xx = np.mgrid[0:80, 0:100].astype(np.float64)
    cov = np.zeros((80, 100))
    sub = (np.arange(8) + 0.5) / 8 - 0.5
    for dy in sub:
        for dx in sub:
            cov += ((xx + dx - 50) ** 2 + (yy + dy - 40) ** 2 <= 25 ** 2)
    cov /= 64
    vals = [cl.edge_blur_sigma(cl.gaussian_blur((60 + 140 * cov).astype(np.float32), s))[0]
            for s in (0.0, 0.5, 1.0, 1.5, 2.0)]
    assert np.all(np.diff(vals) > 0)
    low = cl.edge_blur_sigma(cl.gaussian_blur((60 + 70 * cov).astype(np.float32), 1.0))[0]
    assert low == pytest.approx(vals[2], abs=0.05)


def test_match_blur_sigma_without_edges_is_zero():
    s, measured = cl.match_blur_sigma(np.full((40, 40), 90, np.uint8), None, lambda s: np.zeros((40, 40)), None)
    assert s == 0.0 and np.isnan(measured)
    assert np.isnan(cl.edge_blur_sigma(np.zeros((2, 2)))[0])


def test_gaussian_blur_keeps_constants_at_borders():
    img = np.full((10, 12, 3), 0.25, np.float32)
    out = cl.gaussian_blur(img, 1.5)
    assert out.shape == img.shape and np.allclose(out, 0.25)
    assert cl.gaussian_blur(img, 0.0) is not img
