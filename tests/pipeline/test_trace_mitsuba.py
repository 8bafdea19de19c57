"""The path tracer against Mitsuba 3 (scalar_rgb) on small scenes with the room as area emitter.

Lambert (``specular = 0``) against Mitsuba's ``diffuse``, the white metal against ``roughconductor`` and
the default object material (metallic 0, specular 1) against ``principled`` (see
:mod:`pipeline.trace.bsdf`).

Mitsuba is a test/benchmark-only dependency: these tests skip when it is not installed. Scenes are
built here from NumPy meshes, written as PLY (RGB float vertex colours in [0, 1]) to a temporary
folder, rendered by both renderers at the same camera, and compared over the pixels fully covered by
objects (relative RMSE = RMS difference / mean reference value).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.tolerances import (TRACE_MITSUBA_PRINCIPLED_REL_RMSE_MAX, TRACE_MITSUBA_REL_BIAS_MAX,
                                 TRACE_MITSUBA_REL_RMSE_MAX)
from pipeline.camera import Camera
from pipeline.trace.pbr import RenderSettings, render
from pipeline.trace.scene import ObjectInstance, build_scene
from tests.pipeline.shapes import grid_quad, look_at, uv_sphere

pytestmark = pytest.mark.slow

W, H, F = 48, 36, 42.0
SPP_OURS = 2048
SPP_MITSUBA = 2048
MAX_DEPTH = 8  # scattering events (Mitsuba's max_depth counts the camera segment too: + 1)
REL_RMSE_MAX = TRACE_MITSUBA_REL_RMSE_MAX  # the issue's figure (noise of both renderers included)
REL_BIAS_MAX = TRACE_MITSUBA_REL_BIAS_MAX  # mean difference over object pixels: the systematic part
SPP_PRINCIPLED = 4096  # glossy highlights are noisier: ~2 % relative RMSE at 2048 spp each, ~1.5 % at 4096


def write_ply(path: Path, v: np.ndarray, f: np.ndarray, n: np.ndarray, c: np.ndarray) -> str:
    """Binary PLY with float positions, normals and RGB colours (floats in [0, 1], as Mitsuba wants)."""
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            "property float nx\nproperty float ny\nproperty float nz\n"
            "property float r\nproperty float g\nproperty float b\n"
            f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    vert = np.concatenate([v, n, c], axis=1).astype("<f4")
    face = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", 3)])
    face["n"] = 3
    face["i"] = f
    path.write_bytes(head.encode() + vert.tobytes() + face.tobytes())
    return str(path)


def room_patches(lo=(-2.0, -3.0, -1.5), hi=(2.5, 2.0, 2.0), split=2, n=3):
    """The room as ``6 * split^2`` inward-facing patches, each of one constant colour.

    Mitsuba 3.9 (scalar_rgb) crashes on an area emitter whose radiance is a ``mesh_attribute``, so the
    room's radiance varies patch by patch (a constant per emitter shape) instead of per vertex.
    Returns a list of ``(vertices, faces, radiance (3,))``.
    """
    lo, hi = np.asarray(lo), np.asarray(hi)
    c, h = 0.5 * (lo + hi), 0.5 * (hi - lo)
    ex, ey, ez = np.eye(3)
    sides = [(c - h[2] * ez, h[0] * ex, h[1] * ey), (c + h[2] * ez, h[1] * ey, h[0] * ex),
             (c - h[1] * ey, h[2] * ez, h[0] * ex), (c + h[1] * ey, h[0] * ex, h[2] * ez),
             (c - h[0] * ex, h[1] * ey, h[2] * ez), (c + h[0] * ex, h[2] * ez, h[1] * ey)]
    rng = np.random.default_rng(11)
    out = []
    for cen, u, v in sides:
        for i in range(split):
            for j in range(split):
                pc = cen + ((2 * i + 1) / split - 1) * u + ((2 * j + 1) / split - 1) * v
                pv, pf = grid_quad(pc, u / split, v / split, n)
                out.append((pv, pf, rng.uniform(0.15, 1.0, 3).astype(np.float32)))
    return out


def sphere(radius, center, color, **mat):
    v, f, n = uv_sphere(radius, center, n_lat=48, n_lon=96)
    c = np.broadcast_to(np.asarray(color, np.float32), v.shape).copy()
    return ObjectInstance(vertices=v, faces=f, normals=n, albedo=c, **mat)


def striped_sphere(radius, center, c1, c2, **mat):
    v, f, n = uv_sphere(radius, center, n_lat=48, n_lon=96)
    phi = np.arctan2(v[:, 1] - center[1], v[:, 0] - center[0])
    stripe = (np.cos(3 * phi) > 0)[:, None]
    c = np.where(stripe, np.asarray(c1, np.float32), np.asarray(c2, np.float32))
    return ObjectInstance(vertices=v, faces=f, normals=n, albedo=c, **mat)


def scenes() -> dict[str, list[ObjectInstance]]:
    return {
        "lit_by_room": [striped_sphere(0.5, (0.0, 0.0, 0.0), (0.8, 0.3, 0.2), (0.2, 0.6, 0.7), specular=0.0)],
        "inter_reflection": [sphere(0.42, (-0.44, 0.0, 0.0), (0.9, 0.9, 0.9), specular=0.0),
                             sphere(0.42, (0.44, 0.0, 0.0), (0.9, 0.5, 0.3), specular=0.0)],
        "metallic": [sphere(0.5, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), metallic=1.0, roughness=0.5)],
    }


def default_material_spheres(roughness: float = 0.5) -> list[ObjectInstance]:
    """Two striped spheres of the default object material (metallic 0, specular 1) at ``roughness``."""
    return [striped_sphere(0.42, (-0.44, 0.0, 0.0), (0.8, 0.3, 0.2), (0.2, 0.6, 0.7), roughness=roughness),
            striped_sphere(0.42, (0.44, 0.0, 0.0), (0.9, 0.9, 0.9), (0.1, 0.1, 0.1), roughness=roughness)]


def camera() -> Camera:
    K = np.array([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1.0]])
    return Camera(K=K, T_c2w=look_at((0.3, -2.4, 0.5), (0.0, 0.0, 0.0)), width=W, height=H)


def mitsuba_bsdf(ob: ObjectInstance, dielectric: str = "principled") -> dict:
    """Mitsuba's BSDF matching ``ob``'s material (base colour = the PLY's vertex colours).

    ``dielectric`` picks the reference for a non-metal with a specular lobe: ``"principled"`` (the model
    :mod:`pipeline.trace.bsdf` implements), or ``"roughplastic"`` / ``"roughplastic_nonlinear"`` (for
    comparison only).
    """
    if ob.metallic >= 1.0:
        assert np.all(ob.albedo == 1.0)  # F = 1: Mitsuba's conductor with material "none"
        return {"type": "roughconductor", "material": "none", "distribution": "ggx",
                "alpha": float(ob.roughness) ** 2, "sample_visible": True}
    assert ob.metallic == 0.0
    vc = {"type": "mesh_attribute", "name": "vertex_color"}
    if np.all(ob.albedo == ob.albedo[:1]):  # roughplastic needs a texture with a mean: a constant colour
        vc = {"type": "rgb", "value": ob.albedo[0].tolist()}
    if ob.specular == 0.0:
        return {"type": "diffuse", "reflectance": vc}
    if dielectric == "principled":
        # F0 = 0.04 specular = 0.08 specular_mitsuba (eta = 1.5 at specular 1)
        return {"type": "principled", "base_color": vc, "metallic": 0.0, "roughness": float(ob.roughness),
                "specular": 0.5 * float(ob.specular), "spec_tint": 0.0, "sheen": 0.0, "clearcoat": 0.0,
                "anisotropic": 0.0, "spec_trans": 0.0}
    f0 = 0.04 * float(ob.specular)
    return {"type": "roughplastic", "distribution": "ggx", "alpha": float(ob.roughness) ** 2,
            "int_ior": float((1 + np.sqrt(f0)) / (1 - np.sqrt(f0))), "ext_ior": 1.0,
            "nonlinear": dielectric.endswith("nonlinear"), "diffuse_reflectance": vc}


def render_mitsuba(tmp: Path, patches, objects: list[ObjectInstance], cam: Camera, spp: int,
                   dielectric: str = "principled") -> np.ndarray:
    mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 is a test-only dependency (pip install mitsuba)")
    mi.set_variant("scalar_rgb")
    from pipeline.trace.scene import vertex_normals

    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": MAX_DEPTH + 1}}
    for k, (pv, pf, rad) in enumerate(patches):
        scene[f"room{k}"] = {
            "type": "ply",
            "filename": write_ply(tmp / f"room{k}.ply", pv, pf, vertex_normals(pv, pf), np.tile(rad, (len(pv), 1))),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": rad.tolist()}}}
    for k, ob in enumerate(objects):
        b = mitsuba_bsdf(ob, dielectric)
        scene[f"obj{k}"] = {"type": "ply", "filename": write_ply(tmp / f"obj{k}.ply", ob.vertices, ob.faces,
                                                                 ob.normals, ob.albedo), "bsdf": b}
    T = cam.T_c2w
    eye = T[:3, 3]
    fov_x = float(np.degrees(2 * np.arctan(cam.width / (2 * cam.K[0, 0]))))
    scene["sensor"] = {
        "type": "perspective", "fov": fov_x, "fov_axis": "x",
        "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(), target=(eye + T[:3, 2]).tolist(),
                                                   up=(-T[:3, 1]).tolist()),
        "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height, "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": spp, "seed": 7},
    }
    img = mi.render(mi.load_dict(scene))
    return np.array(img, dtype=np.float64)[..., :3]


def room_mesh(patches) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The patches as one room mesh: vertices, faces and per-vertex linear radiance."""
    rv = np.concatenate([p[0] for p in patches])
    offs = np.cumsum([0] + [len(p[0]) for p in patches])[:-1]
    rf = np.concatenate([p[1] + o for p, o in zip(patches, offs)])
    rad = np.concatenate([np.tile(p[2], (len(p[0]), 1)) for p in patches])
    return rv, rf, rad


def compare(tmp: Path, objects: list[ObjectInstance], spp_ours: int = SPP_OURS, spp_mitsuba: int = SPP_MITSUBA,
            dielectric: str = "principled", seed: int = 0) -> tuple[float, float]:
    """Relative RMSE and relative mean bias of our render against Mitsuba's over fully covered pixels."""
    patches = room_patches()
    rv, rf, rad = room_mesh(patches)
    cam = camera()
    ref = render_mitsuba(tmp, patches, objects, cam, spp_mitsuba, dielectric)
    sc = build_scene(rv, rf, None, objects, room_linear_radiance=rad)
    s = RenderSettings(spp=spp_ours, spp_min=spp_ours, spp_batch=64, max_depth=MAX_DEPTH, rr_depth=3, ao_samples=0)
    ours = render(sc, cam, np.ones((H, W), bool), s, np.random.default_rng(seed))
    from scipy.ndimage import binary_erosion

    m = binary_erosion(ours.coverage >= 1.0, iterations=1)
    assert m.sum() > 150
    diff = ours.pbr[m].astype(np.float64) - ref[m]
    rel = float(np.sqrt(np.mean(diff ** 2)) / np.mean(ref[m]))
    bias = float(np.mean(diff) / np.mean(ref[m]))
    return rel, bias


@pytest.mark.parametrize("name", ["lit_by_room", "inter_reflection", "metallic"])
def test_matches_mitsuba_within_two_percent(name, tmp_path):
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is a test-only dependency (pip install mitsuba)")
    rel, bias = compare(tmp_path, scenes()[name])
    assert rel <= REL_RMSE_MAX, f"{name}: relative RMSE {rel:.4f}, relative bias {bias:+.4f}"
    assert abs(bias) <= REL_BIAS_MAX, f"{name}: relative bias {bias:+.4f}"


@pytest.mark.parametrize("roughness", [0.3, 0.5, 0.8])
def test_default_material_matches_mitsuba_principled(roughness, tmp_path):
    """The default object material (roughness 0.5) and a smoother and a rougher one against ``principled``
    (Disney diffuse with retro-reflection, dielectric Fresnel of IOR 1.5): the old Lambert x (1 - F) +
    Schlick model was 4-7 % darker here."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is a test-only dependency (pip install mitsuba)")
    rel, bias = compare(tmp_path, default_material_spheres(roughness), SPP_PRINCIPLED, SPP_PRINCIPLED)
    assert rel <= TRACE_MITSUBA_PRINCIPLED_REL_RMSE_MAX, f"relative RMSE {rel:.4f}, relative bias {bias:+.4f}"
    assert abs(bias) <= REL_BIAS_MAX, f"relative bias {bias:+.4f}"


@pytest.mark.parametrize("metallic", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("roughness", [0.05, 0.3, 0.5, 0.8, 1.0])
def test_bsdf_equals_mitsuba_principled_pointwise(metallic, roughness):
    """``f cos`` of :mod:`pipeline.trace.bsdf` (specular 1) equals Mitsuba's ``principled`` ``eval`` at random
    direction pairs: the same model term for term, not only on average over a render."""
    mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 is a test-only dependency (pip install mitsuba)")
    mi.set_variant("scalar_rgb")
    from pipeline.trace import bsdf

    base = np.array([0.8, 0.45, 0.1])
    ref = mi.load_dict({"type": "principled", "base_color": {"type": "rgb", "value": base.tolist()},
                        "metallic": metallic, "roughness": roughness, "specular": 0.5, "spec_tint": 0.0,
                        "sheen": 0.0, "clearcoat": 0.0, "anisotropic": 0.0, "spec_trans": 0.0})
    rng = np.random.default_rng(5)
    n = 300
    d = rng.normal(size=(2, n, 3))
    d[..., 2] = np.abs(d[..., 2]) + 1e-3
    wo, wi = d / np.linalg.norm(d, axis=2, keepdims=True)
    ours = bsdf.eval_f_cos(wo, wi, bsdf.Material(np.tile(base, (n, 1)), np.full(n, metallic),
                                                 np.full(n, roughness), np.ones(n)))
    ctx, si = mi.BSDFContext(), mi.SurfaceInteraction3f()
    theirs = np.empty((n, 3))
    for k in range(n):  # Mitsuba's si.wi is the direction towards the camera (our wo), local frame
        si.wi = mi.Vector3f(*wo[k])
        theirs[k] = np.array(ref.eval(ctx, si, mi.Vector3f(*wi[k])))[:3]
    np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-7 * theirs.max())  # float32 Mitsuba
