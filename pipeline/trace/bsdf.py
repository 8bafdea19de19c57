"""Metallic-roughness BSDF: Lambert diffuse + GGX (Trowbridge-Reitz) specular with Schlick Fresnel.

Everything is in the local shading frame (normal = +z) and batched: arrays of ``R`` rays, float64 or
float32. ``f_cos`` below means ``f(wo, wi) * cos(theta_i)``, the quantity a path's throughput is
multiplied by (divided by the pdf).

Model (the glTF 2.0 metallic-roughness model, with two choices that keep it energy conserving and
comparable to a reference renderer):

- ``alpha = roughness**2`` (clamped to :data:`~pipeline.trace.sampling.ALPHA_MIN`);
- ``F0 = lerp(0.04 * specular, base_color, metallic)``; Schlick ``F(c) = F0 + (F90 - F0) (1 - c)^5``
  with ``F90 = clip(50 * max(F0), 0, 1)`` (Filament's rule), so ``specular = 0`` on a dielectric gives
  ``F = 0``, a pure Lambertian surface;
- specular ``F(wo.h) D(h) G1(wo) G1(wi) / (4 wo.z wi.z)`` (separable Smith masking-shadowing, as in
  Mitsuba's ``roughconductor``);
- diffuse ``(1 - metallic) (1 - F_d(wo.z)) base_color / pi`` where ``F_d`` is the dielectric Fresnel:
  the light the specular layer reflects is taken away from the diffuse one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.trace.sampling import (ALPHA_MIN, cosine_hemisphere, ggx_d, ggx_reflect_pdf,
                                     ggx_sample_vndf, reflect, smith_g1)

DIELECTRIC_F0 = 0.04  # reflectance at normal incidence of common dielectrics (IOR ~1.5)


@dataclass(frozen=True)
class Material:
    """Per-ray material parameters (structure of arrays)."""

    base_color: np.ndarray  # (R, 3) linear RGB in [0, 1]
    metallic: np.ndarray    # (R,) in [0, 1]
    roughness: np.ndarray   # (R,) perceptual roughness in [0, 1]
    specular: np.ndarray    # (R,) dielectric specular scale in [0, 1]; 0 = no specular lobe (Lambert)

    def take(self, idx: np.ndarray) -> "Material":
        return Material(self.base_color[idx], self.metallic[idx], self.roughness[idx], self.specular[idx])


def _alpha(mat: Material) -> np.ndarray:
    return np.maximum(mat.roughness * mat.roughness, ALPHA_MIN)


def _f0(mat: Material) -> np.ndarray:
    m = mat.metallic[:, None]
    return (1.0 - m) * (DIELECTRIC_F0 * mat.specular)[:, None] + m * mat.base_color


def schlick(f0: np.ndarray, cos: np.ndarray) -> np.ndarray:
    """Schlick Fresnel with Filament's ``F90 = clip(50 max(F0), 0, 1)``; ``f0 (R, 3)``, ``cos (R,)``."""
    f90 = np.clip(50.0 * f0.max(axis=1, keepdims=True), 0.0, 1.0)
    k = (1.0 - np.clip(cos, 0.0, 1.0)) ** 5
    return f0 + (f90 - f0) * k[:, None]


def _diffuse_weight(mat: Material, wo_z: np.ndarray) -> np.ndarray:
    """(R,) ``(1 - metallic) (1 - F_dielectric(wo.z))``."""
    f0d = (DIELECTRIC_F0 * mat.specular)[:, None] * np.ones((1, 3))
    fd = schlick(f0d, wo_z)[:, 0]
    return (1.0 - mat.metallic) * (1.0 - fd)


def spec_probability(mat: Material, wo_z: np.ndarray) -> np.ndarray:
    """(R,) probability of sampling the specular lobe, proportional to each lobe's rough weight."""
    lum = np.array([0.2126, 0.7152, 0.0722])
    ws = schlick(_f0(mat), wo_z) @ lum
    wd = _diffuse_weight(mat, wo_z) * (mat.base_color @ lum)
    tot = ws + wd
    p = np.where(tot > 0, ws / np.where(tot > 0, tot, 1.0), 0.5)
    # keep both lobes sampled when both exist, so MIS never meets a zero pdf for a non-zero f
    return np.where((ws > 0) & (wd > 0), np.clip(p, 0.1, 0.9), p)


def eval_f_cos(wo: np.ndarray, wi: np.ndarray, mat: Material) -> np.ndarray:
    """``f(wo, wi) cos(theta_i)``, (R, 3); 0 when either direction is below the surface."""
    ok = (wo[:, 2] > 0) & (wi[:, 2] > 0)
    alpha = _alpha(mat)
    h = wo + wi
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    woh = np.einsum("ij,ij->i", wo, h)
    F = schlick(_f0(mat), woh)
    wz = np.maximum(wo[:, 2], 1e-12)
    spec = F * (ggx_d(h, alpha) * smith_g1(wo, alpha) * smith_g1(wi, alpha) / (4.0 * wz))[:, None]
    diff = mat.base_color * (_diffuse_weight(mat, wo[:, 2]) * np.maximum(wi[:, 2], 0.0) / np.pi)[:, None]
    return np.where(ok[:, None], spec + diff, 0.0)


def pdf(wo: np.ndarray, wi: np.ndarray, mat: Material) -> np.ndarray:
    """(R,) solid-angle pdf of :func:`sample` choosing ``wi``."""
    ps = spec_probability(mat, wo[:, 2])
    p_spec = ggx_reflect_pdf(wo, wi, _alpha(mat))
    p_diff = np.where(wi[:, 2] > 0, wi[:, 2] / np.pi, 0.0)
    return np.where(wo[:, 2] > 0, ps * p_spec + (1.0 - ps) * p_diff, 0.0)


def sample(wo: np.ndarray, mat: Material, u_lobe: np.ndarray, u1: np.ndarray,
           u2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample an incident direction for outgoing ``wo`` (local, z > 0).

    Returns
    -------
    wi : (R, 3) local unit direction (may point below the surface: then ``pdf`` is 0)
    f_cos : (R, 3) ``f(wo, wi) cos(theta_i)``
    pdf : (R,) solid-angle pdf of the whole mixture (for MIS and for ``f_cos / pdf``)
    """
    alpha = _alpha(mat)
    ps = spec_probability(mat, wo[:, 2])
    use_spec = u_lobe < ps
    h = ggx_sample_vndf(wo, alpha, u1, u2)
    wi_s = reflect(wo, h)
    wi_d, _ = cosine_hemisphere(u1, u2)
    wi = np.where(use_spec[:, None], wi_s, wi_d)
    return wi, eval_f_cos(wo, wi, mat), pdf(wo, wi, mat)
