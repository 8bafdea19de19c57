"""Compositor benchmark: each blend against a path-traced true image, PSNR/SSIM vs seconds per frame.

Run: ``nice .venv/bin/python -m bench.composite [--views N] [--quick]``. Writes
bench/results/composite.json + .png, composite_ablation.png (PSNR by region, SSIM and noise level of
every variant) and composite_views.png (photo, truth, published, full, per view). ``--sheet`` writes the
7-Scenes contact sheet to runs/bench-composite/composite_sheet.png (not committed: 7-Scenes terms).

Ground truth (issue 10): the path-traced photo mode of the scan generator.

- **Scan**: ``make_scan`` (7scenes layout, 160x120, seed ``SCAN_SEED``) into a temporary folder, ingested
  by :func:`pipeline.ingest.ingest_scan` as the ingest stage does: the pipeline sees its poses,
  intrinsics and scanner mesh (room.ply with the scanner's vertex colours), exactly as for a real scan.
  Views: the first ``--views`` sharp, pose-valid frames with a horizontal surface in view.
- **Objects**: LM-O models (shared data) stood upright on a horizontal surface of the scanner mesh seen
  in the lower middle of each view (2-3 objects per view, 2 mm above the hit point, random yaw; no
  physics).
- **Photo**: :func:`pipeline.synthscan.render.render_traced_view` of the TRUE room (the generator's own
  room, textures, area lights, global illumination) without the objects at ``SPP_TRUTH`` spp, through
  a camera model (:func:`pipeline.synthscan.degrade.camera_photo`: Gaussian PSF of ``CAMERA_BLUR`` px in
  linear light, sRGB, read + shot noise), as ``make_scan(photo_mode="traced", camera=...)`` does.
  This is the traced photo mode's frame (``make_scan(photo_mode="traced")``) at the same view.
- **True image**: the same call with the objects inserted (same renderer, same lights, same seed and
  spp: correlated samples, so the difference is the objects' effect, not noise), through the same
  camera (same automatic exposure, same PSF, same noise draws: one exposure of one sensor). The
  camera makes the compositor's camera matching measurable: the full mode must find the exposure
  (trace stage, against the room mesh colours) and the blur in the photo; it is never told
  ``CAMERA_BLUR`` or the view's exposure.
- **Composites**: what the stages compute on the ingested scan: labels of the visible objects (primary
  rays against the scanner mesh + objects, what raster's labels are), the trace stage's passes
  (``build_scene`` with the stage's lighting settings on room.ply, including its photo-based lighting
  from the scan's own photos (:func:`pipeline.trace.photolights.scan_lighting`), :func:`pipeline.trace.pbr.render`, the
  stage's denoiser, :func:`pipeline.trace.shadow.shadow_ratio` with the stage's settings) at 16 spp (the
  default; also 4 and 64 for the speed axis), blended onto the photo by
  :func:`pipeline.composite.composite_published` / :func:`composite_full` with the composite stage's
  gain, each part switched on/off (ablation), plus a "naive tone" variant (rendered radiance encoded
  with gamma 2.2) and an "oracle shadow pass" variant (the true shadow ratio, truth/photo luminance
  outside the objects, in place of the trace stage's pass: what the blend makes of a perfect pass).
  Chain: published -> + soft edges -> + shadows -> + blur -> + noise (= full); leave-one-out rows
  drop one part of full (camera matching = blur and noise). Lighting rows: the trace stage without
  its photo-based lighting (mesh colours only) and with other room-albedo priors.
- **Metrics** over the objects, a band of ``BAND`` px around them and every pixel the objects darken by
  more than 2 % in the truth: PSNR (dB, 8-bit) and SSIM (skimage, 7x7, mean of the SSIM map over the
  region); PSNR separately over edge pixels (0 < true coverage < 1), band/shadow pixels and object
  interiors; noise level on object interiors. Speed: seconds per frame of the trace passes each blend
  needs plus the blend. The truth's own floor: PSNR between two truth renders with different path seeds
  (view 0).

What it does not show: real scan errors beyond the generator's (its scanner mesh has noise and holes;
poses are exact), motion blur (the camera model here is a Gaussian PSF; the scan's motion-blurred and
defocused frames are excluded), JPEG. The scan's own photos (used by the photo-based lighting) are the
generator's raster-mode photos of the same room, not the traced ones. PSNR/SSIM cannot reward matched
noise (an independent noise field of the right level doubles the noise error): judge noise matching by
the noise column against the truth's.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import RESULTS, BenchResult

log = logging.getLogger("bench.composite")

W, H = 160, 120
SCAN_SEED = 3
SPP_TRUTH = 64      # samples per pixel of the traced photo and truth (same seed: correlated)
BAND = 8            # pixels around the objects in the metric region
OBJECTS = (1, 5, 8, 9)   # LM-O ape, can, driller, duck
CAMERA_BLUR = 1.0   # px: the benchmark camera's Gaussian PSF (CameraModel), on photo and truth alike
CAMERA_EXPOSURE_LOG = 0.35   # per-view automatic exposure: exp(U(-this, this)) (CameraModel.exposure)


def _make_views(tmp: Path, views: int):
    """Generate + ingest the scan; pick views and place objects. Returns (scan, traced_room, cfg, view list).

    Each view: dict(frame, K, T_c2w, insts, cam).
    """
    from bench.common import SHARED_DATA
    from pipeline.config import build_config
    from pipeline.ingest import ingest_scan
    from pipeline.runfolder import load_scan
    from pipeline.objects import load_library
    from pipeline.scanformats.mesh import read_room_ply
    from pipeline.seeding import item_rng
    from pipeline.synthscan.generate import make_scan
    from pipeline.synthscan.render import traced_room_from_scan
    from pipeline.camera import Camera
    from pipeline.trace.scene import build_scene, instance_from_model

    models = SHARED_DATA / "objects" / "lmo" / "models"
    if not models.is_dir():
        raise SystemExit(f"bench.composite needs the LM-O models at {models} (see shared/data/README.md)")
    scan_dir = tmp / "scan"
    t0 = time.perf_counter()
    make_scan(scan_dir, layout="7scenes", seed=SCAN_SEED, width=W, height=H, frames=12)
    cfg = build_config({"scan": {"paths": [str(scan_dir)], "format": "7scenes"}})
    run = tmp / "run"
    ingest_scan(scan_dir, "synth", run / "ingest" / "synth", cfg)
    log.info("scan generated and ingested in %.1f s", time.perf_counter() - t0)
    scan = load_scan(run, "synth")
    tr = traced_room_from_scan(scan_dir)
    info = json.loads((scan_dir / "ground_truth" / "scan.json").read_text())["frames_info"]
    lib = {m.obj_id: m for m in load_library((str(models),))}
    rv, rf, rc = read_room_ply(scan.mesh_path)
    room_scene = build_scene(rv, rf, rc, [], up=scan.up_w)
    out = []
    for fi, fr in enumerate(info):
        if len(out) == views:
            break
        if fr["blur"]["kind"] != "none" or not fr["pose_valid"]:
            continue
        cam = Camera(K=scan.K[fi], T_c2w=scan.T_c2w[fi], width=scan.width, height=scan.height)
        rng = item_rng(0, "bench-composite", "place", str(fi))
        insts = []
        for oid in OBJECTS[:2 + fi % 2]:
            pose = _place_on_surface(room_scene, cam, scan.up_w, lib[oid], rng)
            if pose is not None:
                insts.append(instance_from_model(lib[oid], *pose))
        if insts:
            out.append({"frame": fi, "cam": cam, "insts": insts})
        else:
            log.info("frame %d: no horizontal surface in view, skipped", fi)
    return scan, tr, cfg, (rv, rf, rc), out


def _trace_passes(scene, split, cam, labels, rng, tcfg, spp: int):
    """The trace stage's passes at ``spp``: (pbr, ao, coverage, sr, s_render, s_shadow).

    The stage's own functions (:func:`pipeline.trace.stage.object_passes`, :func:`~pipeline.trace.stage.shadow_pass`)
    with ``tcfg`` at ``spp`` and its shadow samples scaled with ``spp`` (the stage's default is for 16 spp).
    AO is traced (the stage traces it for the published blend only; here that blend is measured beside the
    full one); no object shadows (the stage takes them for fit lighting; this benchmark traces scan lighting).
    """
    from pipeline.trace.stage import object_passes, shadow_pass

    shadow = max(4, tcfg.shadow_samples * spp // 16)
    cfg = dataclasses.replace(tcfg, spp=spp, spp_min=min(tcfg.spp_min, spp), shadow_samples=shadow)
    t0 = time.perf_counter()
    _, fb, pbr, ao = object_passes(scene, cam, labels, cfg, rng, ao=True)
    t1 = time.perf_counter()
    sr = shadow_pass(scene, cam, labels, cfg, rng, room_isect=split[0], obj_isect=split[1])
    t2 = time.perf_counter()
    return pbr, ao, fb.coverage, sr, t1 - t0, t2 - t1


def _lum(x: np.ndarray) -> np.ndarray:
    return x @ np.array([0.2126, 0.7152, 0.0722], np.float32)


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
    # brightness of the objects: mean linear luminance over object interiors, this image / the truth
    from pipeline.color import srgb_to_linear

    lin = lambda x: _lum(srgb_to_linear(x[regions["interior"]].astype(np.float32) / 255.0))  # noqa: E731
    out["interior_gain"] = (float(lin(img).mean() / max(lin(truth).mean(), 1e-6))
                            if regions["interior"].any() else 1.0)
    return out


def _naive_tone(pbr: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """PBR pass re-expressed so that the compositor's sRGB encode yields a gamma-2.2 encode of it."""
    from pipeline.composite import unpremultiply
    from pipeline.color import srgb_to_linear

    col = unpremultiply(pbr, cov, np.zeros_like(pbr))
    return srgb_to_linear(np.clip(col, 0, 1) ** (1 / 2.2)) * cov[..., None]


def run(views: int, quick: bool) -> BenchResult:
    from scipy.ndimage import binary_dilation, gaussian_filter

    from pipeline.composite import composite_full, composite_published
    from pipeline.seeding import item_rng
    from pipeline.synthscan.render import render_traced_view
    from pipeline.trace.scene import build_scene
    from pipeline.trace.shadow import split_intersectors

    spp_truth = 16 if quick else SPP_TRUTH
    spps = (16,) if quick else (4, 16, 64)
    tmp_obj = tempfile.TemporaryDirectory(prefix="bench-composite-")
    tmp = Path(tmp_obj.name)
    import dataclasses
    import resource

    from pipeline.synthscan.degrade import CameraModel, camera_photo
    from pipeline.trace.photolights import frame_exposure, scan_lighting

    scan, tr, cfg, (rv, rf, rc), vlist = _make_views(tmp, views)
    # this secondary benchmark measures the blends on the scan lighting it was built for (the light fit is
    # judged against Mitsuba by bench/lighting.py)
    tcfg = dataclasses.replace(cfg.trace, lighting="scan")
    gain, eb = cfg.composite.exposure / cfg.trace.radiance_scale, cfg.trace.edge_band
    env = None if tcfg.env_radiance < 0 else np.full(3, tcfg.env_radiance, np.float32)
    camera = CameraModel(blur_sigma=CAMERA_BLUR)
    # the trace stage's photo-based lighting (once per scan), timed; and the variants' albedo priors
    c0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    lighting = {"default": scan_lighting(scan, rv, rf, rc, tcfg, 0)}
    c1 = resource.getrusage(resource.RUSAGE_SELF)
    photo_light_secs = (time.perf_counter() - t0, c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime)
    for rho in (0.3, 0.7):
        lighting[f"albedo {rho}"] = scan_lighting(scan, rv, rf, rc, dataclasses.replace(tcfg, room_albedo=rho), 0)
    lighting["mesh colours only"] = (None, None)

    def make_scene(insts, which="default"):
        lv, em = lighting[which]
        return build_scene(rv, rf, rc, insts, lighting=tcfg.lighting, radiance_scale=tcfg.radiance_scale,
                           light_threshold=tcfg.light_threshold, light_gain=tcfg.light_gain, env_radiance=env,
                           published_power=tcfg.published_power, up=scan.up_w, light_vertices=lv, env_map=em)

    def full(ph, p, r, sr=None, pbr=None, exp=True, **kw):
        # exp: the trace stage's measured exposure of this photo (composite.match_exposure)
        return composite_full(ph, p["pbr"] if pbr is None else pbr, p["cov"], p["sr"] if sr is None else sr,
                              p["labels"], rng=r, gain=gain * (p["exposure"] if exp else 1.0), edge_band=eb,
                              **kw).image

    pub_fn = (False, lambda ph, p, r: composite_published(ph, p["pbr"], p["ao"], p["labels"] > 0,
                                                          coverage=p["cov"], gain=gain))
    full_fn = (True, lambda ph, p, r: full(ph, p, r))
    variants = {  # name -> (uses shadow pass, function(photo, passes, rng) -> image)
        "published": pub_fn,
        "hard mask, no AO": (False, lambda ph, p, r: full(ph, p, r, soft_edges=False, shadows=False,
                                                          blur_sigma=0.0, noise_sigma=0.0, exp=False)),
        "+ soft edges": (False, lambda ph, p, r: full(ph, p, r, shadows=False, blur_sigma=0.0, noise_sigma=0.0,
                                                      exp=False)),
        "+ shadows": (True, lambda ph, p, r: full(ph, p, r, blur_sigma=0.0, noise_sigma=0.0, exp=False)),
        "+ exposure (measured)": (True, lambda ph, p, r: full(ph, p, r, blur_sigma=0.0, noise_sigma=0.0)),
        "+ blur (measured)": (True, lambda ph, p, r: full(ph, p, r, noise_sigma=0.0)),
        "full (+ noise)": full_fn,
        "full - soft edges": (True, lambda ph, p, r: full(ph, p, r, soft_edges=False)),
        "full - shadows": (False, lambda ph, p, r: full(ph, p, r, shadows=False)),
        "full - camera matching": (True, lambda ph, p, r: full(ph, p, r, blur_sigma=0.0, noise_sigma=0.0,
                                                                exp=False)),
        "full - exposure": (True, lambda ph, p, r: full(ph, p, r, exp=False)),
        "full - blur": (True, lambda ph, p, r: full(ph, p, r, blur_sigma=0.0)),
        "full, oracle shadow pass": (True, lambda ph, p, r: full(ph, p, r, sr=p["sr_true"])),
        "full, naive tone": (True, lambda ph, p, r: full(ph, p, r, pbr=_naive_tone(p["pbr"], p["cov"]))),
        "published, oracle gain": (False, lambda ph, p, r: composite_published(
            ph, p["pbr"], p["ao"], p["labels"] > 0, coverage=p["cov"], gain=gain * p["gain_oracle"])),
        "full, oracle gain": (True, lambda ph, p, r: full(ph, p, r, pbr=p["pbr"] * p["gain_oracle"], exp=False)),
        "full, oracle gain + shadow pass": (True, lambda ph, p, r: full(ph, p, r, pbr=p["pbr"] * p["gain_oracle"],
                                                                        exp=False,
                                                                        sr=p["sr_true"])),
    }
    rows: dict[tuple[str, int], list[dict]] = {}
    sheet = []
    truth_secs = []
    for vi, v in enumerate(vlist):
        cam, insts, fi = v["cam"], v["insts"], v["frame"]
        K, T = scan.K[fi], scan.T_c2w[fi]
        t0 = time.perf_counter()
        kw = dict(exposure=tr.exposure, spp=spp_truth, seed=tr.seed + fi,
                  T_world_from_canonical=tr.T_world_from_canonical, denoise="none")
        bg = render_traced_view(tr.room, T, K, W, H, **kw)
        tv = render_traced_view(tr.room, T, K, W, H, extra_meshes=insts, **kw)
        truth_secs.append((time.perf_counter() - t0) / 2)
        log.info("view %d (frame %d, %d objects): photo + truth traced in %.1f s", vi, fi, len(insts),
                 time.perf_counter() - t0)
        # the frame's automatic exposure, the same for photo and truth (one exposure of one sensor)
        e_true = float(np.exp(item_rng(0, "bench-composite", "exposure", str(fi)).uniform(-CAMERA_EXPOSURE_LOG,
                                                                                          CAMERA_EXPOSURE_LOG)))
        cam_v = dataclasses.replace(camera, exposure=e_true)
        photo = camera_photo(bg.radiance, cam_v, item_rng(0, "bench-composite", "sensor", str(fi)))
        truth = camera_photo(tv.radiance, cam_v, item_rng(0, "bench-composite", "sensor", str(fi)))
        photo1 = camera_photo(bg.radiance, camera, item_rng(0, "bench-composite", "sensor", str(fi)))
        truth1 = camera_photo(tv.radiance, camera, item_rng(0, "bench-composite", "sensor", str(fi)))
        # the pipeline's side: scanner mesh + objects, the trace stage's scene (photo-based lighting) and its
        # per-frame exposure measure
        scene = make_scene(insts)
        e_est = frame_exposure(scene, cam, photo, radiance_scale=tcfg.radiance_scale, threshold=tcfg.light_threshold)
        e_est1 = frame_exposure(scene, cam, photo1, radiance_scale=tcfg.radiance_scale,
                                threshold=tcfg.light_threshold)
        split = split_intersectors(scene)
        o, d = cam.rays(np.arange(W * H), np.full((W * H, 2), 0.5))
        hh = scene.intersector.intersect(o, d)
        labels = np.where(hh.hit, scene.tri_inst[np.maximum(hh.prim, 0)], 0).astype(np.uint16).reshape(H, W)
        # true shadow ratio: truth / photo luminance where no object is seen (correlated samples)
        cov_t = tv.object_coverage
        lb, lt = _lum(bg.radiance), _lum(tv.radiance)
        sr_true = np.where((cov_t <= 0) & (lb > 1e-6), lt / np.maximum(lb, 1e-6), 1.0).astype(np.float32)
        sr_true = np.clip(sr_true, 0.0, 2.0)
        obj = (cov_t > 0) | (labels > 0)
        near = binary_dilation(obj, np.ones((3, 3), bool), iterations=40)
        dark = near & ~obj & (gaussian_filter(sr_true, 1.5) < 0.98)
        edge = binary_dilation((cov_t > 0) & (cov_t < 1), np.ones((3, 3), bool))
        region = binary_dilation(obj, np.ones((3, 3), bool), iterations=BAND) | dark
        regions = {"region": region, "edges": region & edge, "shadow": region & ~obj & ~edge,
                   "interior": (cov_t >= 1) & ~edge}
        if vi == 0:   # the truth's own noise floor: another truth with other path samples, same sensor draws
            tv2 = render_traced_view(tr.room, T, K, W, H, extra_meshes=insts, **{**kw, "seed": tr.seed + 1000 + fi})
            truth2 = camera_photo(tv2.radiance, cam_v, item_rng(0, "bench-composite", "sensor", str(fi)))
            rows[("truth vs truth (other seed)", 0)] = [_metrics(truth2, truth, regions)]
        for spp in spps:
            prng = item_rng(0, "bench-composite", f"view{vi}", f"spp{spp}")
            pbr, ao, cov, sr, t_render, t_shadow = _trace_passes(scene, split, cam, labels, prng, tcfg, spp)
            # oracle brightness: true / traced mean linear luminance over pixels fully covered in both
            both = (cov_t >= 1) & (cov >= 0.999)
            g_or = (float(_lum(tv.radiance[both]).mean() / max(_lum(pbr[both] / cov[both, None]).mean(), 1e-6))
                    if both.any() else 1.0)
            rows.setdefault(("oracle gain", spp), []).append({"gain": g_or})
            p = {"pbr": pbr, "ao": ao, "cov": cov, "sr": sr, "labels": labels, "sr_true": sr_true,
                 "gain_oracle": g_or * e_true, "exposure": e_est / e_est1}
            if spp == 16:   # what the camera-look estimators found
                est = composite_full(photo, pbr, cov, sr, labels, rng=np.random.default_rng(0), gain=gain * e_est / e_est1,
                                     edge_band=eb)
                rows.setdefault(("estimates", 0), []).append(
                    {"blur_sigma": est.blur_sigma, "photo_noise": est.photo_noise, "noise_added": est.noise_added,
                     "exposure_true": e_true, "exposure_est": e_est, "exposure_est_at_1": e_est1})
                # the same view through the camera at exposure 1 (no auto-exposure): published and full
                p1 = {**p, "exposure": 1.0}
                for name, (uses_sr, fn) in (("published, camera exposure 1", pub_fn),
                                            ("full, camera exposure 1", full_fn)):
                    img = fn(photo1, p1, item_rng(0, "bench-composite", f"view{vi}", "noise"))
                    m = _metrics(img, truth1, regions)
                    m.update(seconds_blend=0.0, seconds=t_render + (t_shadow if uses_sr else 0.0),
                             seconds_trace=t_render + (t_shadow if uses_sr else 0.0))
                    rows.setdefault((name, 16), []).append(m)
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
        # the trace stage's lighting without the photos (mesh colours + constant env: the earlier default) and
        # with other room-albedo priors
        for which in ("mesh colours only", "albedo 0.3", "albedo 0.7"):
            scene_l = make_scene(insts, which)
            prng = item_rng(0, "bench-composite", f"view{vi}", "spp16")
            pbr, ao, cov, sr, t_render, t_shadow = _trace_passes(scene_l, split_intersectors(scene_l), cam, labels,
                                                                 prng, tcfg, 16)
            p = {"pbr": pbr, "ao": ao, "cov": cov, "sr": sr, "labels": labels, "sr_true": sr_true,
                 "exposure": e_est / e_est1}
            for base, (uses_sr, fn) in (("published", pub_fn), ("full", full_fn)):
                img = fn(photo, p, item_rng(0, "bench-composite", f"view{vi}", "noise"))
                m = _metrics(img, truth, regions)
                m.update(seconds_blend=0.0, seconds=t_render + (t_shadow if uses_sr else 0.0),
                         seconds_trace=t_render + (t_shadow if uses_sr else 0.0))
                rows.setdefault((f"{base}, lighting: {which}", 16), []).append(m)
        sheet.append((vi, "truth", truth))
        sheet.append((vi, "photo", photo))
        rows.setdefault(("truth", 0), []).append({"noise": _metrics(truth, truth, regions)["noise"],
                                                  "region_px": float(region.sum()),
                                                  "object_px": float(obj.sum())})
    tmp_obj.cleanup()

    res = BenchResult("composite", speed_label=f"seconds per frame (trace passes + blend, {W}x{H})",
                      accuracy_label="PSNR vs traced truth, objects + band (dB)")
    mean = {k: {m: float(np.mean([r[m] for r in v])) for m in v[0]} for k, v in rows.items()}
    truth_noise = mean[("truth", 0)]["noise"]
    cumulative = ("published", "+ soft edges", "+ shadows", "+ exposure (measured)", "+ blur (measured)",
                  "full (+ noise)")
    minus_one = ("full (+ noise)", "full - soft edges", "full - shadows", "full - camera matching", "full - exposure",
                 "full - blur", "hard mask, no AO", "full, naive tone", "full, oracle shadow pass")
    exposure1 = ("published, camera exposure 1", "full, camera exposure 1")
    light_rows = tuple(f"{b}, lighting: {w}" for w in ("mesh colours only", "albedo 0.3", "albedo 0.7")
                       for b in ("published", "full"))
    oracle = ("published, oracle gain", "full, oracle gain", "full, oracle gain + shadow pass")

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
    for name in light_rows:
        point("trace lighting variants (16 spp)", name, 16, name)
    for name in exposure1:
        point("camera at exposure 1 (no auto exposure)", name, 16, name)
    for name in oracle:
        point("oracle: truth-fitted gain", name, 16, name)
    if len(spps) > 1:
        for name in ("published", "full (+ noise)", "full - soft edges"):
            for spp in spps:
                point(f"{name} vs trace spp", name, spp, f"{spp} spp")
    _ablation_png({name: mean[(name, 16)] for name in dict.fromkeys(cumulative + minus_one + exposure1 + light_rows
                                                                     + oracle)},
                  truth_noise)
    pub, fm = mean[("published", 16)], mean[("full (+ noise)", 16)]
    per_view = {name: [round(float(r["psnr_region"]), 2) for r in rows[(name, 16)]]
                for name in ("published", "full (+ noise)", "+ blur (measured)")}
    floor = mean[("truth vs truth (other seed)", 0)]
    res.figures.update({
        "truth_source": "traced: pipeline.synthscan.render.render_traced_view (true room, objects inserted)",
        "psnr_published_db": round(pub["psnr_region"], 2), "psnr_full_db": round(fm["psnr_region"], 2),
        "ssim_published": round(pub["ssim"], 4), "ssim_full": round(fm["ssim"], 4),
        "psnr_gain_db": round(fm["psnr_region"] - pub["psnr_region"], 2),
        "psnr_per_view_db": per_view,
        "seconds_published": round(pub["seconds"], 3), "seconds_full": round(fm["seconds"], 3),
        "seconds_blend_published": round(pub["seconds_blend"], 4),
        "seconds_blend_full": round(fm["seconds_blend"], 4),
        "speed_ratio_full_over_published": round(fm["seconds"] / pub["seconds"], 2),
        "seconds_truth_render_per_image": round(float(np.mean(truth_secs)), 2),
        "object_brightness_full_over_truth": round(fm["interior_gain"], 3),
        "object_brightness_published_over_truth": round(pub["interior_gain"], 3),
        "oracle_gain_mean": round(mean[("oracle gain", 16)]["gain"], 3),
        "psnr_full_oracle_gain_db": round(mean[("full, oracle gain", 16)]["psnr_region"], 2),
        "psnr_published_oracle_gain_db": round(mean[("published, oracle gain", 16)]["psnr_region"], 2),
        "psnr_full_mesh_colour_lighting_db": round(mean[("full, lighting: mesh colours only", 16)]["psnr_region"], 2),
        "psnr_published_mesh_colour_lighting_db": round(
            mean[("published, lighting: mesh colours only", 16)]["psnr_region"], 2),
        "ssim_full_mesh_colour_lighting": round(mean[("full, lighting: mesh colours only", 16)]["ssim"], 4),
        "ssim_published_mesh_colour_lighting": round(mean[("published, lighting: mesh colours only", 16)]["ssim"], 4),
        "object_brightness_full_mesh_colour_lighting": round(
            mean[("full, lighting: mesh colours only", 16)]["interior_gain"], 3),
        "photo_lighting_seconds_per_scan": {"wall": round(photo_light_secs[0], 3), "cpu": round(photo_light_secs[1], 3),
                                            "photo_frames": tcfg.photo_frames},
        "photo_lighting_env_straight_up": round(float(lighting["default"][1][0, 0].mean()), 4),
        "trace_room_albedo_default": tcfg.room_albedo,
        "camera_model": {**camera.to_dict(), "exposure": f"exp(U(-{CAMERA_EXPOSURE_LOG}, {CAMERA_EXPOSURE_LOG})) per view"},
        "camera_exposure_true": [round(r["exposure_true"], 4) for r in rows[("estimates", 0)]],
        "camera_exposure_estimated": [round(r["exposure_est"], 4) for r in rows[("estimates", 0)]],
        "camera_exposure_estimated_at_exposure_1": [round(r["exposure_est_at_1"], 4) for r in rows[("estimates", 0)]],
        "camera_exposure_estimated_relative": [round(r["exposure_est"] / r["exposure_est_at_1"], 4)
                                               for r in rows[("estimates", 0)]],
        "psnr_published_camera_exposure_1_db": round(mean[("published, camera exposure 1", 16)]["psnr_region"], 2),
        "psnr_full_camera_exposure_1_db": round(mean[("full, camera exposure 1", 16)]["psnr_region"], 2),
        "ssim_published_camera_exposure_1": round(mean[("published, camera exposure 1", 16)]["ssim"], 4),
        "ssim_full_camera_exposure_1": round(mean[("full, camera exposure 1", 16)]["ssim"], 4),
        "trace_light_gain_default": tcfg.light_gain,
        "noise_truth": round(truth_noise, 2), "noise_published": round(pub["noise"], 2),
        "noise_full": round(fm["noise"], 2),
        "truth_floor_psnr_db": round(floor["psnr_region"], 2), "truth_floor_ssim": round(floor["ssim"], 4),
        "estimated_blur_sigma_px": round(mean[("estimates", 0)]["blur_sigma"], 3),
        "estimated_photo_noise_gray": round(mean[("estimates", 0)]["photo_noise"], 3),
        "noise_added_gray": round(mean[("estimates", 0)]["noise_added"], 3),
        "views": len(vlist), "frames": [v["frame"] for v in vlist], "scan_seed": SCAN_SEED,
        "truth_spp": spp_truth, "region_px_mean": round(mean[("truth", 0)]["region_px"], 1),
        "object_px_mean": round(mean[("truth", 0)]["object_px"], 1),
        "table": {name: {k: round(v, 3) for k, v in m.items()} for (name, spp), m in mean.items() if spp == 16},
        "table_by_spp": {f"{name} @ {spp} spp": {k: round(v, 3) for k, v in m.items()}
                         for (name, spp), m in mean.items() if spp > 0},
    })
    res.notes += [
        f"Truth: the scan generator's path-traced photo mode (render_traced_view on the TRUE room: textures, "
        f"one-sided area lights, GI) with the objects inserted, {spp_truth} spp, the same seed as the photo "
        f"(correlated samples), through the same camera model (CameraModel: Gaussian PSF sigma {CAMERA_BLUR} px "
        f"in linear light, then the generator's read + shot noise with the same draws).",
        "Composites: the pipeline's own view of that scan: the ingested scanner mesh (its vertex colours) lit "
        "as the trace stage lights a real scan, trace passes at the given spp with the stage's denoiser and "
        "shadow settings, composite stage gain. So the benchmark measures scan-mesh lighting + passes + blend "
        "against physically traced truth, not one tracer against itself.",
        "Truth floor: PSNR/SSIM of a second truth render with other path samples (same sensor noise) against "
        "the truth, view 0: no composite can be expected to beat it by much.",
        "Photo and truth share one sensor-noise field; the composite's added noise is independent, so PSNR "
        "penalises matched noise: judge noise by the 'noise' vs truth figures.",
        "'full, oracle shadow pass': the true shadow ratio (truth/photo luminance outside the objects) in "
        "place of the trace stage's pass: the blend's ceiling when the shadow pass is right.",
        "'oracle gain' variants scale the trace pass by the truth's object brightness (true / traced mean linear "
        "luminance on fully covered pixels, per view; the composite stage's composite.exposure does the same "
        "scaling): what the blend gives when the trace stage's scan lighting gets the objects' brightness right.",
        "Trace lighting (trace.photo_frames, trace.room_albedo): clipped photo pixels mark lights on the room mesh, "
        "photo rays leaving the mesh fill an environment map for escaping rays, and directions no photo saw get the "
        "radiance that balances the energy of the room points the photos saw (grey-world room albedo prior 0.5, not "
        "fitted to this benchmark; 0.3 and 0.7 shown as 'lighting: albedo' rows). 'lighting: mesh colours only': "
        "mesh colours + a constant mean-radiance environment.",
        "Camera matching = the measured exposure (trace stage: photo / room-mesh colour luminance, per frame) + the "
        "measured blur + the measured noise; 'full - camera matching' drops all three.",
        "Exposure calibration (a generator artefact, not a pipeline step): the generator's scanner mesh carries its "
        "raster light map, which is darker than its traced photos (SYNTHSCAN_TRACED_RASTER_MEAN_RATIO 0.8-1.6; the "
        "estimator finds 1.2-1.5 at exposure 1, camera_exposure_estimated_at_exposure_1), whereas a real scan's mesh "
        "colours are fused from its photos. The benchmark divides the estimate by the same estimate on the view's "
        "exposure-1 photo, so exposure matching is credited only for the exposure it recovers "
        "(camera_exposure_estimated_relative against camera_exposure_true). On 7-Scenes redkitchen the raw estimate "
        "varies 0.85-1.48 over frames (automatic exposure).",
        f"Camera: every view has its own automatic exposure exp(U(-{CAMERA_EXPOSURE_LOG}, {CAMERA_EXPOSURE_LOG})) "
        "(photo and truth alike; the scan mesh keeps the generator's exposure); 'camera exposure 1' rows: the same "
        "views without it.",
        "interior_gain: mean linear luminance of the object interiors, composite / truth.",
        "seconds = trace passes the blend needs (published: PBR+AO render only; shadows: + shadow pass) + blend. "
        "The tracer's spp is adaptive (trace.noise_target), so its time depends on the lighting: the 'lighting' rows "
        "were traced with other lighting and took 1.3-2.7x longer (noisier light, more samples before the stop).",
    ]
    _sheet_png(sheet, len(vlist))
    return res


def _ablation_png(table: dict[str, dict], truth_noise: float) -> None:
    """bench/results/composite_ablation.png: PSNR by region and SSIM of every variant (16 spp)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(table)
    keys = [("psnr_region", "objects + band + shadows"), ("psnr_edges", "edge pixels"),
            ("psnr_shadow", "shadow / band pixels"), ("psnr_interior", "object interiors")]
    fig, axes = plt.subplots(1, 4, figsize=(15, 6.5), dpi=100, gridspec_kw={"width_ratios": [3, 1, 1, 1]})
    y = np.arange(len(names))
    hgt = 0.2
    for i, (k, lab) in enumerate(keys):
        axes[0].barh(y + (i - 1.5) * hgt, [table[n][k] for n in names], height=hgt, label=lab)
    axes[0].set_yticks(y, names)
    axes[0].invert_yaxis()
    axes[0].set_xlabel("PSNR against the path-traced truth (dB)")
    axes[0].set_xlim(max(0.0, min(min(table[n][k] for n in names) for k, _ in keys) - 3.0), None)
    axes[0].legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2)
    axes[0].grid(axis="x", alpha=0.3)
    axes[1].barh(y, [table[n]["ssim"] for n in names], color="gray")
    axes[1].set_yticks(y, [])
    axes[1].invert_yaxis()
    axes[1].set_xlim(max(0.0, min(table[n]["ssim"] for n in names) - 0.05), 1.0)
    axes[1].set_xlabel("SSIM (objects + band)")
    axes[2].barh(y, [table[n]["noise"] for n in names], color="tab:purple")
    axes[2].axvline(truth_noise, color="k", ls="--", label=f"truth {truth_noise:.2f}")
    axes[2].set_yticks(y, [])
    axes[2].invert_yaxis()
    axes[2].set_xlabel("noise on objects (gray)")
    axes[2].legend(fontsize=8)
    axes[3].barh(y, [table[n]["seconds"] for n in names], color="tab:olive")
    axes[3].set_yticks(y, [])
    axes[3].invert_yaxis()
    axes[3].set_xlabel("s / frame (trace + blend)")
    fig.suptitle("composite: published -> + soft edges -> + shadows -> + camera matching (exposure, blur, noise); "
                 "leave-one-out; camera without auto exposure; trace lighting; oracles (16 spp, mean over views)",
                 fontsize=10)
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

    w, h = cam.width, cam.height
    xs = np.linspace(0.3 * w, 0.7 * w, 9)
    ys = np.linspace(0.45 * h, 0.85 * h, 7)
    px = np.array([[x, y] for y in ys for x in xs])
    pix = np.floor(px[:, 1]).astype(int) * w + np.floor(px[:, 0]).astype(int)
    o, d = cam.rays(pix, np.full((len(pix), 2), 0.5))
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
    from pipeline.ingest import ingest_scan
    from pipeline.runfolder import load_scan
    from pipeline.scanformats.common import read_color
    from pipeline.io import atomic_write_image
    from pipeline.objects import load_library
    from pipeline.scanformats.mesh import read_room_ply
    from pipeline.seeding import item_rng
    from pipeline.camera import Camera
    from pipeline.trace.scene import build_scene, instance_from_model
    from pipeline.trace.stage import object_passes, shadow_pass

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
    tcfg = dataclasses.replace(cfg.trace, lighting="scan")   # the sheet shows the scan lighting (see above)
    from pipeline.trace.photolights import scan_lighting

    t0 = time.perf_counter()
    light_v, env_map = scan_lighting(scan, rv, rf, rc, tcfg, 0)
    log.info("photo-based lighting of redkitchen in %.1f s", time.perf_counter() - t0)
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
                            light_gain=tcfg.light_gain, light_vertices=light_v, env_map=env_map)

        o, d = cam.rays(np.arange(w * h), np.full((w * h, 2), 0.5))
        hh = scene.intersector.intersect(o, d)
        labels = np.where(hh.hit, scene.tri_inst[np.maximum(hh.prim, 0)], 0).astype(np.uint16).reshape(h, w)
        t0 = time.perf_counter()
        _, fb, pbr, ao = object_passes(scene, cam, labels, tcfg, rng, ao=True)
        sr = shadow_pass(scene, cam, labels, tcfg, rng)
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


# ---------------------------------------------------------------------------------------------------
# Contact shadows (issue 16): the shadow ratio near where objects meet the floor
# ---------------------------------------------------------------------------------------------------

CONTACT_REF_SAMPLES = 256   # rays per pixel of the stride-1 reference (the issue's)


def contact_scene(lit: bool):
    """A sphere and a box resting on the floor of a box room, seen from 1.1 m at 640x480. ``lit``: a bright
    ceiling (light from above; a noisier reference) instead of a uniformly bright room."""
    import trimesh

    from pipeline.camera import Camera
    from pipeline.geometry import look_at
    from pipeline.trace.scene import ObjectInstance, build_scene

    room = trimesh.creation.box(extents=(4.0, 4.0, 2.6)).subdivide().subdivide().subdivide()
    rv, rf = room.vertices + [0, 0, 1.3], room.faces[:, ::-1]          # faces looking inward
    rad = np.full((len(rv), 3), 0.3 if lit else 1.0)
    if lit:
        rad[rv[:, 2] > 2.59] = 2.0

    def instance(mesh: trimesh.Trimesh) -> ObjectInstance:
        return ObjectInstance(vertices=mesh.vertices, faces=mesh.faces, normals=mesh.vertex_normals,
                              albedo=np.full((len(mesh.vertices), 3), 0.5, np.float32))

    sph = instance(trimesh.creation.icosphere(subdivisions=4, radius=0.12).apply_translation((0, 0, 0.12)))
    box = instance(trimesh.creation.box(extents=(0.2, 0.12, 0.15)).apply_translation((0.35, 0.1, 0.075)))
    sc = build_scene(rv, rf, None, [sph, box], room_linear_radiance=rad)
    cam = Camera(K=np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]]),
                 T_c2w=look_at((0.1, -1.1, 0.8), (0.15, 0.05, 0.05)), width=640, height=480)
    o, d = cam.rays(np.arange(640 * 480), np.full((640 * 480, 2), 0.5))
    h = sc.intersector.intersect(o, d)
    labels = np.where(h.hit, sc.tri_inst[np.maximum(h.prim, 0)], 0).astype(np.uint16).reshape(480, 640)
    return sc, cam, labels


def contact_shadows(quick: bool) -> BenchResult:
    """Shadow-ratio error within 3 px of the objects against a stride-1, 256-ray reference, against CPU."""
    from scipy import ndimage

    from pipeline.config import TraceConfig
    from pipeline.trace.shadow import shadow_ratio, split_intersectors

    cfg = TraceConfig()
    res = BenchResult("composite_contact", speed_label="CPU seconds per frame (shadow pass, 640x480)",
                      accuracy_label="mean |ratio - reference| within 3 px of the objects")
    cache = Path(tempfile.gettempdir()) / "scansynth-bench-contact"
    cache.mkdir(exist_ok=True)
    for lit in (False, True):
        name = "lit ceiling" if lit else "uniform room"
        sc, cam, labels = contact_scene(lit)
        rooms, objs = split_intersectors(sc)
        band = ndimage.binary_dilation(labels > 0, iterations=3) & (labels == 0)
        refs = []
        for k in range(1 if quick else 2):   # two references: the second measures the reference's own noise
            f = cache / f"ref-{int(lit)}-{k}.npy"
            if not f.is_file():
                np.save(f, shadow_ratio(sc, cam, labels, np.random.default_rng(100 + k), samples=CONTACT_REF_SAMPLES,
                                        min_effect=cfg.shadow_min_effect, stride=1, smooth=0.0,
                                        room_isect=rooms, obj_isect=objs))
            refs.append(np.load(f))
        ref = refs[0]
        if len(refs) > 1:
            res.figures[f"{name}: reference self-MAE"] = round(float(np.abs(refs[1] - ref)[band].mean()), 4)
        variants = {"default": {}, "no contact band (grid only)": {"contact_px": 0}}
        for label, extra in variants.items():
            secs, err, mean = [], [], []
            for rep in range(1 if quick else 3):
                t = time.process_time()
                sr = shadow_ratio(sc, cam, labels, np.random.default_rng(rep), samples=cfg.shadow_samples,
                                  min_effect=cfg.shadow_min_effect, stride=cfg.shadow_stride,
                                  smooth=cfg.shadow_smooth, room_isect=rooms, obj_isect=objs, **extra)
                secs.append(time.process_time() - t)
                err.append(float(np.abs(sr - ref)[band].mean()))
                mean.append(float(sr[band].mean()))
            res.add_point(name, speed=min(secs), accuracy=float(np.mean(err)), label=label,
                          baseline=(label != "default" and not lit), band_mean=float(np.mean(mean)),
                          reference_band_mean=float(ref[band].mean()))
            res.figures[f"{name}: {label} MAE"] = round(float(np.mean(err)), 4)
            res.figures[f"{name}: {label} cpu s"] = round(min(secs), 3)
        res.figures[f"{name}: cost ratio default / grid only"] = round(
            res.figures[f"{name}: default cpu s"] / res.figures[f"{name}: no contact band (grid only) cpu s"], 3)
    res.notes.append("MAE against a single 256-ray reference includes that reference's own noise (its self-MAE "
                     "against a second reference is listed): an estimate cannot score much below it.")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=3, help="camera views (1..4)")
    ap.add_argument("--quick", action="store_true", help="low reference quality, one spp setting (smoke run)")
    ap.add_argument("--contact", action="store_true",
                    help="only the contact-shadow measurement (results/composite_contact.json, .png)")
    ap.add_argument("--sheet", action="store_true",
                    help="only the 7-Scenes contact sheet (runs/bench-composite/composite_sheet.png, not committed)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.sheet:
        real_sheet()
        return
    if args.contact:
        res = contact_shadows(args.quick)
        for k, v in zip(res.write(), ("json", "png")):
            print(f"wrote {v}: {k}")
        for k, v in res.figures.items():
            print(f"{k}: {v}")
        return
    res = run(max(1, min(args.views, 4)), args.quick)
    j, p = res.write()
    print(f"wrote {j} and {p}")
    for k, v in res.figures.items():
        if not k.startswith("table"):
            print(f"{k}: {v}")
    for name, m in res.figures["table"].items():
        if "psnr_region" not in m:
            continue
        print(f"{name:32s} PSNR {m['psnr_region']:6.2f} edges {m['psnr_edges']:6.2f} shadow {m['psnr_shadow']:6.2f} "
              f"interior {m['psnr_interior']:6.2f} SSIM {m['ssim']:.4f} noise {m['noise']:.2f} "
              f"brightness {m['interior_gain']:.2f} s {m['seconds']:.3f} (blend {m['seconds_blend'] * 1000:.1f} ms)")


if __name__ == "__main__":
    main()
