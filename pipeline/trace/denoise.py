"""Optional denoising of the traced object pixels, guided by the albedo and normal buffers.

Intel Open Image Denoise (the ``pyoidn`` package) is used when it is installed; otherwise a joint
bilateral filter in NumPy (weights from pixel distance, albedo and normal differences) stands in. Both
run on a crop around the traced pixels only, and leave every pixel outside ``mask`` untouched.
"""

from __future__ import annotations

import importlib.util
import logging

import numpy as np

log = logging.getLogger(__name__)

CROP_MARGIN = 8  # pixels of context kept around the traced region for the filter


def oidn_available() -> bool:
    """True when the ``pyoidn`` package can be imported."""
    return importlib.util.find_spec("pyoidn") is not None


def _crop(mask: np.ndarray) -> tuple[slice, slice] | None:
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        return None
    H, W = mask.shape
    return (slice(max(0, ys.min() - CROP_MARGIN), min(H, ys.max() + CROP_MARGIN + 1)),
            slice(max(0, xs.min() - CROP_MARGIN), min(W, xs.max() + CROP_MARGIN + 1)))


def joint_bilateral(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray, *, radius: int = 3,
                    sigma_px: float = 2.0, sigma_albedo: float = 0.1, sigma_normal: float = 0.2) -> np.ndarray:
    """Joint bilateral filter of ``color (H, W, 3)`` guided by ``albedo`` and ``normal`` (same shape).

    Filters the illumination (colour divided by albedo) so texture stays sharp, then multiplies the
    albedo back. Returns (H, W, 3) float32.
    """
    eps = 1e-3
    illum = color / np.maximum(albedo, eps)
    H, W, _ = color.shape
    pad = radius
    ip = np.pad(illum, ((pad, pad), (pad, pad), (0, 0)), mode="edge")
    ap = np.pad(albedo, ((pad, pad), (pad, pad), (0, 0)), mode="edge")
    npd = np.pad(normal, ((pad, pad), (pad, pad), (0, 0)), mode="edge")
    acc = np.zeros_like(illum, dtype=np.float64)
    wsum = np.zeros((H, W), np.float64)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            sl = (slice(pad + dy, pad + dy + H), slice(pad + dx, pad + dx + W))
            w = np.exp(-(dx * dx + dy * dy) / (2 * sigma_px ** 2)
                       - np.sum((ap[sl] - albedo) ** 2, axis=2) / (2 * sigma_albedo ** 2)
                       - np.sum((npd[sl] - normal) ** 2, axis=2) / (2 * sigma_normal ** 2))
            acc += w[..., None] * ip[sl]
            wsum += w
    return (acc / wsum[..., None] * np.maximum(albedo, eps)).astype(np.float32)


def denoise(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray, mask: np.ndarray, *,
            method: str = "auto") -> np.ndarray:
    """Denoise the pixels of ``color`` inside ``mask``.

    Parameters
    ----------
    color : (H, W, 3) float32 linear radiance (HDR allowed)
    albedo : (H, W, 3) float32 linear base colour in [0, 1]
    normal : (H, W, 3) float32 normals in [-1, 1] (any fixed frame)
    mask : (H, W) bool, pixels that may change
    method : "auto" (OIDN when installed, else bilateral), "oidn" or "bilateral"

    Returns
    -------
    (H, W, 3) float32: ``color`` with the masked pixels denoised.
    """
    if method not in ("auto", "oidn", "bilateral"):
        raise ValueError(f"denoise method {method!r}: expected 'auto', 'oidn' or 'bilateral'")
    out = np.array(color, dtype=np.float32, copy=True)
    box = _crop(mask)
    if box is None:
        return out
    use_oidn = method == "oidn" or (method == "auto" and oidn_available())
    c = np.ascontiguousarray(color[box], np.float32)
    a = np.ascontiguousarray(np.clip(albedo[box], 0, 1), np.float32)
    n = np.ascontiguousarray(np.clip(normal[box], -1, 1), np.float32)
    if use_oidn:
        import pyoidn

        d = pyoidn.denoise(c, a, n, hdr=True, quality="high")
    else:
        d = joint_bilateral(c, a, n)
    m = mask[box]
    out[box][m] = d[m]  # out[box] is a view (basic slicing)
    return out


def denoise_ao(ao: np.ndarray, normal: np.ndarray, mask: np.ndarray, *, method: str = "auto") -> np.ndarray:
    """Denoise an ambient-occlusion buffer inside ``mask``, guided by the normals only.

    Parameters
    ----------
    ao : (H, W) float32 in [0, 1]
    normal : (H, W, 3) float32 normals in [-1, 1]
    mask : (H, W) bool, pixels that may change
    method : as :func:`denoise`

    Returns
    -------
    (H, W) float32 in [0, 1]; pixels outside ``mask`` unchanged.
    """
    img = np.repeat(np.asarray(ao, np.float32)[..., None], 3, axis=2)
    white = np.ones_like(img)
    out = denoise(img, white, normal, mask, method=method).mean(axis=2)
    return np.where(mask, np.clip(out, 0.0, 1.0), ao).astype(np.float32)
