"""The ``trace`` stage: AO, PBR, shadow-ratio, albedo and normal passes of every rastered frame.

Items are the raster stage's accepted frames, ``<scene>/drop<NNNN>/f<frame:06d>``. Each item reads
the raster frame (``labels`` and the JSON's camera and per-instance ``obj_id``, ``R_m2c``, ``t_m2c``),
the ingested scan and object library, and the room mesh at the level of detail prep chose for tracing
(``RUN/prep/<scene>/room_trace.ply``, else the ingest room mesh). It writes
``RUN/trace/<scene>/drop<NNNN>/f<frame:06d>.npz`` with

- ``pbr`` (H, W, 3) float32: linear radiance, premultiplied by ``coverage``; 0 outside traced pixels;
- ``ao`` (H, W) float32 in [0, 1] (1 outside object pixels);
- ``coverage`` (H, W) float32 in [0, 1]: share of the pixel covered by an unoccluded object;
- ``shadow_ratio`` (H, W) float32: room light with objects / without (1 where unchanged);
- ``albedo`` (H, W, 3) float32 and ``normal`` (H, W, 3) float32 (camera frame), premultiplied;
- ``spp`` (H, W) uint16: samples taken per pixel.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from pipeline.config import TraceConfig
from pipeline.errors import InputError
from pipeline.io import atomic_save_npz, load_npz, read_json
from pipeline.runner import Item, Stage, StageContext

log = logging.getLogger(__name__)


def output_path(run_dir: str | Path, scene: str, drop: int, frame: int) -> Path:
    """``RUN/trace/<scene>/drop<NNNN>/f<frame:06d>.npz``."""
    return Path(run_dir) / "trace" / scene / f"drop{drop:04d}" / f"f{frame:06d}.npz"


def load_trace(run_dir: str | Path, scene: str, drop: int, frame: int) -> dict[str, np.ndarray]:
    """The arrays the trace stage wrote for a frame (see the module docstring)."""
    p = output_path(run_dir, scene, drop, frame)
    if not p.is_file():
        raise InputError(f"{p} is missing: run 'scansynth trace' first")
    return load_npz(p)


def settings_from_config(cfg: TraceConfig):
    """:class:`~pipeline.trace.pbr.RenderSettings` of a :class:`TraceConfig`."""
    from pipeline.trace.pbr import RenderSettings

    return RenderSettings(spp=cfg.spp, spp_min=min(cfg.spp_min, cfg.spp), spp_batch=min(4, cfg.spp),
                          noise_target=cfg.noise_target, max_depth=cfg.max_depth, ao_samples=cfg.ao_samples,
                          ao_distance=cfg.ao_distance)


def room_mesh_path(run_dir: Path, scan) -> str:
    """The room mesh to trace: prep's ``room_trace.ply`` when present, else the ingest mesh."""
    p = run_dir / "prep" / scan.name / "room_trace.ply"
    return str(p) if p.is_file() else scan.mesh_path


def plan(ctx: StageContext) -> list[Item]:
    root = ctx.run_dir / "raster"
    items = []
    if not root.is_dir():
        log.warning("trace: %s does not exist; run the raster stage first", root)
        return items
    for npz in sorted(root.glob("*/drop*/f*.npz")):
        scene, drop_dir, stem = npz.parent.parent.name, npz.parent.name, npz.stem
        try:
            drop, frame = int(drop_dir[4:]), int(stem[1:])
        except ValueError:
            continue
        items.append(Item(key=f"{scene}/{drop_dir}/{stem}", data={"scene": scene, "drop": drop, "frame": frame}))
    return items


def run_item(ctx: StageContext, item: Item) -> dict:
    from pipeline.ingest import load_objects, load_scan
    from pipeline.scanformats.mesh import read_room_ply
    from pipeline.trace.denoise import denoise
    from pipeline.trace.pbr import Camera, render, trace_mask
    from pipeline.trace.scene import build_scene, instance_from_model
    from pipeline.trace.shadow import shadow_ratio

    cfg = ctx.cfg.trace
    t0 = time.perf_counter()
    scene_name, drop, frame = item.data["scene"], int(item.data["drop"]), int(item.data["frame"])
    stem = ctx.run_dir / "raster" / scene_name / f"drop{drop:04d}" / f"f{frame:06d}"
    doc = read_json(stem.with_suffix(".json"))
    labels = load_npz(stem.with_suffix(".npz"))["labels"]
    scan = load_scan(ctx.run_dir, scene_name)
    library = {o.obj_id: o for o in load_objects(ctx.run_dir)}
    T_c2w = np.asarray(doc["T_c2w"], np.float64)
    instances = []
    for inst in doc["instances"]:
        oid = int(inst["obj_id"])
        if oid not in library:
            raise InputError(f"{stem}.json: object id {oid} is not in the ingested library; re-run ingest "
                             f"with the same objects.paths as raster")
        R_m2w = T_c2w[:3, :3] @ np.asarray(inst["R_m2c"], np.float64)
        t_m2w = T_c2w[:3, :3] @ np.asarray(inst["t_m2c"], np.float64) + T_c2w[:3, 3]
        instances.append(instance_from_model(library[oid], R_m2w, t_m2w))
    rv, rf, rc = read_room_ply(room_mesh_path(ctx.run_dir, scan))
    env = None if cfg.env_radiance < 0 else np.full(3, cfg.env_radiance, np.float32)
    scene = build_scene(rv, rf, rc, instances, lighting=cfg.lighting, radiance_scale=cfg.radiance_scale,
                        light_threshold=cfg.light_threshold, light_gain=cfg.light_gain, env_radiance=env,
                        published_power=cfg.published_power, up=scan.up_w)
    cam = Camera(K=np.asarray(doc["K"], np.float64), T_c2w=T_c2w, width=int(doc["width"]),
                 height=int(doc["height"]))
    if labels.shape != (cam.height, cam.width):
        raise InputError(f"{stem}.npz: labels {labels.shape} do not match the frame size "
                         f"{(cam.height, cam.width)} in its JSON; re-run raster")
    rng = ctx.rng(item)
    mask = trace_mask(labels, cfg.edge_band)
    fb = render(scene, cam, mask, settings_from_config(cfg), rng)
    pbr = fb.pbr
    if cfg.denoise != "off":
        pbr = denoise(fb.pbr, fb.albedo, fb.normal, fb.coverage > 0, method=cfg.denoise)
    sr = (shadow_ratio(scene, cam, labels, rng, samples=cfg.shadow_samples, min_effect=cfg.shadow_min_effect)
          if cfg.shadow_samples > 0 else np.ones(labels.shape, np.float32))
    atomic_save_npz(output_path(ctx.run_dir, scene_name, drop, frame), pbr=pbr.astype(np.float32),
                    ao=fb.ao, coverage=fb.coverage, shadow_ratio=sr, albedo=fb.albedo, normal=fb.normal,
                    spp=np.minimum(fb.spp, 65535).astype(np.uint16))
    traced = int(mask.sum())
    return {"traced_px": traced, "object_px": int((labels > 0).sum()), "rays": int(fb.rays),
            "mean_spp": float(fb.spp[mask].mean()) if traced else 0.0,
            "shadow_px": int((sr != 1.0).sum()), "seconds": round(time.perf_counter() - t0, 3)}


STAGE = Stage("trace", plan, run_item)
