"""The photo's camera look on rendered pixels: tone response, exposure, blur level and sensor noise.

Plain arrays in, plain arrays out; :mod:`pipeline.composite` uses these to make the inserted objects
look as if the same camera had taken them.

Tone response
    The path tracer lights the objects with the room's captured colours decoded by the sRGB curve
    (:func:`pipeline.trace.lights.srgb_to_linear`) and scaled by ``trace.radiance_scale``. Encoding the
    rendered radiance with the exact inverse (:func:`linear_to_srgb` after dividing by that scale) gives
    a white object beside a white wall the wall's own pixel value, whatever the camera's true response
    is: a mismatch between the true curve and sRGB only bends the light transport a little, while a
    different encode curve would shift every object's brightness. Values above sensor white clip, as in
    the photo.

Blur level
    Measured, not guessed: the no-reference blur effect of Crete et al. 2007
    (:func:`pipeline.blur.blur_effect`, the select stage's measure) of the photo around the objects is
    compared with the same measure of the composite for a few Gaussian blurs of the object layer;
    the blur whose composite matches the photo best wins (:func:`match_blur_sigma`).

Sensor noise
    Estimated from the photo around the objects with Immerkaer's Laplacian-difference mask, taking
    the median absolute response over the flattest pixels (texture only inflates it), and added to the
    object pixels (weighted by coverage) from the item's seeded generator, minus the noise the render
    already has (:func:`noise_to_add`).
"""

from __future__ import annotations

import logging
from typing import Callable, Sequence

import cv2
import numpy as np

from pipeline.blur import TEXTURELESS_STD, blur_effect
from pipeline.trace.lights import srgb_to_linear

log = logging.getLogger(__name__)

__all__ = ["srgb_to_linear", "linear_to_srgb", "encode_u8", "decode_u8", "noise_sigma", "noise_to_add",
           "match_blur_sigma", "gaussian_blur", "BLUR_CANDIDATES"]

# Gaussian sigmas (pixels) tried when matching the photo's blur level; 0 = the render as traced.
BLUR_CANDIDATES: tuple[float, ...] = (0.0, 0.4, 0.6, 0.8, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0)
# Immerkaer 1996 noise mask: cancels planes and (mostly) edges; sum of squared weights = 36.
_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
_MAD_TO_SIGMA = 1.0 / (0.6745 * 6.0)   # median |N(0, 6 sigma)| = 0.6745 * 6 sigma
_MIN_NOISE_PIXELS = 64


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear values to sRGB-encoded float32 in [0, 1] (IEC 61966-2-1), the inverse of the tracer's decode.

    Parameters
    ----------
    x : (...,) float
        Linear values; 1.0 = sensor white. NaN and negative values give 0, values above 1 clip to 1.

    Returns
    -------
    (...,) float32 in [0, 1]
    """
    v = np.nan_to_num(np.asarray(x, np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    v = np.clip(v, 0.0, 1.0)
    return np.where(v <= 0.0031308, v * 12.92, 1.055 * np.power(v, 1.0 / 2.4) - 0.055).astype(np.float32)


def decode_u8(photo: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 sRGB photo -> (H, W, 3) float32 linear in [0, 1] (the tracer's convention)."""
    return srgb_to_linear(np.asarray(photo, np.uint8))


def encode_u8(linear: np.ndarray) -> np.ndarray:
    """Linear (H, W, 3) float -> uint8 sRGB, rounded to nearest (``decode_u8`` then this is the identity)."""
    return np.round(linear_to_srgb(linear) * 255.0).astype(np.uint8)


def gaussian_blur(image: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of an (H, W) or (H, W, C) float32 image; reflecting borders (objects continue past them).

    ``sigma`` in pixels; ``sigma <= 0`` returns a copy.
    """
    img = np.asarray(image, np.float32)
    if sigma <= 0:
        return img.copy()
    k = 2 * int(np.ceil(3.0 * sigma)) + 1
    return cv2.GaussianBlur(img, (k, k), sigmaX=float(sigma), sigmaY=float(sigma), borderType=cv2.BORDER_REFLECT)


def _gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = img.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    return img.astype(np.float32)


def noise_sigma(image: np.ndarray, region: np.ndarray | None = None, *, flat_share: float = 0.5) -> float:
    """Sensor noise standard deviation per channel of an image, in its own units (gray levels for uint8).

    Immerkaer's mask is applied to each channel; over the ``region`` pixels, the ``flat_share``
    flattest ones (smallest gradient of the gray image) are kept and a channel's noise is its median
    absolute response divided by ``0.6745 * 6``; the result is the mean over the channels (the noise of
    one channel, which is what :func:`pipeline.composite.composite_full` adds to each channel). Pixels
    touching a clipped value (0 or 255 in a uint8 image) are left out: clipping removes noise.

    Parameters
    ----------
    image : (H, W, 3) or (H, W) uint8 or float
    region : (H, W) bool, optional
        Pixels to measure over (default: all).
    flat_share : float in (0, 1]

    Returns
    -------
    float >= 0; 0.0 when fewer than 64 usable pixels remain.
    """
    img = np.asarray(image)
    chans = [img[..., c].astype(np.float32) for c in range(img.shape[2])] if img.ndim == 3 \
        else [img.astype(np.float32)]
    g = _gray(img)
    if min(g.shape) < 3:
        return 0.0
    ok = np.ones(g.shape, bool) if region is None else np.asarray(region, bool).copy()
    ok[0, :] = ok[-1, :] = ok[:, 0] = ok[:, -1] = False
    if img.dtype == np.uint8:
        clipped = np.zeros(g.shape, bool)
        for c in chans:
            clipped |= (c <= 0.5) | (c >= 254.5)
        ok &= ~(cv2.dilate(clipped.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    if ok.sum() < _MIN_NOISE_PIXELS:
        return 0.0
    grad = np.abs(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)) + np.abs(cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3))
    idx = np.flatnonzero(ok)
    gv = grad.ravel()[idx]
    n = max(_MIN_NOISE_PIXELS, int(flat_share * gv.size))
    if n < gv.size:
        idx = idx[np.argpartition(gv, n - 1)[:n]]
    sig = [float(np.median(np.abs(cv2.filter2D(c, cv2.CV_32F, _IMMERKAER, borderType=cv2.BORDER_REFLECT))
                           .ravel()[idx])) * _MAD_TO_SIGMA for c in chans]
    return float(np.mean(sig))


def noise_to_add(photo_sigma: float, render_sigma: float) -> float:
    """Standard deviation of the noise that brings a render with ``render_sigma`` up to ``photo_sigma``.

    Independent noises add in variance: ``sqrt(max(photo^2 - render^2, 0))``.
    """
    return float(np.sqrt(max(photo_sigma ** 2 - render_sigma ** 2, 0.0)))


def match_blur_sigma(photo_gray: np.ndarray, render_gray: Callable[[float], np.ndarray], *,
                     candidates: Sequence[float] = BLUR_CANDIDATES) -> tuple[float, float]:
    """The Gaussian blur of the object layer whose composite has the photo's blur effect.

    Parameters
    ----------
    photo_gray : (h, w) uint8 or float
        The photo around the objects (a crop), gray levels.
    render_gray : callable
        ``render_gray(sigma) -> (h, w)`` gray composite of the same crop with the object layer blurred
        by ``sigma`` pixels.
    candidates : sigmas to try, pixels (ascending).

    Returns
    -------
    sigma : float
        Chosen blur, pixels; 0.0 when the photo crop is textureless (its blur cannot be measured) or
        smaller than 8 pixels on a side.
    photo_blur : float
        The photo crop's blur effect (0 sharp .. 1 blurred); NaN when not measured.
    """
    p = np.asarray(photo_gray, np.float32)
    if min(p.shape) < 8 or float(p.std()) < TEXTURELESS_STD:
        return 0.0, float("nan")
    target = blur_effect(p)
    best, best_err = 0.0, np.inf
    for s in candidates:
        err = abs(blur_effect(np.asarray(render_gray(float(s)), np.float32)) - target)
        if err < best_err - 1e-6:
            best, best_err = float(s), err
    return best, float(target)
