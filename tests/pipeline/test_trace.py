"""Tests of pipeline/trace: intersectors, sampling, BSDF, AO and the wavefront integrator.

Analytic scenes only (NumPy meshes built here); every figure has a closed-form answer.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import stats

from pipeline.tolerances import TRACE_FURNACE_REL_TOL
from pipeline.trace import bsdf
from pipeline.trace.intersect import EmbreeIntersector, NumPySlowIntersector
from pipeline.color import srgb_to_linear
from pipeline.trace.lights import AreaLights, published_lights
from pipeline.camera import Camera
from pipeline.trace.pbr import RenderSettings, ambient_occlusion, render, trace_mask
from pipeline.trace.sampling import ggx_reflect_pdf, ggx_sample_vndf, reflect
from pipeline.trace.scene import ObjectInstance, build_scene
from tests.pipeline.shapes import box_room, grid_quad, look_at, quad, uv_sphere


def sphere_object(radius=0.5, center=(0, 0, 0), albedo=1.0, **mat) -> ObjectInstance:
    v, f, n = uv_sphere(radius, center, n_lat=32, n_lon=64)
    return ObjectInstance(vertices=v, faces=f, normals=n, albedo=np.full((len(v), 3), albedo, np.float32), **mat)


def camera(eye=(0.0, -2.5, 0.0), target=(0.0, 0.0, 0.0), w=48, h=36, f=40.0) -> Camera:
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    return Camera(K=K, T_c2w=look_at(eye, target), width=w, height=h)


EMPTY = (np.zeros((0, 3)), np.zeros((0, 3), np.int32), None)


# --------------------------------------------------------------------------------------------------
# Intersectors
# --------------------------------------------------------------------------------------------------

def test_embree_matches_slow_numpy_on_random_and_grazing_rays():
    rng = np.random.default_rng(1)
    sv, sf, _ = uv_sphere(0.7, (0.1, -0.2, 0.3), n_lat=10, n_lon=20)
    tv = rng.uniform(-1, 1, (60, 3, 3))  # random triangle soup, some long and thin
    pv, pf = grid_quad((0, 0, -0.8), (1.5, 0, 0), (0, 1.5, 0), 4)
    verts = np.concatenate([sv, tv.reshape(-1, 3), pv])
    faces = np.concatenate([sf, np.arange(180).reshape(60, 3) + len(sv), pf + len(sv) + 180]).astype(np.int32)
    n = 3000
    o = rng.uniform(-2, 2, (n, 3))
    d = rng.normal(size=(n, 3))
    # grazing rays: nearly parallel to the plane z = -0.8, just above and below it
    g = 600
    o[:g] = np.c_[rng.uniform(-2, 2, (g, 2)), -0.8 + rng.choice([-1, 1], g) * rng.uniform(1e-4, 1e-2, g)]
    d[:g] = np.c_[rng.normal(size=(g, 2)), rng.normal(scale=1e-3, size=g)]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o, d = o.astype(np.float32), d.astype(np.float32)
    fast = EmbreeIntersector(verts, faces).intersect(o, d)
    slow = NumPySlowIntersector(verts, faces).intersect(o, d)
    assert fast.hit.sum() > n // 5 and (~fast.hit).sum() > n // 10  # the test exercises both outcomes
    # rays whose slow answer is numerically unambiguous (hit not within float32 noise of an edge)
    w = np.stack([1 - slow.u - slow.v, slow.u, slow.v], 1)
    margin = np.where(slow.hit, w.min(axis=1), 1.0)
    clear = margin > 1e-4
    assert clear.mean() > 0.98
    np.testing.assert_array_equal(fast.hit[clear], slow.hit[clear])
    both = clear & slow.hit
    np.testing.assert_allclose(fast.t[both], slow.t[both], rtol=1e-4, atol=1e-5)
    same_prim = fast.prim[both] == slow.prim[both]
    assert same_prim.mean() > 0.999  # different prims only for coincident hits (same t)
    occ_f = EmbreeIntersector(verts, faces).occluded(o, d, 1.0)
    occ_s = slow.hit & (slow.t < 1.0)
    agree = occ_f == occ_s
    assert agree[clear & (np.abs(slow.t - 1.0) > 1e-4)].all()


def test_intersectors_respect_tmax_and_empty_mesh():
    v, f = quad((0, 0, 1), (1, 0, 0), (0, 1, 0))
    o = np.zeros((2, 3), np.float32)
    d = np.array([[0, 0, 1], [0, 0, 1]], np.float32)
    for cls in (EmbreeIntersector, NumPySlowIntersector):
        h = cls(v, f).intersect(o, d, np.array([2.0, 0.5], np.float32))
        assert h.hit.tolist() == [True, False] and h.t[0] == pytest.approx(1.0)
        e = cls(np.zeros((0, 3)), np.zeros((0, 3), np.int32)).intersect(o, d)
        assert not e.hit.any() and np.isinf(e.t).all()


# --------------------------------------------------------------------------------------------------
# Sampling and BSDF
# --------------------------------------------------------------------------------------------------

def _chi2_directions(sample_fn, pdf_fn, n=200_000, nz=12, nphi=24, seed=0):
    """Chi-square test of sampled local directions against a solid-angle pdf (z = cos(theta), phi bins)."""
    rng = np.random.default_rng(seed)
    wi = sample_fn(rng, n)
    below = wi[:, 2] <= 0
    up = wi[~below]
    zi = np.clip((up[:, 2] * nz).astype(int), 0, nz - 1)
    pi_ = np.clip(((np.arctan2(up[:, 1], up[:, 0]) % (2 * np.pi)) / (2 * np.pi) * nphi).astype(int), 0, nphi - 1)
    obs = np.bincount(zi * nphi + pi_, minlength=nz * nphi).astype(float)
    # expected mass per bin: integrate the pdf on a fine sub-grid (d omega = dz dphi)
    sub = 16
    zs = (np.arange(nz * sub) + 0.5) / (nz * sub)
    ps = (np.arange(nphi * sub) + 0.5) / (nphi * sub) * 2 * np.pi
    Z, P = np.meshgrid(zs, ps, indexing="ij")
    s = np.sqrt(1 - Z ** 2)
    dirs = np.stack([s * np.cos(P), s * np.sin(P), Z], -1).reshape(-1, 3)
    dens = pdf_fn(dirs).reshape(nz * sub, nphi * sub) * (1.0 / (nz * sub)) * (2 * np.pi / (nphi * sub))
    exp = dens.reshape(nz, sub, nphi, sub).sum(axis=(1, 3)).ravel() * n
    obs = np.append(obs, below.sum())
    exp = np.append(exp, max(n - exp.sum(), 0.0))
    # merge bins with small expectations (chi-square needs >= 5 expected per cell)
    order = np.argsort(exp)
    small = order[np.cumsum(exp[order]) < 5 * 4]
    keep = np.setdiff1d(np.arange(exp.size), small)
    o2 = np.append(obs[keep], obs[small].sum())
    e2 = np.append(exp[keep], exp[small].sum())
    e2 *= o2.sum() / e2.sum()
    chi2 = float(((o2 - e2) ** 2 / np.maximum(e2, 1e-12)).sum())
    return stats.chi2.sf(chi2, df=o2.size - 1)


@pytest.mark.parametrize("alpha,theta_deg", [(0.15, 20.0), (0.4, 60.0), (0.8, 80.0)])
def test_ggx_vndf_sampling_passes_chi_square_against_its_pdf(alpha, theta_deg):
    th = np.radians(theta_deg)
    wo1 = np.array([np.sin(th), 0.0, np.cos(th)])

    def sample(rng, n):
        wo = np.tile(wo1, (n, 1))
        h = ggx_sample_vndf(wo, np.full(n, alpha), rng.random(n), rng.random(n))
        return reflect(wo, h)

    def pdf(dirs):
        return ggx_reflect_pdf(np.tile(wo1, (len(dirs), 1)), dirs, np.full(len(dirs), alpha))

    assert _chi2_directions(sample, pdf) > 1e-3


@pytest.mark.parametrize("metallic,roughness,spec", [(0.0, 0.5, 1.0), (0.5, 0.3, 1.0), (1.0, 0.6, 1.0)])
def test_bsdf_mixture_sampling_passes_chi_square_against_its_pdf(metallic, roughness, spec):
    th = np.radians(45.0)
    wo1 = np.array([np.sin(th), 0.0, np.cos(th)])

    def mat(n):
        return bsdf.Material(np.full((n, 3), 0.7), np.full(n, metallic), np.full(n, roughness), np.full(n, spec))

    def sample(rng, n):
        wi, _, _ = bsdf.sample(np.tile(wo1, (n, 1)), mat(n), rng.random(n), rng.random(n), rng.random(n))
        return wi

    def pdf(dirs):
        return bsdf.pdf(np.tile(wo1, (len(dirs), 1)), dirs, mat(len(dirs)))

    assert _chi2_directions(sample, pdf) > 1e-3


@pytest.mark.parametrize("metallic", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("roughness", [0.05, 0.3, 0.7, 1.0])
def test_bsdf_conserves_energy_and_sampling_is_unbiased(metallic, roughness):
    """Directional albedo for a white base colour at every angle: <= 1 for the metal; for the dielectric,
    Mitsuba's principled (Disney) model reflects more than it receives (up to 1.51 at roughness 1, grazing:
    its diffuse ignores the specular layer's share and adds retro-reflection), so only that bound holds
    (test_trace_mitsuba checks the values against Mitsuba). The importance-sampled estimate equals the
    uniform-hemisphere estimate of the same integral."""
    rng = np.random.default_rng(3)
    n = 40_000
    for cos_o in (1.0, 0.7, 0.3, 0.05):
        wo = np.tile([np.sqrt(1 - cos_o ** 2), 0.0, cos_o], (n, 1))
        m = bsdf.Material(np.ones((n, 3)), np.full(n, metallic), np.full(n, roughness), np.ones(n))
        wi, fc, pdf = bsdf.sample(wo, m, rng.random(n), rng.random(n), rng.random(n))
        est = np.where(pdf > 0, fc[:, 0] / np.where(pdf > 0, pdf, 1), 0.0)
        mean, se = est.mean(), est.std() / np.sqrt(n)
        assert mean <= (1.0 if metallic == 1.0 else 1.52) + 4 * se + 1e-3, (cos_o, mean)
        assert (fc >= 0).all()
        if roughness >= 0.3:  # a uniform-hemisphere estimate is only precise for broad lobes
            z = rng.random(n)
            phi = 2 * np.pi * rng.random(n)
            s = np.sqrt(1 - z * z)
            wu = np.stack([s * np.cos(phi), s * np.sin(phi), z], 1)
            uni = bsdf.eval_f_cos(wo, wu, m)[:, 0] * 2 * np.pi
            se_u = uni.std() / np.sqrt(n)
            assert abs(uni.mean() - mean) < 4 * np.hypot(se, se_u) + 2e-3


def test_lambert_mode_is_exactly_lambertian():
    n = 1000
    rng = np.random.default_rng(0)
    wo = np.tile([0.6, 0.0, 0.8], (n, 1))
    wi = rng.normal(size=(n, 3))
    wi[:, 2] = np.abs(wi[:, 2])
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    m = bsdf.Material(np.full((n, 3), 0.4), np.zeros(n), np.full(n, 0.5), np.zeros(n))
    np.testing.assert_allclose(bsdf.eval_f_cos(wo, wi, m), 0.4 / np.pi * wi[:, 2:3] * np.ones((1, 3)), rtol=1e-12)


def test_srgb_to_linear_endpoints_and_midpoint():
    np.testing.assert_allclose(srgb_to_linear(np.array([0, 255, 188], np.uint8)), [0.0, 1.0, 0.5], atol=3e-3)


# --------------------------------------------------------------------------------------------------
# Ambient occlusion
# --------------------------------------------------------------------------------------------------

def _ao_at(verts, faces, p, n, samples=100_000, max_distance=10.0, seed=0):
    isect = EmbreeIntersector(verts, faces)
    P = np.asarray([p], np.float32)
    N = np.asarray([n], np.float32)
    return ambient_occlusion(isect, P, N, N, np.random.default_rng(seed), samples=samples,
                             max_distance=max_distance, eps=1e-4)[0]


def test_ao_is_one_on_an_open_plane():
    v, f = grid_quad((0, 0, 0), (5, 0, 0), (0, 5, 0), 4)
    assert _ao_at(v, f, (0.3, -0.2, 0.0), (0, 0, 1), samples=20_000) == 1.0


def test_ao_is_zero_inside_a_closed_sphere():
    v, f, _ = uv_sphere(1.0, n_lat=16, n_lon=32, inward=True)
    assert _ao_at(v, f, (0.0, 0.0, -0.999), (0, 0, 1), samples=20_000) == 0.0
    assert _ao_at(v, f, (0.0, 0.0, 0.0), (1, 0, 0), samples=20_000) == 0.0


def test_ao_above_a_plane_with_a_square_blocker_matches_the_form_factor():
    a, h = 0.5, 0.4  # square half-size and height above the point
    pv, pf = grid_quad((0, 0, 0), (5, 0, 0), (0, 5, 0), 4)
    bv, bf = quad((0, 0, h), (a, 0, 0), (0, -a, 0))  # facing down
    v = np.concatenate([pv, bv])
    f = np.concatenate([pf, bf + len(pv)])
    X = a / h  # point-to-parallel-rectangle form factor, four corner rectangles a x a
    F = 4 * (1 / (2 * np.pi)) * 2 * (X / np.sqrt(1 + X * X) * np.arctan(X / np.sqrt(1 + X * X)))
    ao = _ao_at(v, f, (0, 0, 0), (0, 0, 1), samples=400_000)
    assert ao == pytest.approx(1 - F, abs=4e-3)
    # a blocker beyond the AO distance does not count
    assert _ao_at(v, f, (0, 0, 0), (0, 0, 1), samples=20_000, max_distance=0.3) == 1.0


# --------------------------------------------------------------------------------------------------
# Integrator
# --------------------------------------------------------------------------------------------------

def _interior(fb):
    return fb.coverage > 0.999


def test_white_furnace_lambert_sphere_renders_one():
    sc = build_scene(*EMPTY, [sphere_object(specular=0.0)], env_radiance=np.ones(3))
    fb = render(sc, camera(), np.ones((36, 48), bool), RenderSettings(spp=8, spp_min=8), np.random.default_rng(0))
    px = fb.pbr[_interior(fb)]
    assert px.size > 300 and abs(px.mean() - 1.0) < TRACE_FURNACE_REL_TOL
    # samples lost only where the interpolated normal sends a ray under the facet (energy is never gained)
    assert px.max() <= 1.0 + 1e-5 and (np.abs(px - 1.0) > TRACE_FURNACE_REL_TOL).mean() < 0.02


def test_white_furnace_with_inter_reflection_and_russian_roulette():
    obs = [sphere_object(0.45, (-0.5, 0, 0), specular=0.0), sphere_object(0.45, (0.5, 0, 0), specular=0.0)]
    sc = build_scene(*EMPTY, obs, env_radiance=np.ones(3))
    s = RenderSettings(spp=64, spp_min=64, max_depth=64, rr_depth=1)
    fb = render(sc, camera(), np.ones((36, 48), bool), s, np.random.default_rng(0))
    px = fb.pbr[_interior(fb)]
    assert abs(px.mean() - 1.0) < TRACE_FURNACE_REL_TOL


def test_white_furnace_inside_an_emitting_room():
    rv, rf = box_room((-2, -3, -2), (2, 3, 2), n=4)
    sc = build_scene(rv, rf, None, [sphere_object(specular=0.0)], room_linear_radiance=np.ones((len(rv), 3)))
    fb = render(sc, camera(), np.ones((36, 48), bool), RenderSettings(spp=4, spp_min=4), np.random.default_rng(0))
    px = fb.pbr[_interior(fb)]
    assert abs(px.mean() - 1.0) < TRACE_FURNACE_REL_TOL
    assert (np.abs(px - 1.0) > TRACE_FURNACE_REL_TOL).mean() < 0.02


def test_smooth_white_metal_furnace_is_near_one():
    sc = build_scene(*EMPTY, [sphere_object(metallic=1.0, roughness=0.05)], env_radiance=np.ones(3))
    fb = render(sc, camera(), np.ones((36, 48), bool), RenderSettings(spp=4, spp_min=4), np.random.default_rng(0))
    px = fb.pbr[_interior(fb)]
    assert abs(px.mean() - 1.0) < TRACE_FURNACE_REL_TOL and px.max() <= 1.0 + 1e-4


def test_lit_by_room_matches_albedo_times_radiance():
    rv, rf = box_room((-2, -3, -2), (2, 3, 2), n=4)
    sc = build_scene(rv, rf, None, [sphere_object(albedo=0.3, specular=0.0)],
                     room_linear_radiance=np.full((len(rv), 3), 0.8))
    fb = render(sc, camera(), np.ones((36, 48), bool), RenderSettings(spp=4, spp_min=4), np.random.default_rng(0))
    np.testing.assert_allclose(fb.pbr[_interior(fb)], 0.24, rtol=1e-4)
    assert fb.ao[_interior(fb)].min() == 1.0  # room farther than the AO distance


def test_nee_with_mis_matches_bsdf_sampling_alone():
    """A bright (clipped) ceiling patch sampled explicitly gives the same image as BSDF sampling only,
    with less noise."""
    rv, rf = box_room((-2, -3, -2), (2, 3, 2), n=8)
    col = np.zeros((len(rv), 3), np.uint8)
    lamp = (rv[:, 2] > 1.99) & (np.abs(rv[:, 0]) < 1.01) & (np.abs(rv[:, 1]) < 1.6)
    col[lamp] = 255
    obs = [sphere_object(0.5, (0, 0, 0), albedo=0.7, roughness=0.5)]
    sc = build_scene(rv, rf, col, obs, light_gain=3.0)
    assert sc.area_lights.count > 0
    no_nee = dataclasses.replace(sc, area_lights=AreaLights(tri=np.zeros(0, np.int64), cdf=np.zeros(0),
                                                              prob=np.zeros(0), area=np.zeros(0),
                                                              prob_of_tri=np.zeros(len(sc.faces))))
    s = RenderSettings(spp=256, spp_min=256, max_depth=1)
    cam = camera(w=24, h=18, f=40.0)
    mask = np.ones((18, 24), bool)
    a1, a2 = (render(sc, cam, mask, s, np.random.default_rng(k)) for k in (1, 2))
    b1, b2 = (render(no_nee, cam, mask, s, np.random.default_rng(k)) for k in (3, 4))
    m = _interior(a1) & _interior(b1)
    assert m.sum() > 150
    a = 0.5 * (a1.pbr[m] + a2.pbr[m])
    b = 0.5 * (b1.pbr[m] + b2.pbr[m])
    assert abs(a.mean() / b.mean() - 1) < 0.02
    assert np.std(a1.pbr[m] - a2.pbr[m]) < 0.7 * np.std(b1.pbr[m] - b2.pbr[m])


def test_sobol_2d_blocks_are_stratified():
    """Every aligned block of 2**k consecutive points has one point in each elementary box of area 2**-k
    (the (0, 2)-sequence property the stratified sampler relies on), counted box by box."""
    from pipeline.trace.pbr import _sobol_2d

    P = _sobol_2d(6)
    assert P.shape == (64, 2) and P.min() >= 0 and P.max() < 1
    for k in range(1, 7):
        for start in range(0, 64, 2 ** k):
            blk = P[start:start + 2 ** k]
            for a in range(k + 1):
                box = np.floor(blk[:, 0] * 2 ** a) * 2 ** (k - a) + np.floor(blk[:, 1] * 2 ** (k - a))
                assert len(np.unique(box)) == 2 ** k, (k, start, a)


def test_stratified_draws_are_uniform_independent_across_groups_and_even_within_a_pass():
    from pipeline.trace.pbr import StratifiedDraws

    n = 20000
    d = StratifiedDraws(np.random.default_rng(0), pixels=n, max_samples=8, batch=4)
    d.start(np.arange(n), 0, 4)
    U = d.first.astype(np.float64)          # (8 dimensions, 4 n samples)
    assert U.shape == (8, 4 * n) and U.min() >= 0 and U.max() < 1
    for row in U:                           # each sample on its own is uniform: the estimate stays unbiased
        assert stats.kstest(row, "uniform").pvalue > 1e-3
    rng = np.random.default_rng(1)
    iid = rng.random((2, 4 * n))

    def f(x, y):   # smooth and periodic: a pixel's 4-sample mean of it estimates 1/4
        return np.sin(np.pi * x) ** 2 * np.sin(np.pi * y) ** 2

    base = f(*iid).reshape(n, 4).mean(axis=1).var()
    for i, j in ((0, 1), (3, 4), (6, 7), (0, 2), (2, 5)):   # within a 2D group, and across groups
        m = f(U[i], U[j]).reshape(n, 4).mean(axis=1)
        assert m.mean() == pytest.approx(0.25, abs=3e-3)
        assert m.var() < 0.6 * base, (i, j)                   # 0.27-0.41 measured; independent draws: 1
        assert abs(np.corrcoef(U[i], U[j])[0, 1]) < 0.02


def test_stratified_first_bounce_halves_the_noise_of_next_event_estimation():
    """A sphere under a ceiling lamp at 8 spp: the same mean as independent draws, with about half the
    pixel noise (0.079 against 0.154 measured)."""
    rv, rf = box_room((-2, -3, -2), (2, 3, 2), n=8)
    col = np.zeros((len(rv), 3), np.uint8)
    lamp = (rv[:, 2] > 1.99) & (np.abs(rv[:, 0]) < 1.01) & (np.abs(rv[:, 1]) < 1.6)
    col[lamp] = 255
    sc = build_scene(rv, rf, col, [sphere_object(0.5, (0, 0, 0), albedo=0.7, roughness=0.5)], light_gain=3.0)
    cam = camera(w=48, h=36, f=80.0)
    mask = np.ones((36, 48), bool)
    out = {}
    for strat in (True, False):
        s = RenderSettings(spp=8, spp_min=8, max_depth=2, stratified=strat)
        out[strat] = [render(sc, cam, mask, s, np.random.default_rng(k)) for k in range(4)]
    m = _interior(out[True][0]) & _interior(out[False][0])
    assert m.sum() > 500
    mean = {k: np.mean([r.pbr[m].mean() for r in v]) for k, v in out.items()}
    assert mean[True] / mean[False] == pytest.approx(1.0, abs=0.02)
    noise = {k: np.std(v[0].pbr[m] - v[1].pbr[m]) for k, v in out.items()}
    assert noise[True] < 0.7 * noise[False]


def test_primary_ray_hitting_the_room_first_contributes_nothing():
    wall_v, wall_f = quad((0, -1.5, 0), (2, 0, 0), (0, 0, 2))  # between camera and sphere
    sc = build_scene(wall_v, wall_f, None, [sphere_object()], env_radiance=np.ones(3))
    fb = render(sc, camera(), np.ones((36, 48), bool), RenderSettings(spp=4, spp_min=4), np.random.default_rng(0))
    assert fb.coverage.max() == 0 and fb.pbr.max() == 0 and fb.ao.min() == 1.0


def test_coverage_is_fractional_on_edges_and_outputs_are_deterministic():
    sc = build_scene(*EMPTY, [sphere_object(specular=0.0)], env_radiance=np.ones(3))
    s = RenderSettings(spp=16, spp_min=16)
    mask = trace_mask(np.ones((36, 48), np.uint16), 1)
    a = render(sc, camera(), mask, s, np.random.default_rng(5))
    b = render(sc, camera(), mask, s, np.random.default_rng(5))
    for k in ("pbr", "ao", "coverage", "albedo", "normal"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    edge = (a.coverage > 0) & (a.coverage < 1)
    assert edge.sum() > 20
    # premultiplied: radiance equals coverage for a white furnace
    np.testing.assert_allclose(a.pbr[..., 0], a.coverage, atol=5e-3)
    # sphere's projected area: pi r'^2 with r' the silhouette radius in pixels
    d, r, f = 2.5, 0.5, 40.0
    r_px = f * r / np.sqrt(d * d - r * r)
    assert a.coverage.sum() == pytest.approx(np.pi * r_px ** 2, rel=0.03)


def test_adaptive_sampling_stops_early_on_noise_free_pixels():
    sc = build_scene(*EMPTY, [sphere_object(specular=0.0)], env_radiance=np.ones(3))
    fb = render(sc, camera(), np.ones((36, 48), bool), RenderSettings(spp=64, spp_min=4, spp_batch=4),
                np.random.default_rng(0))
    assert fb.spp[_interior(fb)].max() == 4  # zero variance inside: stop at spp_min
    assert fb.spp.max() > 4  # edge pixels are noisy (coverage) and go on


def test_trace_mask_dilates_labels_by_the_edge_band():
    lab = np.zeros((9, 9), np.uint16)
    lab[4, 4] = 3
    assert trace_mask(lab, 0).sum() == 1 and trace_mask(lab, 1).sum() == 9 and trace_mask(lab, 2).sum() == 25
    assert trace_mask(np.zeros((4, 4), np.uint16), 2).sum() == 0


def test_published_lights_give_irradiance_pi_at_the_floor_centre():
    rv, _ = box_room((0, 0, 0), (4, 6, 3), n=1)
    pl = published_lights(rv, np.array([0, 0, 1.0]), power=1.0)
    assert pl.count == 4 and np.all(pl.position[:, 2] == pytest.approx(2.7))
    d = pl.position - np.array([2, 3, 0])
    E = np.sum(pl.intensity[:, 0] * d[:, 2] / np.linalg.norm(d, axis=1) ** 3)
    assert E == pytest.approx(np.pi)


def test_published_mode_lights_an_object_from_above():
    rv, rf = box_room((-2, -3, -2), (2, 3, 2), n=4)
    sc = build_scene(rv, rf, None, [sphere_object(specular=0.0, albedo=0.5)], lighting="published")
    assert sc.point_lights.count == 4 and sc.emission.max() == 0
    cam = camera()
    fb = render(sc, cam, np.ones((36, 48), bool), RenderSettings(spp=16, spp_min=16), np.random.default_rng(0))
    top = fb.pbr[:12][_interior(fb)[:12]].mean()
    bottom = fb.pbr[-12:][_interior(fb)[-12:]].mean()
    assert top > 2 * bottom > 0  # lit from above, the bottom only by the room's bounce light


def test_texture_and_vertex_colour_models_give_their_base_colour():
    from pipeline.trace.scene import instance_from_model
    from pipeline.types import ObjectModel

    v, f, n = uv_sphere(0.5, n_lat=16, n_lon=32)
    uv = np.c_[(np.arctan2(v[:, 1], v[:, 0]) / (2 * np.pi)) % 1.0, 0.5 * (v[:, 2] / 0.5 + 1)].astype(np.float32)
    tex = np.zeros((8, 8, 3), np.uint8)
    tex[:, :6] = (255, 0, 0)  # u < 0.75: red
    tex[:, 6:] = (0, 0, 255)  # u >= 0.75: blue
    textured = ObjectModel(obj_id=1, name="t", source_path="", vertices=v, faces=f, normals=n, vertex_colors=None,
                           uv=uv, texture=tex)
    coloured = ObjectModel(obj_id=2, name="c", source_path="", vertices=v, faces=f, normals=n,
                           vertex_colors=np.full((len(v), 3), (188, 188, 0), np.uint8), uv=None, texture=None)
    plain = ObjectModel(obj_id=3, name="p", source_path="", vertices=v, faces=f, normals=n, vertex_colors=None,
                        uv=None, texture=None, base_color=(0.1, 0.2, 0.3))
    s = RenderSettings(spp=4, spp_min=4, ao_samples=0)
    for model, check in ((coloured, lambda a: np.allclose(a, [0.5, 0.5, 0.0], atol=3e-3)),
                         (plain, lambda a: np.allclose(a, [0.1, 0.2, 0.3], atol=1e-6))):
        sc = build_scene(*EMPTY, [instance_from_model(model, np.eye(3), np.zeros(3))], env_radiance=np.ones(3))
        fb = render(sc, camera(), np.ones((36, 48), bool), s, np.random.default_rng(0))
        assert all(check(a) for a in fb.albedo[_interior(fb)])
    # the camera on -y sees the y < 0 half (u in [0.5, 1]): red and blue halves
    sc = build_scene(*EMPTY, [instance_from_model(textured, np.eye(3), np.zeros(3))], env_radiance=np.ones(3))
    fb = render(sc, camera(), np.ones((36, 48), bool), s, np.random.default_rng(0))
    a = fb.albedo[_interior(fb)]
    red = np.all(np.isclose(a, [1, 0, 0], atol=1e-6), axis=1)
    blue = np.all(np.isclose(a, [0, 0, 1], atol=1e-6), axis=1)
    assert red.sum() > 50 and blue.sum() > 50 and (red | blue).mean() > 0.8


# --------------------------------------------------------------------------------------------------
# Photo-based lighting (pipeline/trace/photolights.py)
# --------------------------------------------------------------------------------------------------

def _open_room():
    """Box room (-2,-3,-2)..(2,3,2) without its ceiling (z = 2): rays upward escape, as through a scan's hole."""
    rv, rf = box_room((-2, -3, -2), (2, 3, 2), n=8)
    keep = ~(rv[rf][:, :, 2] > 1.99).all(axis=1)
    return rv, rf[keep]


def _photo_of(room_scene, cam, lamp, miss_value):
    """What a camera sees: 255 on ``lamp(points)``, 128 elsewhere on the room, ``miss_value`` where rays escape."""

    n = cam.width * cam.height
    o, d = cam.rays(np.arange(n), np.full((n, 2), 0.5))
    h = room_scene.intersector.intersect(o, d)
    p = o + np.where(h.hit, h.t, 0)[:, None] * d
    val = np.where(h.hit, np.where(lamp(p), 255, 128), miss_value).astype(np.uint8)
    return np.repeat(val[:, None], 3, axis=1).reshape(cam.height, cam.width, 3)


@pytest.mark.parametrize("miss_value", [200, 255])
def test_photo_lights_mark_clipped_vertices_and_map_escaping_rays(miss_value):
    from pipeline.trace.photolights import photo_lights

    rv, rf = _open_room()
    room = build_scene(rv, rf, None, [])
    cam = camera(eye=(0.0, -2.0, 0.0), target=(0.0, 1.0, 1.6), w=64, h=48, f=30.0)

    def lamp(p):  # a clipped patch on the far wall y = 3
        return (p[:, 1] > 2.99) & (np.abs(p[:, 0]) < 1.0) & (p[:, 2] > -1.0) & (p[:, 2] < 0.5)

    photo = _photo_of(room, cam, lamp, miss_value)
    assert (photo == 255).any() and (photo == 128).any() and (photo == miss_value).any()
    pl = photo_lights(room.vertices, room.faces, room.intersector, [(photo, cam.K, cam.T_c2w)] * 2,
                      up=np.array([0.0, 0.0, 1.0]), stride=1, light_gain=4.0)
    lv = rv[pl.light_vertices]
    cell = 0.75  # box_room cell size on the y = 3 wall (4 m / 8 in x, 4 m / 8 in z) + margin
    assert len(lv) >= 4 and (lv[:, 1] > 2.99).all() and (np.abs(lv[:, 0]) <= 1.0 + cell).all()
    assert (lv[:, 2] >= -1.0 - cell).all() and (lv[:, 2] <= 0.5 + cell).all()
    assert pl.seen[pl.light_vertices].min() >= 2 and pl.frames_used == 2
    seen = pl.env_count > 0
    want = float(srgb_to_linear(np.uint8(miss_value))) * (4.0 if miss_value == 255 else 1.0)
    assert seen.any() and (~seen).any()
    np.testing.assert_allclose(pl.env[seen], want, rtol=1e-5)
    np.testing.assert_allclose(pl.env[~seen], want, rtol=1e-5)   # fallback: mean of the seen bins
    # the seen bins point up (the open ceiling), the energy-balance samples are unclipped room points
    from pipeline.trace.photolights import ENV_H
    assert np.flatnonzero(seen.any(axis=1)).max() < ENV_H // 2
    grey = float(srgb_to_linear(np.uint8(128)))   # a grey's luminance is its value (weights sum to 1)
    assert len(pl.points) > 0 and np.allclose(pl.radiance, grey, rtol=1e-5)


def test_balance_unseen_gives_radiance_over_albedo_under_an_open_sky():
    """A floor alone: every hemisphere ray of a floor point escapes unseen, so the unseen radiance is L / rho."""
    from pipeline.trace.photolights import ENV_H, ENV_W, PhotoLights, balance_unseen

    fv, ff = grid_quad((0, 0, 0), (2, 0, 0), (0, 2, 0), 4)
    floor = build_scene(fv, ff, None, [], room_linear_radiance=np.full((len(fv), 3), 0.2),
                        up=np.array([0.0, 0.0, 1.0]))
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (50, 2)), np.zeros(50)].astype(np.float32)
    pl = PhotoLights(light_vertices=np.zeros(len(fv), bool), seen=np.zeros(len(fv), np.int32),
                     clipped=np.zeros(len(fv), np.int32), env=np.zeros((ENV_H, ENV_W, 3), np.float32),
                     env_count=np.zeros((ENV_H, ENV_W), np.int32), frames_used=1, points=pts,
                     normals=np.tile(np.float32([0, 0, 1]), (50, 1)), radiance=np.full(50, 0.2, np.float32))
    assert balance_unseen(floor, pl, np.random.default_rng(1), albedo=0.5) == pytest.approx(0.4, rel=1e-5)
    assert balance_unseen(floor, pl, np.random.default_rng(1), albedo=0.25) == pytest.approx(0.8, rel=1e-5)
    # a closed emitting room leaves nothing unseen: no vote, None (the stage keeps its constant fallback)
    rv, rf = box_room((-2, -3, -2), (2, 3, 2), n=4)
    box = build_scene(rv, rf, None, [], room_linear_radiance=np.full((len(rv), 3), 0.3))
    pl2 = dataclasses.replace(pl, points=np.c_[pts[:, :2], np.full(50, -1.99, np.float32)].astype(np.float32))
    assert balance_unseen(box, pl2, np.random.default_rng(1)) is None


def test_light_vertices_become_sampled_lights_and_are_checked():
    rv, rf = box_room((-2, -3, -2), (2, 3, 2), n=4)
    col = np.full((len(rv), 3), 128, np.uint8)
    lv = rv[:, 2] > 1.99
    sc = build_scene(rv, rf, col, [], light_gain=4.0, radiance_scale=2.0, light_vertices=lv)
    np.testing.assert_allclose(sc.emission[:len(rv)][lv], 8.0)
    np.testing.assert_allclose(sc.emission[:len(rv)][~lv], srgb_to_linear(np.uint8(128)) * 2.0, rtol=1e-6)
    assert sc.area_lights.count > 0
    assert build_scene(rv, rf, col, [], light_vertices=np.zeros(len(rv), bool)).area_lights.count == 0
    assert build_scene(rv, rf, col, [], light_gain=0.0, light_vertices=lv).area_lights.count == 0
    with pytest.raises(ValueError, match="light_vertices"):
        build_scene(rv, rf, col, [], light_vertices=lv[:-1])


def test_white_furnace_under_an_environment_map():
    """A uniform environment map of radiance 1 is the furnace; a map bright only above lights the top."""
    from pipeline.trace.photolights import ENV_H, ENV_W

    env = np.ones((ENV_H, ENV_W, 3), np.float32)
    sc = build_scene(*EMPTY, [sphere_object(specular=0.0)], env_map=env, up=np.array([0.0, 0.0, 1.0]))
    fb = render(sc, camera(), np.ones((36, 48), bool), RenderSettings(spp=8, spp_min=8), np.random.default_rng(0))
    px = fb.pbr[_interior(fb)]
    assert px.size > 300 and abs(px.mean() - 1.0) < TRACE_FURNACE_REL_TOL
    top = env.copy()
    top[ENV_H // 2:] = 0.0   # nothing from below the horizon
    sc = build_scene(*EMPTY, [sphere_object(specular=0.0)], env_map=top, up=np.array([0.0, 0.0, 1.0]))
    fb = render(sc, camera(), np.ones((36, 48), bool), RenderSettings(spp=8, spp_min=8), np.random.default_rng(0))
    lum = fb.pbr.mean(axis=2)
    inner = _interior(fb)
    rows = np.arange(36)[:, None] * np.ones((1, 48))
    top, bottom = lum[inner & (rows < 14)].mean(), lum[inner & (rows > 21)].mean()   # image y down
    assert top > 0.75 and bottom < 0.25


@pytest.mark.parametrize("level", [0, 255])
def test_photo_lighting_of_black_and_saturated_photos_is_finite(level):
    """All-black photos see no light and leave nothing to balance; all-saturated ones make every seen vertex a
    light and an environment of light_gain: finite either way, and the tracer renders finite radiance."""
    from pipeline.trace.photolights import balance_unseen, photo_lights

    rv, rf = _open_room()
    room = build_scene(rv, rf, None, [], up=np.array([0.0, 0.0, 1.0]))
    cam = camera(eye=(0.0, -2.0, 0.0), target=(0.0, 1.0, 1.6), w=32, h=24, f=15.0)
    photo = np.full((24, 32, 3), level, np.uint8)
    pl = photo_lights(room.vertices, room.faces, room.intersector, [(photo, cam.K, cam.T_c2w)],
                      up=np.array([0.0, 0.0, 1.0]), stride=1, light_gain=4.0)
    assert np.isfinite(pl.env).all() and (pl.env >= 0).all()
    assert pl.light_vertices.any() == (level == 255)
    x = balance_unseen(room, pl, np.random.default_rng(0))
    assert x is None if level == 255 else (x is not None and x == 0.0)   # clipped points do not vote
    sc = build_scene(rv, rf, None, [sphere_object()], light_vertices=pl.light_vertices, env_map=pl.env,
                     up=np.array([0.0, 0.0, 1.0]))
    fb = render(sc, camera(), np.ones((36, 48), bool), RenderSettings(spp=2, spp_min=2), np.random.default_rng(0))
    assert np.isfinite(fb.pbr).all()


def test_frame_exposure_is_one_for_too_few_room_pixels_and_clamped():
    from pipeline.trace.photolights import EXPOSURE_RANGE, frame_exposure

    rv, rf = box_room((-2, -3, -2), (2, 3, 2), n=4)
    col = np.full((len(rv), 3), 128, np.uint8)
    sc = build_scene(rv, rf, col, [])
    cam = camera(w=48, h=36)
    assert frame_exposure(sc, cam, np.full((36, 48, 3), 128, np.uint8)) == pytest.approx(1.0, rel=1e-5)
    assert frame_exposure(sc, cam, np.full((36, 48, 3), 255, np.uint8)) == 1.0   # all clipped: unmeasurable
    assert frame_exposure(sc, cam, np.full((36, 48, 3), 6, np.uint8)) == 1.0     # near black: unmeasurable
    dim = build_scene(rv, rf, np.full((len(rv), 3), 50, np.uint8), [])   # mesh far darker than the photo
    assert frame_exposure(dim, cam, np.full((36, 48, 3), 240, np.uint8)) == EXPOSURE_RANGE[1]
    assert frame_exposure(sc, cam, np.full((10, 10, 3), 128, np.uint8)) == 1.0   # not the camera's size
    assert frame_exposure(build_scene(*EMPTY, [sphere_object()]), cam, np.full((36, 48, 3), 128, np.uint8)) == 1.0


# --------------------------------------------------------------------------------------------------
# The objects' shadows taken out of the room's light the objects see (fit lighting)
# --------------------------------------------------------------------------------------------------

def _shadow_scene(albedo: float = 0.5, roof: bool = False):
    """A 4 m floor (radiance 0.3, albedo ``albedo``), a 10 cm light 1 m above it (radiance 100, facing
    down), a 20 cm cube 0.1-0.3 m above the floor under the light; ``roof``: a room plate at 0.6 m over the
    floor's -x half, to x = 0 (it hides the light from x < -0.01)."""
    from pipeline.trace.lightfit import RoomLights

    fv, ff = grid_quad((0, 0, 0), (2, 0, 0), (0, 2, 0), 8)
    lv, lf = quad((0, 0, 1.0), (0.05, 0, 0), (0, -0.05, 0))            # normal -z
    parts = [(fv, ff, 0.3, albedo, False), (lv, lf, 100.0, 0.0, True)]
    if roof:
        rv_, rf_ = quad((-0.95, 0, 0.6), (0.95, 0, 0), (0, 0.95, 0))
        parts.append((rv_, rf_, 0.3, albedo, False))
    V, F, rad, alb, lt, off = [], [], [], [], [], 0
    for v, f, r, a, light in parts:
        V.append(v)
        F.append(f + off)
        rad.append(np.full((len(v), 3), r, np.float32))
        alb.append(np.full((len(v), 3), a, np.float32))
        lt.append(np.full(len(f), light))
        off += len(v)
    rl = RoomLights(vertices=np.concatenate(V).astype(np.float32), faces=np.concatenate(F).astype(np.int32),
                    radiance=np.concatenate(rad), light_tri=np.concatenate(lt), num_mesh_vertices=off,
                    num_mesh_tris=sum(len(f) for f in F), albedo=np.concatenate(alb))
    bv, bf = box_room((-0.1, -0.1, 0.1), (0.1, 0.1, 0.3), n=2)
    bf = bf[:, ::-1]                                                      # outward
    cube = ObjectInstance(vertices=bv, faces=bf, normals=np.zeros_like(bv) + [0, 0, 1],
                          albedo=np.full((len(bv), 3), 0.5, np.float32))
    return (build_scene(np.zeros((0, 3)), np.zeros((0, 3), np.int32), None, [cube], lighting="fit", room_lights=rl),
            rl.albedo)


def _room_seen_from_above(scene_albedo, points, samples=256, seed=0):
    """What object paths arriving straight down at floor ``points (n, 3)`` see there."""
    from pipeline.trace.pbr import _emission, object_shadows, shadowed_room_radiance
    from pipeline.trace.shadow import split_intersectors

    scene, albedo = scene_albedo
    ri, oi = split_intersectors(scene)
    sh = object_shadows(scene, ri, oi, albedo, samples=samples, min_effect=0.01)
    n = len(points)
    org = (np.asarray(points, np.float32) + [0, 0, 0.05]).astype(np.float32)
    wi = np.tile(np.float32([0, 0, -1]), (n, 1))
    h = scene.intersector.intersect(org, wi)
    assert h.hit.all() and (scene.tri_inst[h.prim] == 0).all()
    Le = _emission(scene, h.prim, h.u, h.v, wi, False)
    return Le, shadowed_room_radiance(scene, sh, org, wi, h.t, h.prim, h.u, h.v, Le,
                                      np.random.default_rng(seed), 1e-4)


def test_room_point_under_an_object_loses_the_direct_light_it_blocks():
    scene = _shadow_scene()
    # under the cube (the light hidden) and 0.5 m aside (the light seen past the cube, within its reach)
    Le, out = _room_seen_from_above(scene, [(0.02, -0.03, 0.0), (0.5, 0.0, 0.0)])
    assert np.allclose(Le, 0.3)
    # the light, 1 m straight up, 0.1 x 0.1 m, radiance 100: E = 100 * 0.01 * cos * cos / d^2, analytic
    # for the point under it (cos = 1, d = 1 within 0.2 %); taken away at albedo / pi
    E = 100.0 * 0.01 / (1.0 + 0.02 ** 2 + 0.03 ** 2) ** 2
    assert out[0] == pytest.approx(np.full(3, max(0.3 - 0.5 / np.pi * E, 0.0)), abs=0.01)
    assert 0.3 - 0.5 / np.pi * E > 0.05          # the test's numbers leave a shadowed point above 0
    assert np.allclose(out[1], 0.3)              # the cube hides no light from it


def test_object_shadow_needs_the_light_to_reach_the_room_and_never_goes_negative():
    # a point the room itself hides from the light keeps its radiance; a bright albedo clamps at 0
    scene = _shadow_scene(roof=True)
    _, out = _room_seen_from_above(scene, [(-0.08, 0.0, 0.0)])
    assert np.allclose(out, 0.3)                # under the cube, but the roof hides the light anyway
    scene = _shadow_scene(albedo=5.0)
    _, out = _room_seen_from_above(scene, [(0.0, 0.0, 0.0)])
    assert np.all(out >= 0) and np.allclose(out, 0.0)


def test_object_shadows_are_off_without_albedo_or_samples():
    from pipeline.trace.pbr import object_shadows
    from pipeline.trace.shadow import split_intersectors

    scene, albedo = _shadow_scene(albedo=0.0)
    ri, oi = split_intersectors(scene)
    assert object_shadows(scene, ri, oi, albedo, samples=4, min_effect=0.04) is None
    assert object_shadows(scene, ri, oi, None, samples=4, min_effect=0.04) is None
    scene, albedo = _shadow_scene()
    assert object_shadows(scene, ri, oi, albedo, samples=0, min_effect=0.04) is None


@pytest.mark.parametrize("seen_side, lights, expect", [(1, False, 0.0), (-1, False, 0.2), (0, False, 0.2),
                                                        (1, True, 0.2)])
def test_fitted_room_sends_light_only_to_the_side_the_cameras_saw(seen_side, lights, expect):
    """A scan is a shell of sheets seen from one side: a ray meeting a table top from below must not take
    the lit top's colour. Here the whole room is wound outward, so the side vote decides alone: +1 (the
    cameras saw the fronts, i.e. the room from outside) leaves the sphere inside in the dark; -1 and 0
    (both sides) light it as a furnace of 0.2. Lights (clipped regions) stay two-sided, as next-event
    estimation samples them both ways."""
    from pipeline.trace.lightfit import RoomLights

    rv, rf = box_room((-2, -3, -2), (2, 3, 2), n=4)
    rf = np.ascontiguousarray(rf[:, ::-1])           # box_room winds inward; this room faces out
    rl = RoomLights(vertices=rv.astype(np.float32), faces=rf.astype(np.int32),
                    radiance=np.full((len(rv), 3), 0.2, np.float32), light_tri=np.full(len(rf), lights),
                    num_mesh_vertices=len(rv), num_mesh_tris=len(rf), summary={"seen_side": seen_side})
    sc = build_scene(np.zeros((0, 3)), np.zeros((0, 3), np.int32), None, [sphere_object(specular=0.0)],
                     lighting="fit", room_lights=rl)
    fb = render(sc, camera(), np.ones((36, 48), bool), RenderSettings(spp=8, spp_min=8), np.random.default_rng(0))
    px = fb.pbr[_interior(fb)]
    assert px.size > 300
    if expect == 0.0:
        assert px.max() == 0.0
    else:
        assert abs(px.mean() - expect) < expect * TRACE_FURNACE_REL_TOL


def test_a_rooms_intersector_serves_every_scene_of_that_room():
    """The trace stage builds a room's own intersector once per worker and reuses it for the next drop: that
    holds while every scene of the room starts with the same room triangles, whatever objects follow. Rays
    through the room and the objects' place give the same hits as the intersector built for each scene."""
    from pipeline.trace.shadow import split_intersectors

    rv, rf = box_room((-2, -2, 0), (2, 2, 2.5), n=3)
    a = build_scene(rv, rf, None, [sphere_object(0.3, (0.0, 0.0, 1.0))])
    b = build_scene(rv, rf, None, [sphere_object(0.2, (0.5, 0.5, 0.5)), sphere_object(0.4, (-1.0, 0.0, 1.0))])
    room_a, _ = split_intersectors(a)
    room_b, objs_b = split_intersectors(b, room_a)
    assert room_b is room_a
    rng = np.random.default_rng(0)
    org = rng.uniform((-1.5, -1.5, 0.1), (1.5, 1.5, 2.4), (2000, 3)).astype(np.float32)   # inside the room
    d = rng.normal(size=(2000, 3)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    own, _ = split_intersectors(b)
    h1, h2 = room_b.intersect(org, d), own.intersect(org, d)
    assert h1.hit.all() and np.array_equal(h1.prim, h2.prim) and np.array_equal(h1.t, h2.t)
    assert objs_b.intersect(org, d).hit.any()                   # the objects are b's own
    assert np.array_equal(a.vertices[a.faces[:a.num_room_tris]], b.vertices[b.faces[:b.num_room_tris]])
