"""Compositor benchmark: each blend against a path-traced "true image", PSNR/SSIM vs seconds per frame.

Run: ``nice .venv/bin/python -m bench.composite [--views N] [--quick]``. Writes
bench/results/composite.json + .png, composite_ablation.png (PSNR by region, SSIM and noise level of
every variant) and composite_views.png (photo, truth, published, full, per view). ``--sheet`` writes the
7-Scenes contact sheet to runs/bench-composite/composite_sheet.png (not committed: 7-Scenes terms).

What it does (everything rendered in this run, with the project's own path tracer, pipeline/trace):

- A small synthetic room (a 4 x 4 x 2.5 m box, textured by its vertex colours, a clipped lamp on the
  ceiling) holding two objects on the floor (a diffuse red ball and a glossy green one), seen from
  ``--views`` cameras at 160x120. The tracer's "scan" lighting is used throughout: the room emits its
  own decoded colours (the lamp with the clipped-light gain), exactly as the trace stage lights a real
  scan.
- **Photo**: the room alone, 4x4 supersampled (room radiance = its emitted colour), through a camera
  model: Gaussian optics blur (``CAM_BLUR`` px) in linear light, sRGB encoding (the curve the scan's
  colours are decoded with), per-channel sensor noise (``CAM_NOISE`` gray levels), 8-bit.
- **True image**: the same room with the objects in it, the same renderer and lights at reference
  quality: objects by :func:`pipeline.trace.pbr.render` at 256 spp (premultiplied radiance and
  coverage), the room behind them darkened by a brute-force shadow ratio computed here (256
  cosine-weighted rays per room pixel within 40 px of the objects, the same rays cast with and without
  the objects; a ray blocked by an object brings the object's albedo times the point's mean light,
  the one-bounce model the tracer's shadow pass states; independent of that pass's code), then
  the same camera with the SAME noise field as the
  photo (one exposure of one sensor).
- **Composites**: the trace passes at the trace stage's default settings (16 spp adaptive, AO, the
  PBR/AO denoiser of ``trace.denoise``, the shadow pass as the stage calls it; also 4 and 64 spp for
  the speed axis) composited onto the photo by
  :func:`pipeline.composite.composite_published` and :func:`composite_full` with each part switched
  on/off (ablation), plus a "naive tone" variant (rendered radiance encoded with gamma 2.2 instead of the
  inverse of the tracer's sRGB decode) and an "oracle shadow pass" variant (the reference shadow ratio in
  place of the trace stage's: what the compositor makes of an accurate shadow pass).
- **Metrics** over the objects and a band of 8 px around them plus every pixel the reference shadow
  darkens by more than 2 %: PSNR (dB, 8-bit) and SSIM (skimage, 7x7, mean of the SSIM map over the
  region); PSNR separately over edge pixels (0 < reference coverage < 1), shadow pixels and object
  interiors; sensor-noise match (noise estimated on object interiors of the composite and of the
  truth, gray levels). Speed: seconds per frame of the trace passes each blend needs plus the blend.

What it does not show: the physical accuracy of the tracer's lighting model (truth and composites use
the same model: the room as an emitter of its captured colours, one-bounce shadow ratio); real camera
effects beyond Gaussian blur and white noise (motion blur, JPEG, vignetting, auto exposure); real scan
errors (mesh holes, misregistration). PSNR/SSIM cannot reward matched noise: an independent noise
field of the right level doubles the noise error, so noise matching is judged by the noise-match
column, not by PSNR.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from bench.common import RESULTS, BenchResult

log = logging.getLogger("bench.composite")

W, H = 160, 120
CAM_BLUR = 1.0     # pixels, Gaussian sigma of the camera's optics blur
CAM_NOISE = 2.5    # gray levels (0..255), per-channel sensor noise
BAND = 8           # pixels around the objects in the metric region
REF_SPP, REF_SHADOW = 256, 256


def _room():
    from pipeline.trace.shapes import box_room

    rv, rf = box_room((-2, -2, 0), (2, 2, 2.5), n=40)
    x, y, z = rv[:, 0], rv[:, 1], rv[:, 2]
    col = np.zeros((len(rv), 3))
    floor, ceil = z < 1e-6, z > 2.5 - 1e-6
    checker = ((np.floor(x / 0.3) + np.floor(y / 0.3)) % 2)[:, None]
    col[floor] = (np.array([150, 120, 90]) + 50 * checker[floor])
    wall = ~floor & ~ceil
    stripes = (0.5 + 0.5 * np.sin(9.0 * (x + y) + 5.0 * z))[:, None]
    col[wall] = np.array([170, 175, 185]) * (0.8 + 0.2 * stripes[wall])
    col[ceil] = 200
    lamp = ceil & (np.abs(x) < 0.6) & (np.abs(y) < 0.6)
    col[lamp] = 255
    return rv, rf, np.clip(np.round(col), 0, 255).astype(np.uint8)


def _objects():
    from pipeline.trace.scene import ObjectInstance
    from pipeline.trace.shapes import uv_sphere

    out = []
    for r, c, alb, rough in (((0.2), (0.0, 0.0, 0.2), (0.6, 0.12, 0.08), 0.8),
                             ((0.11), (0.33, -0.22, 0.11), (0.15, 0.45, 0.2), 0.3)):
        v, f, n = uv_sphere(r, c, n_lat=24, n_lon=48)
        out.append(ObjectInstance(vertices=v, faces=f, normals=n, albedo=np.tile(np.float32(alb), (len(v), 1)),
                                  roughness=rough))
    return out


def _cameras(n: int):
    from pipeline.trace.pbr import Camera
    from pipeline.trace.shapes import look_at

    K = np.array([[150.0, 0, (W - 1) / 2], [0, 150.0, (H - 1) / 2], [0, 0, 1]])
    eyes = [(0.1, -1.5, 0.8), (1.0, -1.1, 0.6), (-0.9, -1.2, 1.1), (0.5, 1.3, 0.9)]
    return [Camera(K=K, T_c2w=look_at(e, (0.1, -0.05, 0.15)), width=W, height=H) for e in eyes[:n]]


def _emission_at(scene, prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(R, 3) emitted radiance interpolated at hits (barycentrics ``u``, ``v`` of vertices 1 and 2)."""
    f = scene.faces[prim]
    E = scene.emission
    return (1.0 - u - v)[:, None] * E[f[:, 0]] + u[:, None] * E[f[:, 1]] + v[:, None] * E[f[:, 2]]


def _room_radiance(room_scene, cam, ss: int = 4) -> np.ndarray:
    """Linear radiance of the room alone, ss x ss supersampled, (H, W, 3) float32 (clipped at 1 by the camera)."""
    from pipeline.trace.pbr import primary_rays

    pix = np.arange(W * H)
    acc = np.zeros((W * H, 3))
    s = (np.arange(ss) + 0.5) / ss
    for jy in s:
        for jx in s:
            o, d = primary_rays(cam, pix, np.tile([jx, jy], (W * H, 1)))
            h = room_scene.intersector.intersect(o, d)
            ok = h.hit
            acc[ok] += _emission_at(room_scene, h.prim[ok], h.u[ok], h.v[ok])
    return (acc / ss ** 2).reshape(H, W, 3).astype(np.float32)


def _reference_shadow_ratio(scene, room_scene, cam, labels: np.ndarray, rng: np.random.Generator, *,
                            samples: int = 256, band: int = 40) -> np.ndarray:
    """Brute-force shadow ratio (independent of pipeline/trace/shadow.py), (H, W) float32.

    For each room pixel within ``band`` px of the objects: the room point behind the pixel centre,
    ``samples`` cosine-weighted rays, cast against the room with the objects and against the room
    alone (the same rays). A ray that reaches the room brings the room's emitted radiance, one that
    escapes the environment radiance, one that hits an object the object's albedo times the mean
    light arriving at the point without objects (one-bounce estimate, the model the tracer's shadow
    pass states). Ratio of the two mean luminances; 1 elsewhere.
    """
    from scipy.ndimage import binary_dilation

    from pipeline.trace.pbr import primary_rays

    lum = np.array([0.2126, 0.7152, 0.0722])
    out = np.ones(W * H, np.float32)
    obj = labels > 0
    region = binary_dilation(obj, np.ones((3, 3), bool), iterations=band) & ~obj
    pix = np.flatnonzero(region)
    o, d = primary_rays(cam, pix, np.full((len(pix), 2), 0.5))
    h = room_scene.intersector.intersect(o, d)
    pix, o, d = pix[h.hit], o[h.hit], d[h.hit]
    t, prim = h.t[h.hit], h.prim[h.hit]
    V = room_scene.vertices.astype(np.float64)
    F = room_scene.faces[prim]
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
    n = np.where((np.einsum("ij,ij->i", n, d) > 0)[:, None], -n, n)
    p = o + t[:, None] * d + 1e-4 * n
    env = np.asarray(scene.env_radiance, np.float64) @ lum
    obj_alb = scene.albedo.astype(np.float64) @ lum

    def light(sc, hits, mean_light: np.ndarray | None) -> np.ndarray:
        L = np.full(len(hits.t), env)
        ok = hits.hit
        f = sc.faces[hits.prim[ok]]
        u, v = hits.u[ok], hits.v[ok]
        w = 1.0 - u - v
        E = sc.emission.astype(np.float64) @ lum
        val = w * E[f[:, 0]] + u * E[f[:, 1]] + v * E[f[:, 2]]
        if mean_light is not None:   # objects present: a blocked ray brings albedo x the point's mean light
            is_obj = sc.tri_inst[hits.prim[ok]] > 0
            alb = w * obj_alb[f[:, 0]] + u * obj_alb[f[:, 1]] + v * obj_alb[f[:, 2]]
            val = np.where(is_obj, alb * mean_light[ok], val)
        L[ok] = val
        return L

    chunk = max(1, 400_000 // samples)
    for a in range(0, len(pix), chunk):
        nn, pp = n[a:a + chunk], p[a:a + chunk]
        k = len(nn)
        u1, u2 = rng.random((k, samples)), rng.random((k, samples))
        r, phi = np.sqrt(u1), 2 * np.pi * u2
        loc = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], -1)   # (k, S, 3)
        helper = np.where(np.abs(nn[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        tt = np.cross(nn, helper)
        tt /= np.linalg.norm(tt, axis=1, keepdims=True)
        bb = np.cross(nn, tt)
        dirs = (loc[..., :1] * tt[:, None] + loc[..., 1:2] * bb[:, None] + loc[..., 2:] * nn[:, None]).reshape(-1, 3)
        orig = np.repeat(pp, samples, axis=0)
        dirs32, orig32 = dirs.astype(np.float32), orig.astype(np.float32)
        without = light(room_scene, room_scene.intersector.intersect(orig32, dirs32), None).reshape(k, samples).mean(1)
        with_obj = light(scene, scene.intersector.intersect(orig32, dirs32),
                         np.repeat(without, samples)).reshape(k, samples).mean(1)
        out[pix[a:a + chunk]] = np.where(without > 0, with_obj / np.maximum(without, 1e-12), 1.0)
    return out.reshape(H, W)


def _camera(lin: np.ndarray, noise: np.ndarray) -> np.ndarray:
    from pipeline import camera_look as cl

    x = cl.linear_to_srgb(cl.gaussian_blur(lin, CAM_BLUR)) * 255.0 + noise
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def _labels(scene, cam) -> np.ndarray:
    from pipeline.trace.pbr import primary_rays

    o, d = primary_rays(cam, np.arange(W * H), np.full((W * H, 2), 0.5))
    h = scene.intersector.intersect(o, d)
    return np.where(h.hit, scene.tri_inst[np.maximum(h.prim, 0)], 0).astype(np.uint16).reshape(H, W)


def _passes(scene, cam, labels, rng, spp: int, shadow: int):
    """The trace stage's passes at ``spp`` / ``shadow`` rays: (pbr, ao, coverage, sr, s_render, s_shadow)."""
    from pipeline.config import TraceConfig
    from pipeline.trace.pbr import trace_mask
    from pipeline.trace.pbr import render
    from pipeline.trace.shadow import shadow_ratio
    from pipeline.trace.stage import settings_from_config
    import dataclasses

    cfg = dataclasses.replace(TraceConfig(), spp=spp, spp_min=min(4, spp))
    t0 = time.perf_counter()
    fb = render(scene, cam, trace_mask(labels, cfg.edge_band), settings_from_config(cfg), rng)
    pbr, ao = fb.pbr, fb.ao
    if cfg.denoise != "off":   # as the trace stage does (trace.denoise, "auto" = OIDN when installed)
        from pipeline.trace.denoise import denoise, denoise_ao

        pbr = denoise(fb.pbr, fb.albedo, fb.normal, fb.coverage > 0, method=cfg.denoise)
        ao = denoise_ao(fb.ao, fb.normal, fb.coverage > 0, method=cfg.denoise)
    t1 = time.perf_counter()
    sr = shadow_ratio(scene, cam, labels, rng, samples=shadow, min_effect=cfg.shadow_min_effect,
                      stride=cfg.shadow_stride, smooth=cfg.shadow_smooth)
    t2 = time.perf_counter()
    return pbr, ao, fb.coverage, sr, t1 - t0, t2 - t1


def _metrics(img: np.ndarray, truth: np.ndarray, regions: dict[str, np.ndarray]) -> dict[str, float]:
    from skimage.metrics import structural_similarity

    from pipeline import camera_look as cl

    d = img.astype(np.float64) - truth.astype(np.float64)
    out = {}
    for name, m in regions.items():
        mse = float((d[m] ** 2).mean()) if m.any() else 0.0
        out[f"psnr_{name}"] = 10 * np.log10(255.0 ** 2 / max(mse, 1e-10))
    _, smap = structural_similarity(truth, img, channel_axis=-1, data_range=255, full=True)
    out["ssim"] = float(smap.mean(axis=-1)[regions["region"]].mean())
    out["noise"] = cl.noise_sigma(img, regions["interior"])
    return out


def _naive_tone(pbr: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """PBR pass re-expressed so that the compositor's sRGB encode yields a gamma-2.2 encode of it."""
    from pipeline.composite import unpremultiply
    from pipeline.trace.lights import srgb_to_linear

    col = unpremultiply(pbr, cov, np.zeros_like(pbr))
    return srgb_to_linear(np.clip(col, 0, 1) ** (1 / 2.2)) * cov[..., None]


def run(views: int, quick: bool) -> BenchResult:
    from scipy.ndimage import binary_dilation

    from pipeline.composite import composite_full, composite_published
    from pipeline.config import TraceConfig
    from pipeline.seeding import item_rng
    from pipeline.trace.pbr import RenderSettings, render, trace_mask
    from pipeline.trace.scene import build_scene
    from pipeline.trace.shadow import shadow_ratio

    rv, rf, rc = _room()
    objs = _objects()
    scene = build_scene(rv, rf, rc, objs)
    room_scene = build_scene(rv, rf, rc, [])
    ref_spp, ref_shadow = (64, 64) if quick else (REF_SPP, REF_SHADOW)
    spps = (16,) if quick else (4, 16, 64)

    variants = {  # name -> (uses shadow pass, function(photo, passes, rng) -> image)
        "published": (False, lambda ph, p, r: composite_published(ph, p["pbr"], p["ao"], p["labels"] > 0,
                                                                  coverage=p["cov"])),
        "hard mask, no AO": (False, lambda ph, p, r: composite_full(ph, p["pbr"], p["cov"], p["sr"], p["labels"],
                                                                    rng=r, soft_edges=False, shadows=False,
                                                                    blur_sigma=0.0, noise_sigma=0.0).image),
        "+ soft edges": (False, lambda ph, p, r: composite_full(ph, p["pbr"], p["cov"], p["sr"], p["labels"], rng=r,
                                                                shadows=False, blur_sigma=0.0, noise_sigma=0.0).image),
        "+ shadows": (True, lambda ph, p, r: composite_full(ph, p["pbr"], p["cov"], p["sr"], p["labels"], rng=r,
                                                            blur_sigma=0.0, noise_sigma=0.0).image),
        "+ blur (measured)": (True, lambda ph, p, r: composite_full(ph, p["pbr"], p["cov"], p["sr"], p["labels"],
                                                                    rng=r, noise_sigma=0.0).image),
        "full (+ noise)": (True, lambda ph, p, r: composite_full(ph, p["pbr"], p["cov"], p["sr"], p["labels"],
                                                                 rng=r).image),
        "full - soft edges": (True, lambda ph, p, r: composite_full(ph, p["pbr"], p["cov"], p["sr"], p["labels"],
                                                                    rng=r, soft_edges=False).image),
        "full - shadows": (False, lambda ph, p, r: composite_full(ph, p["pbr"], p["cov"], p["sr"], p["labels"],
                                                                  rng=r, shadows=False).image),
        "full - blur": (True, lambda ph, p, r: composite_full(ph, p["pbr"], p["cov"], p["sr"], p["labels"], rng=r,
                                                              blur_sigma=0.0).image),
        "full, oracle shadow pass": (True, lambda ph, p, r: composite_full(ph, p["pbr"], p["cov"], p["sr_ref"],
                                                                           p["labels"], rng=r).image),
        "full, naive tone": (True, lambda ph, p, r: composite_full(ph, _naive_tone(p["pbr"], p["cov"]), p["cov"],
                                                                   p["sr"], p["labels"], rng=r).image),
    }
    rows: dict[tuple[str, int], list[dict]] = {}
    sheet = []
    for vi, cam in enumerate(_cameras(views)):
        rng = item_rng(0, "bench-composite", f"view{vi}")
        labels = _labels(scene, cam)
        room_lin = _room_radiance(room_scene, cam)
        t0 = time.perf_counter()
        ref = render(scene, cam, trace_mask(labels, 3),
                     RenderSettings(spp=ref_spp, spp_min=ref_spp, spp_batch=16, noise_target=0.0, max_depth=3,
                                    ao_samples=0), rng)
        sr_ref = _reference_shadow_ratio(scene, room_scene, cam, labels, rng, samples=ref_shadow)
        log.info("view %d: reference in %.1f s", vi, time.perf_counter() - t0)
        truth_lin = ref.pbr + (1.0 - ref.coverage)[..., None] * room_lin * sr_ref[..., None]
        noise = (CAM_NOISE * rng.standard_normal((H, W, 3))).astype(np.float32)
        photo = _camera(room_lin, noise)
        truth = _camera(truth_lin, noise)
        obj = (ref.coverage > 0) | (labels > 0)
        edge = binary_dilation((ref.coverage > 0) & (ref.coverage < 1), np.ones((3, 3), bool))
        region = binary_dilation(obj, np.ones((3, 3), bool), iterations=BAND) | (sr_ref < 0.98)
        regions = {"region": region, "edges": region & edge, "shadow": region & ~obj & ~edge,
                   "interior": (ref.coverage >= 1) & ~edge}
        for spp in spps:
            prng = item_rng(0, "bench-composite", f"view{vi}", f"spp{spp}")
            shadow = max(4, TraceConfig().shadow_samples * spp // 16)   # the stage's default at 16 spp
            pbr, ao, cov, sr, t_render, t_shadow = _passes(scene, cam, labels, prng, spp, shadow)
            p = {"pbr": pbr, "ao": ao, "cov": cov, "sr": sr, "labels": labels, "sr_ref": sr_ref}
            if spp == 16:   # what the camera-look estimators found, against the camera model's true values
                est = composite_full(photo, pbr, cov, sr, labels, rng=np.random.default_rng(0))
                rows.setdefault(("estimates", 0), []).append(
                    {"blur_sigma": est.blur_sigma, "photo_noise": est.photo_noise, "noise_added": est.noise_added})
            for name, (uses_sr, fn) in variants.items():
                if spp != 16 and name not in ("published", "full (+ noise)", "full - soft edges"):
                    continue
                best = np.inf
                for _ in range(2):
                    t = time.perf_counter()
                    img = fn(photo, p, item_rng(0, "bench-composite", f"view{vi}", "noise"))
                    best = min(best, time.perf_counter() - t)
                m = _metrics(img, truth, regions)
                m.update(seconds_blend=best, seconds=t_render + (t_shadow if uses_sr else 0.0) + best,
                         seconds_trace=t_render + (t_shadow if uses_sr else 0.0))
                rows.setdefault((name, spp), []).append(m)
                if spp == 16 and name in ("published", "full (+ noise)"):
                    sheet.append((vi, name, img))
        sheet.append((vi, "truth", truth))
        sheet.append((vi, "photo", photo))
        truth_noise = _metrics(truth, truth, regions)["noise"]
        rows.setdefault(("truth", 0), []).append({"noise": truth_noise})

    res = BenchResult("composite", speed_label="seconds per frame (trace passes + blend, 160x120)",
                      accuracy_label="PSNR over objects + 8 px band + shadows (dB)")
    mean = {k: {m: float(np.mean([r[m] for r in v])) for m in v[0]} for k, v in rows.items()}
    truth_noise = mean[("truth", 0)]["noise"]
    cumulative = ("published", "hard mask, no AO", "+ soft edges", "+ shadows", "+ blur (measured)", "full (+ noise)")
    minus_one = ("full (+ noise)", "full - soft edges", "full - shadows", "full - blur", "full, naive tone",
                 "full, oracle shadow pass")

    def point(series: str, name: str, spp: int, label: str, baseline: bool = False) -> None:
        m = mean[(name, spp)]
        extra = {k: round(v, 4) for k, v in m.items()}
        extra.update(noise_error=round(abs(m["noise"] - truth_noise), 3), spp=spp, variant=name)
        res.add_point(series, speed=m["seconds"], accuracy=m["psnr_region"], label=label, baseline=baseline,
                      **extra)

    for name in cumulative:
        point("parts added one by one (16 spp)", name, 16, name, baseline=(name == "published"))
    for name in minus_one[1:]:
        point("full minus one part (16 spp)", name, 16, name)
    if len(spps) > 1:
        for name in ("published", "full (+ noise)", "full - soft edges"):
            for spp in spps:
                point(f"{name} vs trace spp", name, spp, f"{spp} spp")
    _ablation_png({name: mean[(name, 16)] for name in dict.fromkeys(cumulative + minus_one)}, truth_noise)
    pub, full = mean[("published", 16)], mean[("full (+ noise)", 16)]
    res.figures.update({
        "psnr_published_db": round(pub["psnr_region"], 2), "psnr_full_db": round(full["psnr_region"], 2),
        "ssim_published": round(pub["ssim"], 4), "ssim_full": round(full["ssim"], 4),
        "psnr_gain_db": round(full["psnr_region"] - pub["psnr_region"], 2),
        "seconds_published": round(pub["seconds"], 3), "seconds_full": round(full["seconds"], 3),
        "seconds_blend_published": round(pub["seconds_blend"], 4),
        "seconds_blend_full": round(full["seconds_blend"], 4),
        "speed_ratio_full_over_published": round(full["seconds"] / pub["seconds"], 2),
        "noise_truth": round(truth_noise, 2), "noise_published": round(pub["noise"], 2),
        "noise_full": round(full["noise"], 2),
        "estimated_blur_sigma_px": round(mean[("estimates", 0)]["blur_sigma"], 3),
        "estimated_photo_noise_gray": round(mean[("estimates", 0)]["photo_noise"], 3),
        "noise_added_gray": round(mean[("estimates", 0)]["noise_added"], 3),
        "views": views, "reference_spp": ref_spp, "reference_shadow_rays": ref_shadow,
        "camera_blur_px": CAM_BLUR, "camera_noise_gray": CAM_NOISE,
        "table": {name: {k: round(v, 3) for k, v in m.items()} for (name, spp), m in mean.items() if spp == 16},
        "table_by_spp": {f"{name} @ {spp} spp": {k: round(v, 3) for k, v in m.items()}
                         for (name, spp), m in mean.items() if spp > 0},
    })
    res.notes += [
        "Truth and composites use the same tracer and lights (room = emitter of its captured colours); the "
        "benchmark measures the compositing, not the physical accuracy of that lighting model.",
        "Truth objects: 256 spp; truth shadows: a brute-force 256-ray shadow ratio in this file (same rays with "
        "and without objects, every room pixel within 40 px of the objects), independent of pipeline/trace/shadow.py; "
        "composites: trace-stage passes at the given spp with the stage's shadow settings (trace.shadow_samples "
        "at 16 spp, scaled with spp; shadow_stride, shadow_smooth, shadow_min_effect as configured by default).",
        "Photo and truth share one sensor-noise field; the composite's added noise is independent, so PSNR "
        "penalises matched noise: judge noise by the 'noise' vs truth figures.",
        "Camera model: Gaussian blur sigma 1 px in linear light, sRGB encode, 2.5 gray levels per-channel noise.",
        "'full, oracle shadow pass' uses the reference shadow ratio in place of the trace stage's pass: the "
        "compositor's ceiling when the shadow pass is accurate (its time is that of the stage's pass).",
        "seconds = trace passes the blend needs (published: PBR+AO render only; shadows: + shadow pass) + blend.",
    ]
    _sheet_png(sheet, views)
    return res


def _ablation_png(table: dict[str, dict], truth_noise: float) -> None:
    """bench/results/composite_ablation.png: PSNR by region and SSIM of every variant (16 spp)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(table)
    keys = [("psnr_region", "objects + band + shadows"), ("psnr_edges", "edge pixels"),
            ("psnr_shadow", "shadow / band pixels"), ("psnr_interior", "object interiors")]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.8), dpi=100, gridspec_kw={"width_ratios": [3, 1, 1]})
    y = np.arange(len(names))
    hgt = 0.2
    for i, (k, lab) in enumerate(keys):
        axes[0].barh(y + (i - 1.5) * hgt, [table[n][k] for n in names], height=hgt, label=lab)
    axes[0].set_yticks(y, names)
    axes[0].invert_yaxis()
    axes[0].set_xlabel("PSNR against the path-traced truth (dB)")
    axes[0].set_xlim(15, None)
    axes[0].legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2)
    axes[0].grid(axis="x", alpha=0.3)
    axes[1].barh(y, [table[n]["ssim"] for n in names], color="gray")
    axes[1].set_yticks(y, [])
    axes[1].invert_yaxis()
    axes[1].set_xlim(0.7, 1.0)
    axes[1].set_xlabel("SSIM (objects + band)")
    axes[2].barh(y, [table[n]["noise"] for n in names], color="tab:purple")
    axes[2].axvline(truth_noise, color="k", ls="--", label=f"truth {truth_noise:.2f}")
    axes[2].set_yticks(y, [])
    axes[2].invert_yaxis()
    axes[2].set_xlabel("noise on objects (gray levels)")
    axes[2].legend(fontsize=8)
    fig.suptitle("composite: what each part buys (trace passes at 16 spp; mean over views)")
    fig.tight_layout()
    fig.savefig(RESULTS / "composite_ablation.png")
    plt.close(fig)


def _sheet_png(sheet, views: int) -> None:
    import cv2

    from pipeline.io import atomic_write_image

    order = ["photo", "truth", "published", "full (+ noise)"]
    rows = []
    for vi in range(views):
        tiles = []
        for name in order:
            img = next(im for v, n, im in sheet if v == vi and n == name)
            big = cv2.resize(img, (W * 2, H * 2), interpolation=cv2.INTER_NEAREST).copy()
            cv2.putText(big, name, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1, cv2.LINE_AA)
            tiles.append(big)
        rows.append(np.concatenate(tiles, axis=1))
    atomic_write_image(RESULTS / "composite_views.png", np.concatenate(rows, axis=0))


# ---------------------------------------------------------------------------------------------------
# Real-scan contact sheet (7-Scenes redkitchen from ../shared/data)
# ---------------------------------------------------------------------------------------------------

SHEET_CACHE = RESULTS.parents[1] / "runs" / "bench-composite"   # git-ignored
SHEET_OBJECTS = (1, 5, 8, 9)   # LM-O ape, can, driller, duck


def _place_on_surface(scene_room, cam, up: np.ndarray, model, rng) -> tuple[np.ndarray, np.ndarray] | None:
    """A pose putting ``model`` upright on a horizontal surface seen near the lower middle of the view."""
    from pipeline.trace.pbr import primary_rays

    w, h = cam.width, cam.height
    xs = np.linspace(0.3 * w, 0.7 * w, 9)
    ys = np.linspace(0.45 * h, 0.85 * h, 7)
    px = np.array([[x, y] for y in ys for x in xs])
    pix = np.floor(px[:, 1]).astype(int) * w + np.floor(px[:, 0]).astype(int)
    o, d = primary_rays(cam, pix, np.full((len(pix), 2), 0.5))
    hits = scene_room.intersector.intersect(o, d)
    ok = np.flatnonzero(hits.hit & (hits.t > 0.5) & (hits.t < 2.5))
    if ok.size == 0:
        return None
    V, F = scene_room.vertices.astype(np.float64), scene_room.faces[hits.prim[ok]]
    ng = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    ng /= np.maximum(np.linalg.norm(ng, axis=1, keepdims=True), 1e-20)
    p_hit = o[ok] + hits.t[ok, None] * d[ok]
    flat = np.flatnonzero(np.abs(ng @ up) > 0.93)
    if flat.size == 0:
        return None
    k = flat[rng.integers(flat.size)]
    yaw = rng.uniform(0, 2 * np.pi)
    # model frame -> world: model z (BOP models stand on -z ... +z) to up, then yaw about up
    z = up / np.linalg.norm(up)
    a = np.cross(z, [1.0, 0, 0]) if abs(z[0]) < 0.9 else np.cross(z, [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(z, a)
    R0 = np.stack([a, b, z], axis=1)
    c, s = np.cos(yaw), np.sin(yaw)
    R = R0 @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    v = np.asarray(model.vertices) @ R.T
    t = p_hit[k].astype(np.float64) - z * float((v @ z).min()) + 0.002 * z
    return R, t


def real_sheet(frames: int = 4, scale: float = 0.5) -> None:
    """Published vs full composites of LM-O objects on 7-Scenes redkitchen frames.

    Written to ``runs/bench-composite/composite_sheet.png`` (git-ignored: the 7-Scenes terms forbid
    redistributing the frames with the project). Columns: photo, published, full, then zoomed crops of
    published and full around the objects.
    """
    import cv2

    from bench.common import SHARED_DATA
    from pipeline.composite import composite_full, composite_published
    from pipeline.config import build_config
    from pipeline.ingest import ingest_scan, load_scan, read_color
    from pipeline.io import atomic_write_image
    from pipeline.objects import load_library
    from pipeline.scanformats.mesh import read_room_ply
    from pipeline.seeding import item_rng
    from pipeline.trace.pbr import Camera, render, trace_mask
    from pipeline.trace.scene import build_scene, instance_from_model
    from pipeline.trace.shadow import shadow_ratio
    from pipeline.trace.stage import settings_from_config

    scan_dir = SHARED_DATA / "scans" / "7scenes-redkitchen"
    if not scan_dir.is_dir():
        log.warning("no real data at %s: contact sheet skipped", scan_dir)
        return
    cfg = build_config({"scan": {"paths": [str(scan_dir)], "format": "7scenes"}})
    run = SHEET_CACHE
    if not (run / "ingest" / "redkitchen" / "scan.json").is_file():
        t0 = time.perf_counter()
        ingest_scan(scan_dir, "redkitchen", run / "ingest" / "redkitchen", cfg)
        log.info("ingested redkitchen in %.0f s", time.perf_counter() - t0)
    scan = load_scan(run, "redkitchen")
    lib = {m.obj_id: m for m in load_library((str(SHARED_DATA / "objects" / "lmo" / "models"),))}
    rv, rf, rc = read_room_ply(scan.mesh_path)
    room_scene = build_scene(rv, rf, rc, [], up=scan.up_w)
    tcfg = cfg.trace
    rows = []
    picks = np.linspace(0, scan.num_frames - 1, frames + 2).round().astype(int)[1:-1]
    for fi in picks:
        rng = item_rng(0, "bench-composite-sheet", str(fi))
        w, h = round(scan.width * scale), round(scan.height * scale)
        K = scan.K[fi].copy()
        K[:2] *= scale
        K[0, 2] = (scan.K[fi][0, 2] + 0.5) * scale - 0.5
        K[1, 2] = (scan.K[fi][1, 2] + 0.5) * scale - 0.5
        cam = Camera(K=K, T_c2w=scan.T_c2w[fi], width=w, height=h)
        insts = []
        for oid in SHEET_OBJECTS[:2 + fi % 2]:
            pose = _place_on_surface(room_scene, cam, scan.up_w, lib[oid], rng)
            if pose is not None:
                insts.append(instance_from_model(lib[oid], *pose))
        if not insts:
            log.warning("frame %d: no horizontal surface in view, skipped", fi)
            continue
        scene = build_scene(rv, rf, rc, insts, up=scan.up_w, lighting=tcfg.lighting,
                            radiance_scale=tcfg.radiance_scale, light_threshold=tcfg.light_threshold,
                            light_gain=tcfg.light_gain)
        from pipeline.trace.pbr import primary_rays

        o, d = primary_rays(cam, np.arange(w * h), np.full((w * h, 2), 0.5))
        hh = scene.intersector.intersect(o, d)
        labels = np.where(hh.hit, scene.tri_inst[np.maximum(hh.prim, 0)], 0).astype(np.uint16).reshape(h, w)
        t0 = time.perf_counter()
        fb = render(scene, cam, trace_mask(labels, tcfg.edge_band), settings_from_config(tcfg), rng)
        pbr, ao = fb.pbr, fb.ao
        if tcfg.denoise != "off":
            from pipeline.trace.denoise import denoise, denoise_ao

            pbr = denoise(fb.pbr, fb.albedo, fb.normal, fb.coverage > 0, method=tcfg.denoise)
            ao = denoise_ao(fb.ao, fb.normal, fb.coverage > 0, method=tcfg.denoise)
        sr = shadow_ratio(scene, cam, labels, rng, samples=tcfg.shadow_samples, min_effect=tcfg.shadow_min_effect,
                          stride=tcfg.shadow_stride, smooth=tcfg.shadow_smooth)
        log.info("frame %d: %d objects, traced in %.1f s", fi, len(insts), time.perf_counter() - t0)
        photo = cv2.resize(read_color(scan, fi), (w, h), interpolation=cv2.INTER_AREA)
        pub = composite_published(photo, pbr, ao, labels > 0, coverage=fb.coverage)
        full = composite_full(photo, pbr, fb.coverage, sr, labels, rng=rng, edge_band=tcfg.edge_band)
        ys, xs = np.nonzero(labels > 0)
        cy, cx = int(ys.mean()), int(xs.mean())
        half = 48
        y0, x0 = int(np.clip(cy - half, 0, h - 2 * half)), int(np.clip(cx - half, 0, w - 2 * half))
        tiles = []
        for name, img in (("photo", photo), ("published", pub),
                          (f"full (blur {full.blur_sigma:.2f} px, noise {full.photo_noise:.1f})", full.image)):
            big = img.copy()
            cv2.putText(big, name, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 0), 1, cv2.LINE_AA)
            tiles.append(big)
        for img in (pub, full.image):
            crop = img[y0:y0 + 2 * half, x0:x0 + 2 * half]
            tiles.append(cv2.resize(crop, (h, h), interpolation=cv2.INTER_NEAREST))
        rows.append(np.concatenate(tiles, axis=1))
    if rows:
        # 7-Scenes frames may not be redistributed with the project: the sheet stays in the git-ignored runs/
        atomic_write_image(SHEET_CACHE / "composite_sheet.png", np.concatenate(rows, axis=0))
        log.info("wrote %s", SHEET_CACHE / "composite_sheet.png")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=3, help="camera views (1..4)")
    ap.add_argument("--quick", action="store_true", help="low reference quality, one spp setting (smoke run)")
    ap.add_argument("--sheet", action="store_true",
                    help="only the 7-Scenes contact sheet (runs/bench-composite/composite_sheet.png, not committed)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.sheet:
        real_sheet()
        return
    res = run(max(1, min(args.views, 4)), args.quick)
    j, p = res.write()
    print(f"wrote {j} and {p}")
    for k, v in res.figures.items():
        if not k.startswith("table"):
            print(f"{k}: {v}")
    for name, m in res.figures["table"].items():
        print(f"{name:22s} PSNR {m['psnr_region']:6.2f} edges {m['psnr_edges']:6.2f} shadow {m['psnr_shadow']:6.2f} "
              f"interior {m['psnr_interior']:6.2f} SSIM {m['ssim']:.4f} noise {m['noise']:.2f} "
              f"s {m['seconds']:.3f} (blend {m['seconds_blend'] * 1000:.1f} ms)")


if __name__ == "__main__":
    main()
