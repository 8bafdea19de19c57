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

from pipeline.color import LUMINANCE_F64
from pipeline.trace.sampling import ALPHA_MIN, cosine_hemisphere, ggx_d, ggx_sample_vndf, reflect, smith_g1

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


@dataclass(frozen=True)
class Lobes:
    """Per-ray quantities of :class:`Material` that depend only on ``wo``, computed once per batch."""

    base: np.ndarray     # (R, 3) base colour
    alpha: np.ndarray    # (R,) GGX alpha
    f0: np.ndarray       # (R, 3) Fresnel reflectance at normal incidence
    f90: np.ndarray      # (R, 1) Fresnel reflectance at grazing incidence
    diff: np.ndarray     # (R, 3) diffuse albedo: (1 - metallic) (1 - F_dielectric(wo.z)) base / pi
    p_spec: np.ndarray   # (R,) probability of sampling the specular lobe




def schlick(f0: np.ndarray, cos: np.ndarray, f90: np.ndarray | None = None) -> np.ndarray:
    """Schlick Fresnel with Filament's ``F90 = clip(50 max(F0), 0, 1)``; ``f0 (R, 3)``, ``cos (R,)``."""
    if f90 is None:
        f90 = np.clip(50.0 * f0.max(axis=1, keepdims=True), 0.0, 1.0)
    k = (1.0 - np.clip(cos, 0.0, 1.0)) ** 5
    return f0 + (f90 - f0) * k[:, None]


def prepare(mat: Material, wo_z: np.ndarray) -> Lobes:
    """The :class:`Lobes` of ``mat`` seen from directions with local ``z = wo_z (R,)``."""
    dt = mat.base_color.dtype
    alpha = np.maximum(mat.roughness * mat.roughness, dt.type(ALPHA_MIN))
    m = mat.metallic[:, None]
    f0d = (DIELECTRIC_F0 * mat.specular)[:, None]
    f0 = (1 - m) * f0d + m * mat.base_color
    f90 = np.clip(50 * f0.max(axis=1, keepdims=True), 0, 1)
    k = ((1 - np.clip(wo_z, 0, 1)) ** 5)[:, None]
    fd = f0d + (np.clip(50 * f0d, 0, 1) - f0d) * k  # dielectric Fresnel at wo (scalar per ray)
    diff = mat.base_color * ((1 - m) * (1 - fd) / np.pi)
    ws = (f0 + (f90 - f0) * k) @ LUMINANCE_F64.astype(dt)
    wd = (diff @ LUMINANCE_F64.astype(dt)) * np.pi
    tot = ws + wd
    p = np.where(tot > 0, ws / np.where(tot > 0, tot, 1), 0.5)
    # keep both lobes sampled when both exist, so MIS never meets a zero pdf for a non-zero f
    p = np.where((ws > 0) & (wd > 0), np.clip(p, 0.1, 0.9), p).astype(dt)
    return Lobes(base=mat.base_color, alpha=alpha, f0=f0, f90=f90, diff=diff, p_spec=p)


def eval_pdf(L: Lobes, wo: np.ndarray, wi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``f(wo, wi) cos(theta_i)`` (R, 3) and the sampling pdf of ``wi`` (R,), sharing the GGX terms."""
    ok = (wo[:, 2] > 0) & (wi[:, 2] > 0)
    h = wo + wi
    hn = np.linalg.norm(h, axis=1, keepdims=True)
    h = h / np.maximum(hn, 1e-12)
    woh = np.einsum("ij,ij->i", wo, h)
    F = schlick(L.f0, woh, L.f90)
    wz = np.maximum(wo[:, 2], 1e-12)
    D = ggx_d(h, L.alpha)
    g1o = smith_g1(wo, L.alpha)
    spec_pdf = g1o * D / (4 * wz)
    wiz = np.maximum(wi[:, 2], 0)
    f = F * (spec_pdf * smith_g1(wi, L.alpha))[:, None] + L.diff * wiz[:, None]
    pdf = L.p_spec * spec_pdf + (1 - L.p_spec) * wiz / np.pi
    ok &= hn[:, 0] > 1e-12
    return np.where(ok[:, None], f, 0), np.where(ok, pdf, 0)


def sample_prepared(L: Lobes, wo: np.ndarray, u_lobe: np.ndarray, u1: np.ndarray,
                    u2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`sample` for prepared lobes."""
    use_spec = u_lobe < L.p_spec
    wi = np.empty_like(wo)
    s = np.flatnonzero(use_spec)
    d = np.flatnonzero(~use_spec)
    if s.size:
        h = ggx_sample_vndf(wo[s], L.alpha[s], u1[s], u2[s])
        wi[s] = reflect(wo[s], h)
    if d.size:
        wi[d] = cosine_hemisphere(u1[d], u2[d])[0]
    f, pdf = eval_pdf(L, wo, wi)
    return wi, f, pdf


def eval_f_cos(wo: np.ndarray, wi: np.ndarray, mat: Material) -> np.ndarray:
    """``f(wo, wi) cos(theta_i)``, (R, 3); 0 when either direction is below the surface."""
    return eval_pdf(prepare(mat, wo[:, 2]), wo, wi)[0]


def pdf(wo: np.ndarray, wi: np.ndarray, mat: Material) -> np.ndarray:
    """(R,) solid-angle pdf of :func:`sample` choosing ``wi``."""
    return eval_pdf(prepare(mat, wo[:, 2]), wo, wi)[1]


def sample(wo: np.ndarray, mat: Material, u_lobe: np.ndarray, u1: np.ndarray,
           u2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample an incident direction for outgoing ``wo`` (local, z > 0).

    Returns
    -------
    wi : (R, 3) local unit direction (may point below the surface: then ``pdf`` is 0)
    f_cos : (R, 3) ``f(wo, wi) cos(theta_i)``
    pdf : (R,) solid-angle pdf of the whole mixture (for MIS and for ``f_cos / pdf``)
    """
    return sample_prepared(prepare(mat, wo[:, 2]), wo, u_lobe, u1, u2)
