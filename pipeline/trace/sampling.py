"""Direction sampling with pdfs, batched over rays (structure-of-arrays, float32/float64 NumPy).

All local-frame functions use a frame where the surface normal is +z. Solid-angle pdfs are in 1/sr.
GGX (Trowbridge-Reitz) uses ``alpha`` = perceptual roughness squared; visible-normal sampling follows
Heitz, "Sampling the GGX Distribution of Visible Normals", JCGT 7(4), 2018, and the masking term is
Smith's (separable, as in Mitsuba's ``roughconductor``).
"""

from __future__ import annotations

import numpy as np

ALPHA_MIN = 1e-3  # smallest GGX alpha: below it the lobe is a near-delta and float32 pdfs overflow


def orthonormal_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents ``(t, b)`` completing unit normals ``n (R, 3)`` to right-handed frames.

    Duff et al., "Building an Orthonormal Basis, Revisited", JCGT 6(1), 2017 (branchless).
    """
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    s = np.where(z >= 0, 1.0, -1.0).astype(n.dtype)
    a = -1.0 / (s + z)
    b = x * y * a
    t = np.stack([1.0 + s * x * x * a, s * b, -s * x], axis=1)
    bb = np.stack([b, s + y * y * a, -y], axis=1)
    return t, bb


def local_frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(t, b, n)``: the frame of unit normals ``n (R, 3)``, to reuse across several rotations."""
    t, b = orthonormal_basis(n)
    return t, b, n


def frame_to_world(local: np.ndarray, frame: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """Local directions (R, 3) to world in a :func:`local_frame`."""
    t, b, n = frame
    return local[:, :1] * t + local[:, 1:2] * b + local[:, 2:3] * n


def frame_to_local(w: np.ndarray, frame: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """World directions (R, 3) to the local coordinates of a :func:`local_frame`."""
    t, b, n = frame
    return np.stack([np.einsum("ij,ij->i", w, t), np.einsum("ij,ij->i", w, b),
                     np.einsum("ij,ij->i", w, n)], axis=1)


def to_world(local: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Rotate local directions (+z = ``n``) to world: (R, 3) -> (R, 3)."""
    t, b = orthonormal_basis(n)
    return local[:, :1] * t + local[:, 1:2] * b + local[:, 2:3] * n


def cosine_hemisphere(u1: np.ndarray, u2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cosine-weighted directions about +z from uniforms ``u1, u2 (R,)`` in [0, 1).

    Returns
    -------
    dirs : (R, 3) local unit directions, z >= 0
    pdf : (R,) solid-angle pdf ``cos(theta) / pi``
    """
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    z = np.sqrt(np.maximum(0.0, 1.0 - u1))
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    return d, z / np.pi


def ggx_d(h_local: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """GGX normal distribution ``D(h)`` (1/sr, projected-area normalised) for local half vectors (R, 3)."""
    a2 = alpha * alpha
    hz = h_local[:, 2]
    denom = (h_local[:, 0] ** 2 + h_local[:, 1] ** 2) / a2 + hz * hz
    d = 1.0 / (np.pi * a2 * denom * denom)
    return np.where(hz > 0, d, 0.0)


def smith_g1(w_local: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Smith masking ``G1(w)`` for GGX (isotropic), local directions (R, 3)."""
    z = w_local[:, 2]
    z2 = np.maximum(z * z, 1e-12)
    tan2 = np.maximum(0.0, 1.0 - z2) / z2
    g = 2.0 / (1.0 + np.sqrt(1.0 + alpha * alpha * tan2))
    return np.where(z > 0, g, 0.0)


def ggx_sample_vndf(wo_local: np.ndarray, alpha: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Half vectors sampled from the GGX distribution of normals visible from ``wo`` (z > 0).

    Returns (R, 3) local unit half vectors with pdf ``G1(wo) max(0, wo.h) D(h) / wo.z``.
    """
    # stretch the view vector to the hemisphere configuration
    vh = np.stack([alpha * wo_local[:, 0], alpha * wo_local[:, 1], wo_local[:, 2]], axis=1)
    vh /= np.linalg.norm(vh, axis=1, keepdims=True)
    lensq = vh[:, 0] ** 2 + vh[:, 1] ** 2
    inv = 1.0 / np.sqrt(np.maximum(lensq, 1e-20))
    t1 = np.where(lensq[:, None] > 1e-14,
                  np.stack([-vh[:, 1] * inv, vh[:, 0] * inv, np.zeros_like(lensq)], axis=1),
                  np.array([1.0, 0.0, 0.0], dtype=wo_local.dtype))
    t2 = np.cross(vh, t1)
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    p1 = r * np.cos(phi)
    p2 = r * np.sin(phi)
    s = 0.5 * (1.0 + vh[:, 2])
    p2 = (1.0 - s) * np.sqrt(np.maximum(0.0, 1.0 - p1 * p1)) + s * p2
    p3 = np.sqrt(np.maximum(0.0, 1.0 - p1 * p1 - p2 * p2))
    nh = p1[:, None] * t1 + p2[:, None] * t2 + p3[:, None] * vh
    h = np.stack([alpha * nh[:, 0], alpha * nh[:, 1], np.maximum(1e-7, nh[:, 2])], axis=1)
    return h / np.linalg.norm(h, axis=1, keepdims=True)


def ggx_reflect_pdf(wo_local: np.ndarray, wi_local: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Solid-angle pdf of ``wi`` when reflecting ``wo`` about a VNDF-sampled half vector.

    ``pdf(wi) = G1(wo) D(h) / (4 wo.z)`` with ``h = normalize(wo + wi)``; 0 below the surface.
    """
    h = wo_local + wi_local
    hn = np.linalg.norm(h, axis=1, keepdims=True)
    h = h / np.maximum(hn, 1e-12)
    wz = np.maximum(wo_local[:, 2], 1e-12)
    pdf = smith_g1(wo_local, alpha) * ggx_d(h, alpha) / (4.0 * wz)
    ok = (wo_local[:, 2] > 0) & (wi_local[:, 2] > 0) & (hn[:, 0] > 1e-12)
    return np.where(ok, pdf, 0.0)


def reflect(w: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Mirror ``w`` about ``h`` (both (R, 3), unit): ``2 (w.h) h - w``."""
    return 2.0 * np.einsum("ij,ij->i", w, h)[:, None] * h - w


def power_heuristic(pdf_a: np.ndarray, pdf_b: np.ndarray) -> np.ndarray:
    """MIS weight of technique a against b (Veach's power heuristic, beta = 2); 0 where both are 0."""
    a2 = pdf_a * pdf_a
    s = a2 + pdf_b * pdf_b
    return np.where(s > 0, a2 / np.where(s > 0, s, 1.0), 0.0)
