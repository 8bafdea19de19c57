"""Colour: the sRGB transfer curve, luminance and exposure, written once.

Linear values are relative radiance with 1.0 = sensor white; sRGB is IEC 61966-2-1. Functions keep the
float precision they are given (float32 in, float32 out; float64 in, float64 out); integers are taken as
8-bit codes.

Examples
--------
>>> import numpy as np
>>> encode_u8(decode_u8(np.arange(256, dtype=np.uint8))).tolist() == list(range(256))
True
"""

from __future__ import annotations

import numpy as np

__all__ = ["LUMINANCE", "LUMINANCE_F64", "srgb_to_linear", "linear_to_srgb", "decode_u8", "encode_u8",
           "exposure_ratio"]

LUMINANCE_F64 = np.array([0.2126, 0.7152, 0.0722])   # Rec. 709 luminance weights, linear RGB
LUMINANCE = LUMINANCE_F64.astype(np.float32)          # the same weights in float32 (images, radiance)
LUMINANCE_F64.flags.writeable = False
LUMINANCE.flags.writeable = False


def _srgb_curve(x: np.ndarray) -> np.ndarray:
    """The sRGB decoding curve on float32 sRGB values in [0, 1]."""
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


# the 256 uint8 codes decoded once: an image is then a table lookup, the same values as the curve per pixel
_U8_LINEAR = _srgb_curve(np.arange(256, dtype=np.float32) / np.float32(255.0))
_U8_LINEAR.flags.writeable = False


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB colours (uint8 0..255 or float 0..1) to linear float32.

    Parameters
    ----------
    c : (...,) uint8 codes or float sRGB values in [0, 1]

    Returns
    -------
    (...,) float32 linear values
    """
    x = np.asarray(c)
    if x.dtype == np.uint8:
        return np.asarray(_U8_LINEAR[x])        # a new array (0-d for a 0-d input), as the curve gives
    return _srgb_curve(x.astype(np.float32))


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """Linear values to sRGB-encoded values in [0, 1], in the input's float precision.

    NaN and negative values give 0, values above 1 (and +inf) clip to 1. Non-float input is taken as
    float32.
    """
    v = np.asarray(x)
    if not np.issubdtype(v.dtype, np.floating):
        v = v.astype(np.float32)
    v = np.clip(np.nan_to_num(v, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    return np.where(v <= 0.0031308, v * 12.92, 1.055 * np.power(v, 1.0 / 2.4) - 0.055).astype(v.dtype)


def decode_u8(image: np.ndarray) -> np.ndarray:
    """uint8 sRGB image -> float32 linear in [0, 1]."""
    return srgb_to_linear(np.asarray(image, np.uint8))


def encode_u8(linear: np.ndarray) -> np.ndarray:
    """Linear values -> uint8 sRGB codes, rounded to nearest (the inverse of :func:`decode_u8`)."""
    return np.round(linear_to_srgb(linear) * 255.0).astype(np.uint8)


def exposure_ratio(photo_lum: np.ndarray, reference_lum: np.ndarray, *, floor: float = 0.02,
                   min_samples: int = 1) -> float | None:
    """Exposure of a photo relative to a reference rendering of the same points: the geometric median
    ``exp(median(log(photo / reference)))`` over points where both luminances exceed ``floor``.

    Parameters
    ----------
    photo_lum, reference_lum : (N,) linear luminances of the same N points (float precision is kept)
    floor : darker points are left out (noise and clipping at black dominate them)
    min_samples : fewer qualifying points give None

    Returns
    -------
    float, or None when fewer than ``min_samples`` points qualify
    """
    p, r = np.asarray(photo_lum), np.asarray(reference_lum)
    good = (r > floor) & (p > floor)
    if good.sum() < max(1, min_samples):
        return None
    return float(np.exp(np.median(np.log(p[good] / r[good]))))
