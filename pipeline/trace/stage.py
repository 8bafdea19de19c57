"""The ``trace`` stage: AO, PBR, shadow-ratio, albedo and normal passes of every rastered frame.

Items are chunks of a drop's frames, ``<scene>/drop<NNNN>/f<first>-f<last>`` (``trace.frames_per_item``):
the Embree scene (room + placed objects) is built once per item and each of its frames is traced with
it. What does not change between items of a scene (the room mesh and its photo-based lighting) is kept
per worker process (:func:`_room`). Each frame's generator is derived
from the run seed and the frame's own key, so outputs do not depend on how frames are grouped. An item
reads the raster frames (``labels`` and the JSON's camera and per-instance ``obj_id``, ``R_m2c``,
``t_m2c``), the ingested scan and object library, and the room mesh at the level of detail prep chose
for tracing (``RUN/prep/<scene>/room_trace.ply``, else the ingest room mesh). It writes
``RUN/trace/<scene>/drop<NNNN>/f<frame:06d>.npz`` per frame with

- ``pbr`` (H, W, 3) float32: linear radiance, premultiplied by ``coverage``; 0 outside traced pixels
  (denoised with ``trace.denoise``);
- ``ao`` (H, W) float32 in [0, 1] (1 outside object pixels; denoised too); traced for
  ``composite.mode = "published"`` only, its one reader (1 everywhere otherwise: :func:`ao_used`);
- ``coverage`` (H, W) float32 in [0, 1]: share of the pixel covered by an unoccluded object;
- ``shadow_ratio`` (H, W) float32: room light with objects / without (1 where unchanged);
- ``albedo`` (H, W, 3) float32 and ``normal`` (H, W, 3) float32 (camera frame), premultiplied;
- ``spp`` (H, W) uint16: samples taken per pixel;
- ``exposure`` () float32: the photo's exposure relative to the room mesh colours (1 = the same; see
  :func:`pipeline.trace.photolights.frame_exposure`; 1 without a photo).
"""

from __future__ import annotations

import functools
import logging
import os
from pathlib import Path

import numpy as np

from pipeline.config import TraceConfig
from pipeline.errors import InputError
from pipeline.io import atomic_save_npz, load_npz
from pipeline.runfolder import (DROP_TPATH, FRAMES_TPATH, SCAN_TPATH, TRACE_TPATH, FrameKey, RasterFrame,
                                file_stamp, load_objects, load_raster_frame, load_scan, path, raster_frames,
                                room_trace_mesh)
from pipeline.runner import worker_count
from pipeline.scanformats.common import read_color
from pipeline.stages import Item, Stage, StageContext
from pipeline.threads import one_blas_thread

log = logging.getLogger(__name__)


def settings_from_config(cfg: TraceConfig, ao: bool = True):
    """:class:`~pipeline.trace.pbr.RenderSettings` of a :class:`TraceConfig`; ``ao=False``: no AO pass."""
    from pipeline.trace.pbr import RenderSettings

    return RenderSettings(spp=cfg.spp, spp_min=min(cfg.spp_min, cfg.spp), spp_batch=min(4, cfg.spp),
                          noise_target=cfg.noise_target, max_depth=cfg.max_depth,
                          ao_samples=cfg.ao_samples if ao else 0, ao_distance=cfg.ao_distance)


def ao_used(cfg) -> bool:
    """Whether a run's composite reads the AO pass: only the published blend (PBR x AO) does; the full blend's
    path-traced radiance holds the objects' self-occlusion already. Elsewhere the pass is not traced (its
    rays and its denoising were 9 % of a 7-Scenes trace item) and ``ao`` is written as 1."""
    return cfg.composite.mode == "published"


def plan(ctx: StageContext) -> list[Item]:
    frames = raster_frames(ctx.run_dir)
    if not frames:
        log.warning("trace: no raster frame in %s; run the raster stage first", ctx.run_dir / "raster")
    # Chunks of a drop's frames: the scene is built once per item, and items small enough to spread over the
    # workers (one item per drop left one core idle at the end of a run). Keys depend only on the frames.
    drops: dict[tuple[str, int], list[int]] = {}
    for k in frames:
        drops.setdefault((k.scene, k.drop), []).append(k.frame)
    n = ctx.cfg.trace.frames_per_item
    items = []
    for (scene, drop), fr in sorted(drops.items()):
        for i in range(0, len(fr), n):
            chunk = fr[i:i + n]
            items.append(Item(key=f"{DROP_TPATH.format(scene=scene, drop=drop)}/f{chunk[0]:06d}-f{chunk[-1]:06d}",
                              data={"scene": scene, "drop": drop, "frames": chunk}))
    # the largest items first (a stable sort: drop order among equals). The workers take items in this
    # order, so the short remainder chunks fill the last gaps instead of a full chunk running alone at the
    # end: on the 7-Scenes kitchen (12 items) one worker sat idle for the last 8.6 s of a 100 s stage
    items.sort(key=lambda it: -len(it.data["frames"]))
    if ctx.cfg.trace.lighting == "fit":
        # the light fit once per scene, here, before the items spread over the workers (each would fit
        # it again until the first had written it); the items read RUN/trace/<scene>/lights.npz. Nothing
        # else runs meanwhile: its shadow rays and level searches take as many threads as the run has
        # workers (the same bytes on any number; BLAS stays on one thread per product, whose rounding
        # would change with more)
        threads = min(worker_count(ctx.cfg), os.cpu_count() or 1)
        for scene in sorted({sc for sc, _ in drops}):
            try:
                with one_blas_thread():
                    _room(str(ctx.run_dir), scene, ctx.cfg.trace, ctx.cfg.run.seed, _stamps(ctx, scene), threads)
            except InputError as e:   # said by every item of the scene, which fails alone
                log.warning("trace: light fit of %s: %s", scene, e)
    return items


def _stamps(ctx: StageContext, scene_name: str) -> tuple:
    """Stamps of the files a scene's room lighting is made from (the key of :func:`_room`'s cache)."""
    scan = load_scan(ctx.run_dir, scene_name)
    return tuple(file_stamp(p) for p in (path(ctx.run_dir, SCAN_TPATH, scene=scene_name),
                                         path(ctx.run_dir, FRAMES_TPATH, scene=scene_name),
                                         Path(room_trace_mesh(ctx.run_dir, scan, ctx.cfg.trace.room_mesh)))
                 if p.is_file())


def _instances(rf: RasterFrame, library: dict) -> list:
    from pipeline.trace.scene import instance_from_model

    out = []
    for inst in rf.instances:
        if inst.obj_id not in library:
            raise InputError(f"{rf.stem}.json: object id {inst.obj_id} is not in the ingested library; re-run "
                             f"ingest with the same objects.paths as raster")
        out.append(instance_from_model(library[inst.obj_id], inst.R_m2w, inst.t_m2w))
    return out


def object_passes(scene, cam, labels: np.ndarray, cfg: TraceConfig, rng: np.random.Generator, *, ao: bool,
                  object_shadows=None) -> tuple:
    """The objects' passes of one frame: ``(mask, fb, pbr, ao)``, as the stage traces and denoises them.

    ``mask`` (H, W) bool: the traced pixels (:func:`~pipeline.trace.pbr.trace_mask` of ``labels (H, W)``);
    ``fb``: :func:`~pipeline.trace.pbr.render`'s :class:`~pipeline.trace.pbr.FrameBuffers`; ``pbr``
    (H, W, 3) and ``ao`` (H, W) float32: its passes after ``cfg.denoise``. ``ao=False`` traces no AO
    (``ao`` is then ``fb.ao``, 1 everywhere). ``object_shadows``: the scene's
    :class:`~pipeline.trace.pbr.ObjectShadows` (fit lighting), or None. Shared with ``bench/composite.py``,
    which measures the blends on the stage's own passes.
    """
    from pipeline.trace.denoise import denoise, denoise_ao
    from pipeline.trace.pbr import render, trace_mask

    mask = trace_mask(labels, cfg.edge_band)
    fb = render(scene, cam, mask, settings_from_config(cfg, ao=ao), rng, object_shadows=object_shadows)
    pbr, ao_pass = fb.pbr, fb.ao
    if cfg.denoise != "off":
        pbr = denoise(fb.pbr, fb.albedo, fb.normal, fb.coverage > 0, method=cfg.denoise)
        if ao:
            ao_pass = denoise_ao(fb.ao, fb.normal, fb.coverage > 0, method=cfg.denoise)
    return mask, fb, pbr, ao_pass


def shadow_pass(scene, cam, labels: np.ndarray, cfg: TraceConfig, rng: np.random.Generator, *, room_isect=None,
                obj_isect=None) -> np.ndarray:
    """(H, W) float32 shadow ratio of one frame with ``cfg``'s settings (1 everywhere when
    ``cfg.shadow_samples`` is 0); drawn from ``rng`` after :func:`object_passes`. Shared with
    ``bench/composite.py``."""
    from pipeline.trace.shadow import shadow_ratio

    if cfg.shadow_samples <= 0:
        return np.ones(labels.shape, np.float32)
    return shadow_ratio(scene, cam, labels, rng, samples=cfg.shadow_samples, min_effect=cfg.shadow_min_effect,
                        stride=cfg.shadow_stride, smooth=cfg.shadow_smooth, room_isect=room_isect,
                        obj_isect=obj_isect)


def trace_frame(ctx: StageContext, scene, rf: RasterFrame, labels: np.ndarray, *, room_isect=None,
                obj_isect=None, exposure: float = 1.0, object_shadows=None) -> dict:
    """Trace one frame with a prebuilt scene and write its NPZ; returns the frame's summary.

    ``exposure``: the photo's exposure relative to the room mesh colours
    (:func:`pipeline.trace.photolights.frame_exposure`), stored for the compositor. ``object_shadows``: the
    scene's :class:`~pipeline.trace.pbr.ObjectShadows` (fit lighting), or None.
    """
    from pipeline.seeding import item_rng

    cfg = ctx.cfg.trace
    cam = rf.camera
    if labels.shape != cam.shape:
        raise InputError(f"raster frame {rf.key}: labels {labels.shape} do not match the frame size {cam.shape} "
                         f"in its JSON; re-run raster")
    rng = item_rng(ctx.cfg.run.seed, ctx.stage, str(rf.key))
    mask, fb, pbr, ao = object_passes(scene, cam, labels, cfg, rng, ao=ao_used(ctx.cfg),
                                      object_shadows=object_shadows)
    sr = shadow_pass(scene, cam, labels, cfg, rng, room_isect=room_isect, obj_isect=obj_isect)
    atomic_save_npz(rf.key.path(ctx.run_dir, TRACE_TPATH), pbr=pbr.astype(np.float32),
                    ao=ao, coverage=fb.coverage, shadow_ratio=sr, albedo=fb.albedo, normal=fb.normal,
                    spp=np.minimum(fb.spp, 65535).astype(np.uint16), exposure=np.float32(exposure))
    traced = int(mask.sum())
    return {"traced_px": traced, "object_px": int((labels > 0).sum()), "rays": int(fb.rays),
            "mean_spp": round(float(fb.spp[mask].mean()), 3) if traced else 0.0,
            "shadow_px": int((sr != 1.0).sum())}


@functools.lru_cache(maxsize=2)
def _room(run_dir: str, scene_name: str, cfg: TraceConfig, seed: int, stamps: tuple, fit_threads: int = 1) -> tuple:
    """``(scan, room vertices, faces, colours, light_vertices, env_map, room_lights)`` of a scene, read-only
    arrays (``room_lights``: the fitted :class:`~pipeline.trace.lightfit.RoomLights`, fit lighting only).

    Kept per worker process for the next item of the same scene (the photo-based lighting alone costs
    ~0.7 CPU s per item on 7-Scenes); ``stamps`` (path, mtime, size of scan.json and the room mesh)
    make a changed file a new entry. ``fit_threads``: the light fit's threads, where it has to fit.
    """
    scan, rv, rf, rc = _room_mesh(run_dir, scene_name, cfg.room_mesh, stamps)
    light_v = env_map = rl = None
    if cfg.lighting == "scan" and cfg.photo_frames > 0:   # per scan, not per item: same result in every chunk
        from pipeline.trace.photolights import scan_lighting

        light_v, env_map = scan_lighting(scan, rv, rf, rc, cfg, seed)
    if cfg.lighting == "fit":
        rl = room_lights(run_dir, scan, rv, rf, rc, cfg, seed, stamps, fit_threads)
    for a in (light_v, env_map):
        if isinstance(a, np.ndarray):
            a.setflags(write=False)
    return scan, rv, rf, rc, light_v, env_map, rl


@functools.lru_cache(maxsize=2)
def _room_mesh(run_dir: str, scene_name: str, room_mesh: str, stamps: tuple) -> tuple:
    """``(scan, room vertices, faces, colours)`` of a scene, read-only arrays, kept per worker process (read
    by :func:`warm` while the main process fits the lights); ``stamps`` as for :func:`_room`."""
    from pipeline.scanformats.mesh import read_room_ply

    scan = load_scan(run_dir, scene_name)
    rv, rf, rc = read_room_ply(room_trace_mesh(run_dir, scan, room_mesh))
    for a in (rv, rf, rc):
        if a is not None:   # a mesh without colours has none
            a.setflags(write=False)
    return scan, rv, rf, rc


def warm(ctx: StageContext) -> None:
    """A worker's start-up while the main process plans (fits the lights): the tracer's modules and the room
    mesh every item of a scene reads (about 1.5 CPU s per worker on 7-Scenes), for as many scenes as
    :func:`_room_mesh` keeps, those with the most frames first (the plan puts the largest items first)."""
    import collections

    from pipeline.trace import denoise, pbr, scene, shadow  # noqa: F401 - imported for their start-up cost

    frames = collections.Counter(k.scene for k in raster_frames(ctx.run_dir))
    for name in sorted(frames, key=lambda sc: (-frames[sc], sc))[:_room_mesh.cache_info().maxsize]:
        _room_mesh(str(ctx.run_dir), name, ctx.cfg.trace.room_mesh, _stamps(ctx, name))


def fit_settings(cfg: TraceConfig, width: int):
    """:class:`~pipeline.trace.lightfit.FitSettings` of a :class:`TraceConfig` for photos ``width`` wide."""
    from pipeline.trace.lightfit import FitSettings
    from pipeline.trace.photolights import GRID_W

    return FitSettings(points=cfg.fit_points, cell=cfg.fit_cell, stride=max(1, round(width / GRID_W)),
                       sparsity=cfg.fit_sparsity,
                       level_tolerance=cfg.fit_level_tolerance, max_emitters=cfg.fit_emitters,
                       refine=cfg.fit_refine, polish=cfg.fit_polish,
                       albedo_group=cfg.fit_albedo_group,
                       threshold=cfg.light_threshold, radiance_scale=cfg.radiance_scale,
                       white_prior=cfg.fit_white_prior,
                       white_patch=cfg.fit_white_patch, ceiling_albedo=cfg.fit_ceiling_albedo,
                       edge_colour=cfg.fit_edge_colour, capture_views=cfg.fit_capture_views,
                       capture_albedo=cfg.fit_capture_albedo,
                       known_complete=cfg.lights_complete)


# the light fit's source, the modules it computes with and this one (which picks its photos and settings), relative
# to pipeline/: part of the fitted lights' cache key
FIT_SOURCES = tuple(sorted(f"trace/lightfit/{p.name}" for p in (Path(__file__).parent / "lightfit").glob("*.py"))) + (
    "trace/photolights.py", "trace/intersect.py", "trace/sampling.py", "trace/scene.py", "trace/stage.py", "color.py",
    "geometry.py", "camera.py", "seeding.py", "scanformats/common.py")


@functools.lru_cache(maxsize=None)
def fit_code() -> str:
    """sha256 of the light fit's source and of the modules it computes with (:data:`FIT_SOURCES`), part of the
    fitted lights' cache key: a run resumed after any of them changed fits again instead of reading an earlier
    version's lights.npz back (a change elsewhere in the tracer refits too, at ~15 s per scan: safe side)."""
    import hashlib

    import pipeline

    h = hashlib.sha256()
    root = Path(pipeline.__file__).parent
    for name in FIT_SOURCES:
        h.update(name.encode() + b"\0" + (root / name).read_bytes())
    return h.hexdigest()


def room_lights(run_dir: str, scan, rv, rf, rc, cfg: TraceConfig, seed: int, stamps: tuple, threads: int = 1):
    """The scan's fitted lights (:func:`pipeline.trace.lightfit.fit_room_lights`), once per scan.

    Kept in ``RUN/trace/<scene>/lights.npz`` with the key it was made for (the fit's settings and source
    (:func:`fit_code`), the seed, and the contents of scan.json, the frames table and the room mesh): a worker
    or a later run with the same key reads it, anything else fits again (the same bytes for the same key:
    writers racing write the same file).
    """
    import hashlib
    import json

    from pipeline.runfolder import ROOM_LIGHTS_TPATH
    from pipeline.seeding import item_rng
    from pipeline.trace.lightfit import RoomLights, fit_room_lights, read_lights_file

    st = fit_settings(cfg, scan.width)
    # the key hashes the files' contents, not their stamps: a resumed or repeated run writes the same bytes
    def digest(p: str) -> str:
        q = Path(p)
        return hashlib.sha256(q.read_bytes()).hexdigest() if q.is_file() else ""

    files = [digest(s[0]) for s in stamps] + ([digest(cfg.lights_file)] if cfg.lights_file else [])
    key = hashlib.sha256(json.dumps([repr(st), cfg.photo_frames, seed, files, fit_code()], sort_keys=True).encode()
                         ).hexdigest()[:16]
    out = path(run_dir, ROOM_LIGHTS_TPATH, scene=scan.name)
    if out.is_file():
        try:
            rl = RoomLights.load(out)
            if rl.summary.get("key") == key:
                return rl
        except (OSError, ValueError, KeyError):
            pass
    have = np.flatnonzero([bool(p) for p in scan.color_paths])
    idx = (have[np.unique(np.linspace(0, have.size - 1, max(1, cfg.photo_frames)).round().astype(int))]
           if have.size else have)
    frames = [(read_color(scan, int(i)), scan.K[i], scan.T_c2w[i]) for i in idx]
    known = read_lights_file(cfg.lights_file, cfg.radiance_scale) if cfg.lights_file else []
    rl = fit_room_lights(rv, rf, rc, frames, up=scan.up_w, rng=item_rng(seed, "trace", "light-fit", scan.name),
                         settings=st, name=scan.name, known_lights=known, threads=threads)
    rl.summary["key"] = key
    rl.save(out)
    return rl


# the room's own intersector (shadow rays), kept per worker for the next item of the same scene
_ROOM_ISECT: dict = {}


def run_item(ctx: StageContext, item: Item) -> dict:
    with one_blas_thread():   # the workers fill the cores (pipeline.threads)
        return _run_item(ctx, item)


def _run_item(ctx: StageContext, item: Item) -> dict:
    from pipeline.trace.pbr import object_shadows
    from pipeline.trace.scene import build_scene
    from pipeline.trace.shadow import split_intersectors

    cfg = ctx.cfg.trace
    scene_name, drop = item.data["scene"], int(item.data["drop"])
    frames = [int(f) for f in item.data["frames"]]
    stamps = _stamps(ctx, scene_name)
    scan, rv, rf, rc, light_v, env_map, rl = _room(str(ctx.run_dir), scene_name, cfg, ctx.cfg.run.seed, stamps)
    library = {o.obj_id: o for o in load_objects(ctx.run_dir)}
    env = None if cfg.env_radiance < 0 else np.full(3, cfg.env_radiance, np.float32)
    scene = None
    split = (None, None)
    osh = None
    out = {}
    for frame in frames:
        raster = load_raster_frame(ctx.run_dir, FrameKey(scene_name, drop, frame))
        labels = load_npz(raster.stem.with_suffix(".npz"))["labels"]
        if scene is None:  # one placement per drop: every frame's instances have the same world poses
            scene = build_scene(rv, rf, rc, _instances(raster, library), lighting=cfg.lighting,
                                room_lights=rl,
                                radiance_scale=cfg.radiance_scale, light_threshold=cfg.light_threshold,
                                light_gain=cfg.light_gain, env_radiance=env,
                                published_power=cfg.published_power, up=scan.up_w,
                                light_vertices=light_v, env_map=env_map)
            if cfg.shadow_samples > 0 or (rl is not None and cfg.object_shadows > 0):
                # the room's intersector is the same for every drop of the scene: built once per worker
                rkey = (str(ctx.run_dir), scene_name, cfg, ctx.cfg.run.seed, stamps)
                split = split_intersectors(scene, _ROOM_ISECT.get(rkey))
                _ROOM_ISECT.clear()
                _ROOM_ISECT[rkey] = split[0]
            if rl is not None:   # the fit's albedo takes the objects' shadows out of the room they see
                osh = object_shadows(scene, *split, rl.albedo, samples=cfg.object_shadows,
                                     min_effect=cfg.shadow_min_effect)
        exposure = 1.0
        if cfg.lighting in ("scan", "fit") and frame < scan.num_frames and scan.color_paths[frame]:
            from pipeline.trace.photolights import frame_exposure

            exposure = frame_exposure(scene, scan.camera(frame), read_color(scan, frame),
                                      radiance_scale=cfg.radiance_scale, threshold=cfg.light_threshold)
        out[f"f{frame:06d}"] = trace_frame(ctx, scene, raster, labels, room_isect=split[0], obj_isect=split[1],
                                           exposure=exposure, object_shadows=osh)
    return {"frames": out}


STAGE = Stage("trace", plan, run_item, warm=warm)
