"""Metallic-roughness BSDF: Mitsuba 3's ``principled`` BSDF (Burley's Disney BRDF) restricted to its
base_color / metallic / roughness parameters, with ``specular`` blending it with plain Lambert.

Everything is in the local shading frame (normal = +z) and batched: arrays of ``R`` rays, float64 or
float32. ``f_cos`` below means ``f(wo, wi) * cos(theta_i)``, the quantity a path's throughput is
multiplied by (divided by the pdf).

Model, with ``b`` the base colour, ``m`` metallic, ``r`` roughness, ``s`` specular,
``h = normalize(wo + wi)``, ``c_d = wo.h``, ``F_S(x) = (1 - x)^5``:

- ``f = (1 - m) b / pi * (1 - s + s * f_disney) + F(c_d) D(h) G1(wo) G1(wi) / (4 wo.z wi.z)``;
- GGX (Trowbridge-Reitz) ``D`` with ``alpha = r**2`` (clamped to
  :data:`~pipeline.trace.sampling.ALPHA_MIN`), separable Smith masking-shadowing ``G1(wo) G1(wi)``;
- ``F = (1 - m) s F_dielectric(c_d; IOR 1.5) + m (b + (1 - b) F_S(c_d))``: the exact unpolarised
  dielectric Fresnel (F0 = 0.04) for the non-metal, Schlick with the base colour for the metal;
- ``f_disney = (1 - F_i/2)(1 - F_o/2) + R_r (F_o + F_i + F_o F_i (R_r - 1))``, ``F_i = F_S(wi.z)``,
  ``F_o = F_S(wo.z)``, ``R_r = 2 r c_d^2``: Burley's diffuse with retro-reflection (Fd90 = 0.5 + R_r),
  not multiplied by ``1 - F``.

At ``s = 1`` this is, term for term, Mitsuba 3's ``principled`` with ``specular = 0.5`` (eta 1.5),
``spec_tint``, ``sheen``, ``clearcoat``, ``spec_trans``, ``anisotropic``, ``flatness`` 0 (see
``tests/pipeline/test_trace_mitsuba.py``, which renders it as the reference); ``m = 1`` is Mitsuba's
``roughconductor`` with F = 1 for a white base; ``s = 0`` with ``m = 0`` is exactly Lambertian (Mitsuba's
``diffuse``; the room and emitters use it). Intermediate ``s`` is the linear blend of the two.

Why this model: it is one well-defined reference, so a render can be checked against Mitsuba pixel for
pixel. The previous Lambert x ``(1 - F_schlick(wo))`` + Schlick model was 4-7 % darker than
``principled`` and matched no reference BSDF; ``roughplastic``, whose single-scattering rough interface
loses energy, is further off (the old model rendered 8-111 % brighter than it at roughness 0.3-0.8).
The price is Disney's: the model is not energy conserving. Its white directional albedo is 1.02-1.05 near
normal incidence and up to 1.2-1.5 at grazing angles (the diffuse term ignores the light the specular
layer reflects, and retro-reflection brightens rough surfaces), as in Mitsuba; a model capped at an
albedo of 1 stays >= 4 % darker than ``principled`` in the comparison renders.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.color import LUMINANCE_F64
from pipeline.trace.sampling import ALPHA_MIN, cosine_hemisphere, ggx_d, ggx_sample_vndf, reflect, smith_g1

DIELECTRIC_IOR = 1.5  # index of refraction of the dielectric layer (common plastics, paints, glass)
DIELECTRIC_F0 = ((DIELECTRIC_IOR - 1) / (DIELECTRIC_IOR + 1)) ** 2  # its reflectance at normal incidence, 0.04


@dataclass(frozen=True)
class Material:
    """Per-ray material parameters (structure of arrays)."""

    base_color: np.ndarray  # (R, 3) linear RGB in [0, 1]
    metallic: np.ndarray    # (R,) in [0, 1]
    roughness: np.ndarray   # (R,) perceptual roughness in [0, 1]
    specular: np.ndarray    # (R,) in [0, 1]: weight of the principled dielectric against Lambert (0 = Lambert)

    def take(self, idx: np.ndarray) -> "Material":
        return Material(self.base_color[idx], self.metallic[idx], self.roughness[idx], self.specular[idx])


@dataclass(frozen=True)
class Lobes:
    """Per-ray quantities of :class:`Material` that depend only on ``wo``, computed once per batch."""

    base: np.ndarray     # (R, 3) base colour
    rough: np.ndarray    # (R,) perceptual roughness (Disney retro-reflection)
    alpha: np.ndarray    # (R,) GGX alpha
    metal: np.ndarray    # (R, 1) metallic: weight of the Schlick (base colour) Fresnel
    diel: np.ndarray     # (R, 1) (1 - metallic) specular: weight of the dielectric Fresnel
    disney: np.ndarray   # (R,) specular: weight of Disney's diffuse shape against Lambert's
    fo: np.ndarray       # (R,) Schlick weight (1 - wo.z)^5
    diff: np.ndarray     # (R, 3) (1 - metallic) base / pi
    p_spec: np.ndarray   # (R,) probability of sampling the specular lobe


def schlick_weight(cos: np.ndarray) -> np.ndarray:
    """``(1 - cos)^5`` with ``cos`` clipped to [0, 1]."""
    return (1 - np.clip(cos, 0, 1)) ** 5


def schlick(f0: np.ndarray, cos: np.ndarray) -> np.ndarray:
    """Schlick Fresnel ``F0 + (1 - F0) (1 - cos)^5`` (the metal's); ``f0 (R, 3)``, ``cos (R,)``."""
    return f0 + (1 - f0) * schlick_weight(cos)[:, None]


def fresnel_dielectric(cos: np.ndarray, eta: float = DIELECTRIC_IOR) -> np.ndarray:
    """Unpolarised Fresnel reflectance of light arriving from outside (``cos`` in [0, 1]) on a dielectric
    of relative index ``eta > 1`` (no total internal reflection from this side), (R,)."""
    c = np.clip(cos, 0, 1)
    ct = np.sqrt(np.maximum(1 - (1 - c * c) / (eta * eta), 0))
    rs = (c - eta * ct) / np.maximum(c + eta * ct, 1e-12)
    rp = (eta * c - ct) / np.maximum(eta * c + ct, 1e-12)
    return 0.5 * (rs * rs + rp * rp)


def prepare(mat: Material, wo_z: np.ndarray) -> Lobes:
    """The :class:`Lobes` of ``mat`` seen from directions with local ``z = wo_z (R,)``."""
    dt = mat.base_color.dtype
    alpha = np.maximum(mat.roughness * mat.roughness, dt.type(ALPHA_MIN))
    m = mat.metallic[:, None]
    diel = (1 - m) * mat.specular[:, None]
    diff = mat.base_color * ((1 - m) / np.pi)
    lum = LUMINANCE_F64.astype(dt)
    # lobe choice: the Fresnel reflectance at wo.z against the diffuse albedo
    ws = (diel[:, 0] * fresnel_dielectric(wo_z).astype(dt) + (m * schlick(mat.base_color, wo_z)) @ lum)
    wd = (diff @ lum) * np.pi
    tot = ws + wd
    p = np.where(tot > 0, ws / np.where(tot > 0, tot, 1), 0.5)
    # keep both lobes sampled when both exist, so MIS never meets a zero pdf for a non-zero f
    p = np.where((ws > 0) & (wd > 0), np.clip(p, 0.1, 0.9), p).astype(dt)
    return Lobes(base=mat.base_color, rough=mat.roughness, alpha=alpha, metal=m, diel=diel,
                 disney=mat.specular, fo=schlick_weight(wo_z), diff=diff, p_spec=p)


def eval_pdf(L: Lobes, wo: np.ndarray, wi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``f(wo, wi) cos(theta_i)`` (R, 3) and the sampling pdf of ``wi`` (R,), sharing the GGX terms."""
    ok = (wo[:, 2] > 0) & (wi[:, 2] > 0)
    h = wo + wi
    hn = np.linalg.norm(h, axis=1, keepdims=True)
    h = h / np.maximum(hn, 1e-12)
    woh = np.einsum("ij,ij->i", wo, h)
    F = L.diel * fresnel_dielectric(woh)[:, None] + L.metal * schlick(L.base, woh)
    wz = np.maximum(wo[:, 2], 1e-12)
    D = ggx_d(h, L.alpha)
    g1o = smith_g1(wo, L.alpha)
    spec_pdf = g1o * D / (4 * wz)
    wiz = np.maximum(wi[:, 2], 0)
    # Disney's diffuse (Burley 2012, with retro-reflection) for the dielectric, Lambert's at specular 0
    fi, fo = schlick_weight(wiz), L.fo
    rr = 2 * L.rough * woh * woh
    shape = (1 - 0.5 * fi) * (1 - 0.5 * fo) + rr * (fo + fi + fo * fi * (rr - 1))
    shape = 1 + L.disney * (shape - 1)
    f = F * (spec_pdf * smith_g1(wi, L.alpha))[:, None] + L.diff * (shape * wiz)[:, None]
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
