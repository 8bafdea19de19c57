"""The photo's camera look on rendered pixels: tone response, exposure, blur level and sensor noise.

Plain arrays in, plain arrays out; :mod:`pipeline.composite` uses these to make the inserted objects
look as if the same camera had taken them.

Tone response
    The path tracer lights the objects with the room's captured colours decoded by the sRGB curve
    (:func:`pipeline.color.srgb_to_linear`) and scaled by ``trace.radiance_scale``. Encoding the
    rendered radiance with the exact inverse (:func:`pipeline.color.linear_to_srgb` after dividing by that scale) gives
    a white object beside a white wall the wall's own pixel value, whatever the camera's true response
    is: a mismatch between the true curve and sRGB only bends the light transport a little, while a
    different encode curve would shift every object's brightness. Values above sensor white clip, as in
    the photo.

Blur level
    Measured, not guessed, by the width of edges (:func:`edge_blur_sigma`, the re-blur gradient ratio
    of Zhuo and Sim 2011): the photo's edges around the objects are compared with the composite's
    object edges for a few Gaussian blurs of the object layer, and the blur whose edges match wins
    (:func:`match_blur_sigma`). The select stage's no-reference measure (Crete et al.'s blur effect,
    :func:`pipeline.blur.blur_effect`) is not used here: it depends on content, and the room's soft
    texture beside the objects' crisp silhouettes makes it read 1.5-2 px for a camera blur of 1 px. Only the silhouettes of the objects are measured
    on the composite side (their interior shading is soft in itself), with a noise field of the photo's
    own gray-level noise added (noise makes edges look sharper). The per-edge estimates are summarised
    by their 75th percentile, because the photo's noisy fine texture gives many falsely sharp edge
    pixels: against the path-traced truth of bench/composite.py (camera PSF 0.5-2 px on photo and
    truth) it reads a 1 px blur as 0.6-1.0 px and is within 0.15 dB of the true sigma from 1 to 2 px,
    where the 25th percentile reads 0-0.8 px. Photos softer than the render by less than about 0.5 px are left unblurred.

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


log = logging.getLogger(__name__)

__all__ = ["noise_sigma", "noise_to_add", "match_blur_sigma", "edge_blur_sigma", "gaussian_blur", "BLUR_CANDIDATES"]

# Gaussian sigmas (pixels) tried when matching the photo's blur level; 0 = the render as traced.
BLUR_CANDIDATES: tuple[float, ...] = (0.0, 0.4, 0.6, 0.8, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0)
# Immerkaer 1996 noise mask: cancels planes and (mostly) edges; sum of squared weights = 36.
_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
_MAD_TO_SIGMA = 1.0 / (0.6745 * 6.0)   # median |N(0, 6 sigma)| = 0.6745 * 6 sigma
_MIN_NOISE_PIXELS = 64
REBLUR_SIGMA = 1.0        # pixels, re-blur of the edge-width measure
EDGE_PERCENTILE = 75.0    # percentile of per-edge-pixel blur estimates (see the module docstring)
EDGE_CANNY = (20, 50)      # Canny thresholds (Sobel magnitude): low, so that many edges vote
MIN_EDGE_PIXELS = 20      # fewer usable edge pixels: blur not measurable


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


def edge_blur_sigma(gray: np.ndarray, region: np.ndarray | None = None, *, sigma0: float = REBLUR_SIGMA,
                    percentile: float = EDGE_PERCENTILE) -> tuple[float, int]:
    """Blur level of an image from its edges: the re-blur gradient ratio (Zhuo and Sim 2011).

    At a step edge blurred by a Gaussian of ``sigma``, re-blurring by ``sigma0`` lowers the gradient
    maximum by ``R = sqrt(sigma^2 + sigma0^2) / sigma``, so ``sigma = sigma0 / sqrt(R^2 - 1)``,
    whatever the edge's contrast. Evaluated at Canny edge pixels (:data:`EDGE_CANNY`) and
    summarised by a percentile (:data:`EDGE_PERCENTILE`). The value includes the
    pixel's own footprint (a perfectly sharp anti-aliased edge gives about 0.8): compare it only with
    the same measure of another image, as :func:`match_blur_sigma` does.

    Parameters
    ----------
    gray : (H, W) float or uint8, gray levels 0..255
    region : (H, W) bool, optional; edge pixels outside it are ignored
    sigma0 : re-blur sigma, pixels
    percentile : percentile of the per-edge-pixel estimates

    Returns
    -------
    sigma : float, pixels (NaN when fewer than 2 usable edge pixels)
    count : int, edge pixels used
    """
    g = np.asarray(gray, np.float32)
    if min(g.shape) < 3:
        return float("nan"), 0

    def grad(x: np.ndarray) -> np.ndarray:
        gx = cv2.Sobel(x, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT)
        gy = cv2.Sobel(x, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT)
        return np.hypot(gx, gy)

    a, b = grad(g), grad(gaussian_blur(g, sigma0))
    edges = cv2.Canny(np.clip(np.round(g), 0, 255).astype(np.uint8), *EDGE_CANNY) > 0
    if region is not None:
        edges &= np.asarray(region, bool)
    r = a[edges] / np.maximum(b[edges], 1e-6)
    r = r[r > 1.0 + 1e-4]
    if r.size < 2:
        return float("nan"), int(r.size)
    return float(np.percentile(sigma0 / np.sqrt(r * r - 1.0), percentile)), int(r.size)


def match_blur_sigma(photo_gray: np.ndarray, photo_region: np.ndarray | None,
                     render_gray: Callable[[float], np.ndarray], render_region: np.ndarray | None, *,
                     candidates: Sequence[float] = BLUR_CANDIDATES) -> tuple[float, float]:
    """The Gaussian blur of the object layer whose edges are as soft as the photo's.

    :func:`edge_blur_sigma` of the photo (over ``photo_region``) is compared with the same measure of
    the composite (over ``render_region``, the objects' edges) for each candidate blur; the closest wins.

    Parameters
    ----------
    photo_gray : (h, w) uint8 or float, the photo around the objects (a crop), gray levels
    photo_region : (h, w) bool or None, photo pixels to measure (not the objects)
    render_gray : callable, ``render_gray(sigma) -> (h, w)`` gray composite of the same crop with the
        object layer blurred by ``sigma`` pixels
    render_region : (h, w) bool or None, composite pixels to measure (the objects and their edges)
    candidates : sigmas to try, pixels; the first one (ascending) whose composite edges are at least as
        soft as the photo's, or the one before it when that is closer, is chosen

    Returns
    -------
    sigma : float
        Chosen blur, pixels; 0.0 when the photo or the render has too few edges (fewer than
        :data:`MIN_EDGE_PIXELS`) to measure.
    photo_edge_sigma : float
        The photo's :func:`edge_blur_sigma`; NaN when not measured.
    """
    target, n = edge_blur_sigma(photo_gray, photo_region)
    if n < MIN_EDGE_PIXELS:
        return 0.0, float("nan")
    # walk up the candidates to where the composite's edges first get as soft as the photo's: past
    # that the measure is not monotonic (blurred edges drop below the edge detector's thresholds)
    prev: tuple[float, float] | None = None
    for s in sorted(candidates):
        v, m = edge_blur_sigma(render_gray(float(s)), render_region)
        if m < MIN_EDGE_PIXELS:
            break
        if v >= target:
            if prev is not None and abs(prev[1] - target) < abs(v - target):
                return prev[0], target
            return float(s), target
        prev = (float(s), v)
    best = prev[0] if prev is not None else 0.0
    return best, target
