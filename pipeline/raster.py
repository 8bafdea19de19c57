"""Raster passes and annotations: what the camera sees of the dropped objects, per frame.

Items are (scene, drop, frame): a simulated drop gets the kept frames that :mod:`pipeline.frame_views`
predicts to pass the three rejection checks below (at most ``raster.frames_per_drop``, the best-seeing
first), so no work goes to frames that would be rejected; a poses file's drop gets the frames it lists,
or every kept frame. For each item:

1. Camera-from-model poses of the instances; each instance's projected window (from its vertices).
   **Early rejection** before any rendering: when even the sum of the windows' areas inside the image
   is below ``raster.min_visible_area`` of the image, the frame cannot reach it and is rejected.
2. **Object passes**: each instance alone over its projected window (amodal depth, so amodal masks
   and the object depth/label composition come from the same rasterization), plus the parts of its
   silhouette outside the image (for BOP's ``px_count_all``). Nearest instance per pixel -> object
   depth and front labels (uint16: no 255-object limit). Second rejection check on the amodal union,
   before the room pass.
3. **Scene depth**: the room mesh's depth at the frame, rendered once per frame and cached on disk
   (``RUN/raster/<scene>/scene_depth/f<frame:06d>.npz``), shared by every drop.
4. **Occlusion**: object pixels behind the room are hidden; with ``raster.real_depth_fusion`` the real
   sensor depth also hides them where it is valid and nearer by more than a tolerance (thin parts
   such as chair legs are often missing from scan meshes). Third rejection check on visible pixels.
5. **Annotations** (:mod:`pipeline.annotate`): poses, boxes, pixel counts, visible fractions.

Outputs: ``RUN/raster/<scene>/drop<NNNN>/f<frame:06d>.npz`` with ``depth`` (H, W) float32 metres (the
nearest object's depth, 0 = no object), ``labels`` (H, W) uint16 (visible instance index + 1, 0 = none)
and ``amodal`` (N, H, ceil(W/8)) uint8 (bit-packed amodal masks, :func:`pipeline.annotate.unpack_masks`);
and ``f<frame:06d>.json`` with the camera and the per-instance annotations (metres). A rejected frame
has only its JSON, with ``"status": "rejected"`` and the reason. ``frame`` is the index into the
Scan's arrays; ``frame_id`` in the JSON is the scan's own number.

Poses without physics: ``scansynth raster RUN --poses poses.json`` (or ``raster.poses = "poses.json"``
in the config) renders chosen poses instead of the simulate stage's drops. Schema (one object, or a
list of them)::

    {"scene": "kitchen",              # Scan.name
     "drop": 0,                       # drop index (output folder drop0000)
     "frames": [0, 5],                # optional: frame indices to render (default: selection / all)
     "instances": [{"obj_id": 1,                       # library id
                    "R_m2w": [[1,0,0],[0,1,0],[0,0,1]], # model-to-world rotation
                    "t_m2w": [0.1, 0.2, 0.0]}]}        # model-to-world translation, metres
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from pipeline import annotate, runfolder
from pipeline.camera import Camera, scaled_intrinsics
from pipeline.config import RasterConfig
from pipeline.errors import InputError
from pipeline.geometry import nearest_rotation
from pipeline.io import atomic_save_npz, atomic_write_json, load_npz, read_json
from pipeline.runfolder import (RASTER_TPATH, REAL_DEPTH_TPATH, SCENE_DEPTH_TPATH, SUMMARY_TPATH, FrameKey,
                                frames_to_render, list_scenes, load_objects, load_placement, load_room_mesh,
                                load_scan, simulated_drops)
from pipeline.scanformats.common import read_depth
from pipeline.stages import Item, Stage, StageContext
from pipeline.tolerances import BOP_VISIB_DELTA_M, POSE_ORTHONORMAL_TOL
from pipeline.types import ObjectModel, Placement, Scan

log = logging.getLogger(__name__)

# Objects are rendered in windows of at most TILE x TILE pixels (one fixed-size GL context): reading
# back and linearising a whole frame per object would cost more than drawing most objects.
TILE = 256


# ---------------------------------------------------------------------------------------------------
# Camera
# ---------------------------------------------------------------------------------------------------

def resize_nearest(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize (depth must not be interpolated across edges)."""
    if image.shape[1] == width and image.shape[0] == height:
        return image
    import cv2

    return cv2.resize(image, (width, height), interpolation=cv2.INTER_NEAREST)


# ---------------------------------------------------------------------------------------------------
# Meshes in the rasterizer
# ---------------------------------------------------------------------------------------------------

def object_mesh_key(obj: ObjectModel) -> str:
    """Rasterizer key of an object model: its id and a digest of its geometry."""
    h = hashlib.blake2b(digest_size=8)
    h.update(np.ascontiguousarray(obj.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(obj.faces, dtype=np.int64).tobytes())
    return f"obj{obj.obj_id}-{h.hexdigest()}"


def ensure_objects(rasterizer, objects: Sequence[ObjectModel]) -> dict[int, str]:
    """Upload the object models the rasterizer does not hold yet; ``{obj_id: mesh key}``."""
    keys = {}
    for obj in objects:
        key = object_mesh_key(obj)
        if not rasterizer.has_mesh(key):
            rasterizer.add_mesh(key, obj.vertices, obj.faces)
        keys[int(obj.obj_id)] = key
    return keys


# ---------------------------------------------------------------------------------------------------
# One frame
# ---------------------------------------------------------------------------------------------------

def render_rect(rasterizer, K: np.ndarray, T_c2w: np.ndarray, instances, rect: tuple[int, int, int, int],
                tile: tuple[int, int], image: tuple[int, int]) -> np.ndarray:
    """Depth of ``instances`` over the pixel rectangle ``rect = (x0, y0, x1, y1)`` of the image plane.

    One render in a ``tile``-sized window when the rectangle fits in it, else image-sized windows
    covering it (the only two viewport sizes used for objects).

    Returns
    -------
    (y1 - y0, x1 - x0) float32, metres, 0 = not covered.
    """
    x0, y0, x1, y1 = rect
    w, h = x1 - x0, y1 - y0
    if w <= tile[0] and h <= tile[1]:
        return rasterizer.render_depth(K, T_c2w, tile[0], tile[1], instances, x0=x0, y0=y0)[:h, :w]
    out = np.zeros((h, w), np.float32)
    W, H = image
    for ty in range(y0, y1, H):
        for tx in range(x0, x1, W):
            d = rasterizer.render_depth(K, T_c2w, W, H, instances, x0=tx, y0=ty)
            out[ty - y0:ty - y0 + H, tx - x0:tx - x0 + W] = d[:min(H, y1 - ty), :min(W, x1 - tx)]
    return out


@dataclass(frozen=True)
class FrameResult:
    """Passes and annotations of one frame of one drop."""

    status: str                     # "ok" | "rejected"
    reason: str                     # why rejected ("" when ok)
    check: str                      # rejection check: "bound" | "amodal" | "visible" | ""
    width: int
    height: int
    K: np.ndarray                   # (3, 3) float64, intrinsics at the render resolution
    T_c2w: np.ndarray               # (4, 4) float64
    instances: list = field(default_factory=list)  # per-instance annotation dicts (pipeline.annotate)
    depth: np.ndarray | None = None    # (H, W) float32, nearest object depth, metres, 0 = none
    labels: np.ndarray | None = None   # (H, W) uint16, visible instance index + 1
    amodal: np.ndarray | None = None   # (N, H, W) bool, silhouettes inside the image
    front: np.ndarray | None = None    # (H, W) uint16, nearest instance index + 1 before room occlusion
    visib: np.ndarray | None = None    # (N, H, W) bool, mask_visib (bop_toolkit's rule on written_depth)
    written_depth: np.ndarray | None = None  # (H, W) float32 metres: the dataset's depth (0 = invalid)
    stats: dict = field(default_factory=dict)  # pixel counts: objects, occluded by room / real depth


def render_frame(rasterizer, *, K: np.ndarray, T_c2w: np.ndarray, width: int, height: int,
                 placement: Placement, mesh_keys: dict[int, str],
                 scene_depth: Callable[[], np.ndarray], real_depth: Callable[[], np.ndarray | None],
                 cfg: RasterConfig, depth_scale: float = 1.0, fill_room: bool = False) -> FrameResult:
    """All raster passes and annotations of one frame.

    Parameters
    ----------
    rasterizer : pipeline.render_gl.MeshRasterizer
        Holds the object meshes under ``mesh_keys``.
    K : (3, 3) float64
        Intrinsics at the render resolution (``width`` x ``height``), OpenCV convention.
    T_c2w : (4, 4) float64
        Camera-to-world, metres.
    placement : Placement
        Instances to render (world poses).
    mesh_keys : dict
        ``obj_id -> rasterizer mesh key``.
    scene_depth : callable
        Returns the room's (H, W) float32 depth (0 = no hit); called only when the frame survives the
        object passes (so the cache is filled only for frames that need it).
    real_depth : callable
        Returns the real sensor depth (H, W) float32 metres at the render resolution (0 = invalid), or
        None when the frame has none. It occludes objects only with ``cfg.real_depth_fusion``; it is
        always part of the written depth.
    cfg : RasterConfig
    depth_scale : float
        ``export.depth_scale`` (mm per PNG unit): visibility is judged on the depth as the dataset
        stores it (:func:`pipeline.annotate.quantize_depth`).
    fill_room : bool
        ``composite.depth_fill == "room"``: the written depth takes the room's depth wherever the sensor
        has none (see :func:`pipeline.annotate.written_depth`).
    """
    K = np.asarray(K, dtype=np.float64)
    T_c2w = np.asarray(T_c2w, dtype=np.float64)
    n = len(placement.obj_ids)
    area = float(width * height)
    R_m2c, t_m2c = Camera(K=K, T_c2w=T_c2w, width=width, height=height).poses_m2c(placement.R_m2w, placement.t_m2w)
    base = dict(width=width, height=height, K=K, T_c2w=T_c2w)

    def reject(check: str, reason: str, **extra) -> FrameResult:
        return FrameResult(status="rejected", reason=reason, check=check, stats=extra, **base)

    windows = [annotate.projected_window(K, R_m2c[i], t_m2c[i],
                                         rasterizer.hull_vertices(mesh_keys[int(placement.obj_ids[i])]),
                                         width, height, rasterizer.znear) for i in range(n)]
    bound = sum(annotate.window_area_in_image(w, width, height) for w in windows) / area
    if bound < cfg.min_visible_area:
        return reject("bound", f"objects project onto at most {bound:.2%} of the image "
                               f"(< raster.min_visible_area = {cfg.min_visible_area:.2%})", bound_share=bound)

    passes = object_passes(rasterizer, K, T_c2w, placement, mesh_keys, windows, width, height)
    crops, rects, amodal = passes.crops, passes.rects, passes.amodal
    depth, front = annotate.compose_front_crops(crops, width, height)
    obj_px = int((front > 0).sum())
    if obj_px / area < cfg.min_visible_area:
        return reject("amodal", f"objects cover {obj_px / area:.2%} of the image before occlusion "
                                f"(< raster.min_visible_area = {cfg.min_visible_area:.2%})", object_px=obj_px)

    room = scene_depth()
    sensor = real_depth()
    real = sensor if cfg.real_depth_fusion else None
    vis = annotate.visible_labels(depth, front, room, real, tol_abs=cfg.fusion_tol_abs,
                                  tol_rel=cfg.fusion_tol_rel)
    labels = vis.labels
    stats = {"object_px": obj_px, "occluded_by_room_px": int(vis.occluded_by_room.sum()),
             "occluded_by_real_px": int(vis.occluded_by_real.sum()), "visible_px": int((labels > 0).sum())}
    if stats["visible_px"] / area < cfg.min_visible_area:
        return reject("visible", f"visible object pixels cover {stats['visible_px'] / area:.2%} of the image "
                                 f"(< raster.min_visible_area = {cfg.min_visible_area:.2%})", **stats)
    # The dataset's depth, then visibility and gt_info by bop_toolkit's rule on that depth as it is
    # stored (quantised to the PNG's units): mask_visib, visib_fract and depth/ agree by construction.
    written = annotate.written_depth(labels, depth, sensor, room, vis.occluded_by_room,
                                     fill_room or sensor is None)
    stored = annotate.quantize_depth(written, depth_scale)
    visib = annotate.bop_visib_masks(crops, (height, width), n, stored, K, BOP_VISIB_DELTA_M)
    inst = annotate.instance_annotations(obj_ids=placement.obj_ids, R_m2c=R_m2c, t_m2c=t_m2c, amodal=amodal,
                                         px_outside=passes.px_outside, box_outside=passes.box_outside,
                                         visib=visib,
                                         valid_depth=stored > 0, visib_threshold=cfg.visib_threshold,
                                         rects=rects)
    for a, R, t in zip(inst, placement.R_m2w, placement.t_m2w):   # the world poses, as simulate placed them
        a["R_m2w"], a["t_m2w"] = np.asarray(R, np.float64).tolist(), np.asarray(t, np.float64).tolist()
    return FrameResult(status="ok", reason="", check="", instances=inst, depth=depth, labels=labels,
                       amodal=amodal, front=front, stats=stats, visib=visib, written_depth=written, **base)


@dataclass(frozen=True)
class ObjectPasses:
    """Each instance rendered alone (:func:`object_passes`): its depth inside the image and its extent
    beyond it."""

    crops: list              # per instance: (depth crop (h, w) float32 m, x0, y0) inside the image, or None
    rects: list              # per instance: its window inside the image (x0, y0, x1, y1) px, or None
    amodal: np.ndarray       # (N, H, W) bool, unoccluded silhouette inside the image
    px_outside: np.ndarray   # (N,) int64, silhouette pixels beyond the image borders
    box_outside: list        # per instance: (x, y, w, h) box of those pixels, or None


def object_passes(rasterizer, K: np.ndarray, T_c2w: np.ndarray, placement: Placement, mesh_keys: dict[int, str],
                  windows: list, width: int, height: int) -> ObjectPasses:
    """Render each instance alone in its projected window (``windows``, from
    :func:`pipeline.annotate.projected_window`): inside the image for its depth and amodal mask, beyond
    the borders only to count its silhouette pixels and their box there (the BOP canvas is larger than
    the image)."""
    n = len(placement.obj_ids)
    tile = (min(TILE, width), min(TILE, height))
    crops: list = [None] * n
    rects: list = [None] * n
    amodal = np.zeros((n, height, width), bool)
    px_outside = np.zeros(n, np.int64)
    box_outside: list = [None] * n
    for i in range(n):
        inside, outside = annotate.split_window(windows[i], width, height)
        T_m2w = annotate.rigid(placement.R_m2w[i], placement.t_m2w[i])
        inst = [(mesh_keys[int(placement.obj_ids[i])], T_m2w)]
        rects[i] = inside
        if inside is not None:
            d = render_rect(rasterizer, K, T_c2w, inst, inside, tile, (width, height))
            crops[i] = (d, inside[0], inside[1])
            amodal[i, inside[1]:inside[3], inside[0]:inside[2]] = d > 0
        for rect in outside:
            hit = render_rect(rasterizer, K, T_c2w, inst, rect, tile, (width, height)) > 0
            px_outside[i] += int(hit.sum())
            box_outside[i] = annotate.union_box(box_outside[i], annotate.bbox_xywh(hit, rect[0], rect[1]))
    return ObjectPasses(crops=crops, rects=rects, amodal=amodal, px_outside=px_outside, box_outside=box_outside)


def frame_doc(result: FrameResult, *, scene: str, drop: int, frame: int, frame_id: int,
              fusion: bool) -> dict:
    """JSON annotation document of a frame (metres, OpenCV camera)."""
    return {"scene": scene, "drop": int(drop), "frame": int(frame), "frame_id": int(frame_id),
            "status": result.status, "reason": result.reason, "check": result.check,
            "width": result.width, "height": result.height, "K": result.K.tolist(),
            "T_c2w": result.T_c2w.tolist(), "real_depth_fusion": bool(fusion),
            "visible_share": (result.stats.get("visible_px", 0) / (result.width * result.height)),
            "stats": result.stats, "instances": result.instances}


def save_frame(stem: str | Path, result: FrameResult, doc: dict) -> None:
    """Write ``<stem>.npz`` (ok frames only) then ``<stem>.json``, each atomically."""
    stem = Path(stem)
    if result.status == "ok":
        atomic_save_npz(stem.with_suffix(".npz"), depth=result.depth, labels=result.labels,
                        amodal=annotate.pack_masks(result.amodal), visib=annotate.pack_masks(result.visib),
                        written_depth=result.written_depth)
    atomic_write_json(stem.with_suffix(".json"), doc)


# ---------------------------------------------------------------------------------------------------
# Poses files
# ---------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class PosesEntry:
    """One placement read from a poses file, with optional frames to render."""

    placement: Placement
    frames: tuple[int, ...] | None


def _matrix(path: Path, where: str, value, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{path}: {where} = {value!r} is not a numeric array of shape {shape}") from None
    if a.shape != shape:
        raise InputError(f"{path}: {where} has shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{path}: {where} contains NaN or inf")
    return a


def load_poses_file(path: str | Path, *, obj_ids: Sequence[int] | None = None,
                    scenes: Sequence[str] | None = None) -> list[PosesEntry]:
    """Read a poses file (schema in the module docstring).

    Parameters
    ----------
    obj_ids, scenes
        When given, every instance's ``obj_id`` and every ``scene`` must be among them.

    Raises
    ------
    InputError
        Unreadable JSON, a missing key, a non-rigid rotation, an unknown object or scene, or a
        (scene, drop) given twice; the message names the file and the entry.
    """
    path = Path(path)
    try:
        raw = read_json(path)
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: cannot read the poses file ({e}); it must be JSON "
                         f"(schema in pipeline/raster.py)") from None
    entries = raw if isinstance(raw, list) else [raw]
    out, seen = [], set()
    for k, e in enumerate(entries):
        where = f"entry {k}"
        if not isinstance(e, dict) or not {"scene", "drop", "instances"} <= set(e):
            raise InputError(f"{path}: {where} must be an object with keys 'scene', 'drop', 'instances' "
                             f"(and optionally 'frames'); got {str(e)[:80]}")
        scene, drop = e["scene"], e["drop"]
        if not isinstance(scene, str) or (scenes is not None and scene not in scenes):
            raise InputError(f"{path}: {where}: scene {scene!r} is not an ingested scene "
                             f"(scenes: {', '.join(scenes or [])})")
        if isinstance(drop, bool) or not isinstance(drop, int) or drop < 0:
            raise InputError(f"{path}: {where}: drop = {drop!r} must be an integer >= 0")
        if (scene, drop) in seen:
            raise InputError(f"{path}: {where}: scene {scene!r} drop {drop} appears twice")
        seen.add((scene, drop))
        ids, Rs, ts = [], [], []
        if not isinstance(e["instances"], list):
            raise InputError(f"{path}: {where}: 'instances' must be a list")
        for j, inst in enumerate(e["instances"]):
            w = f"{where} instance {j}"
            if not isinstance(inst, dict) or not {"obj_id", "R_m2w", "t_m2w"} <= set(inst):
                raise InputError(f"{path}: {w} must have 'obj_id', 'R_m2w' (3x3) and 't_m2w' (3, metres)")
            oid = inst["obj_id"]
            if isinstance(oid, bool) or not isinstance(oid, int) or (obj_ids is not None and oid not in obj_ids):
                raise InputError(f"{path}: {w}: obj_id {oid!r} is not in the object library "
                                 f"(ids: {', '.join(map(str, obj_ids or []))})")
            R = _matrix(path, f"{w} R_m2w", inst["R_m2w"], (3, 3))
            Rn, err, det = nearest_rotation(R)
            if err > POSE_ORTHONORMAL_TOL or abs(det - 1.0) > POSE_ORTHONORMAL_TOL:
                raise InputError(f"{path}: {w}: R_m2w is not a rotation (|R^T R - I| = {err:.2e}, "
                                 f"det = {det:.4f}; up to {POSE_ORTHONORMAL_TOL:g} is re-orthonormalised); give "
                                 f"an orthonormal matrix with det +1")
            if err > 1e-9:   # an annotation's rounding: use the nearest rotation, and say so
                log.warning("%s: %s: R_m2w is orthonormal to %.1e only; using the nearest rotation (SVD)",
                            path, w, err)
                R = Rn
            ids.append(oid)
            Rs.append(R)
            ts.append(_matrix(path, f"{w} t_m2w", inst["t_m2w"], (3,)))
        frames = e.get("frames")
        if frames is not None:
            if not isinstance(frames, list) or not all(isinstance(f, int) and not isinstance(f, bool)
                                                       and f >= 0 for f in frames):
                raise InputError(f"{path}: {where}: 'frames' must be a list of frame indices >= 0")
            frames = tuple(sorted(set(frames)))
        n = len(ids)
        pl = Placement(scene=scene, drop=drop, obj_ids=np.asarray(ids, dtype=np.int32).reshape(n),
                       R_m2w=np.asarray(Rs, dtype=np.float64).reshape(n, 3, 3),
                       t_m2w=np.asarray(ts, dtype=np.float64).reshape(n, 3),
                       at_rest=np.ones(n, bool), max_penetration=0.0, verdict="accepted")
        out.append(PosesEntry(placement=pl, frames=frames))
    return out


def save_poses_file(path: str | Path, placements: Sequence[Placement],
                    frames: Sequence[Sequence[int] | None] | None = None) -> Path:
    """Write placements as a poses file that :func:`load_poses_file` reads back."""
    docs = []
    for k, p in enumerate(placements):
        d = {"scene": p.scene, "drop": int(p.drop),
             "instances": [{"obj_id": int(o), "R_m2w": np.asarray(R).tolist(), "t_m2w": np.asarray(t).tolist()}
                           for o, R, t in zip(p.obj_ids, p.R_m2w, p.t_m2w)]}
        if frames is not None and frames[k] is not None:
            d["frames"] = [int(f) for f in frames[k]]
        docs.append(d)
    return atomic_write_json(path, docs)


# ---------------------------------------------------------------------------------------------------
# Stage
# ---------------------------------------------------------------------------------------------------

def _placements(ctx: StageContext, scene: str, obj_ids: Sequence[int] | None = None
                ) -> list[tuple[Placement, tuple[int, ...] | None]]:
    """Placements to render for ``scene``: from the poses file when configured, else the simulate stage."""
    if ctx.cfg.raster.poses:
        if obj_ids is None:
            obj_ids = [o.obj_id for o in load_objects(ctx.run_dir)]
        entries = load_poses_file(ctx.cfg.raster.poses, obj_ids=obj_ids, scenes=list_scenes(ctx.run_dir))
        return [(e.placement, e.frames) for e in entries if e.placement.scene == scene]
    out = []
    for drop in simulated_drops(ctx.run_dir, scene):
        p = load_placement(ctx.run_dir, scene, drop)
        if p.verdict != "accepted":
            log.info("raster: %s drop %d skipped (simulate verdict %s)", scene, drop, p.verdict)
            continue
        out.append((p, None))
    return out


class _FramePredictor:
    """:func:`pipeline.frame_views.frame_view` of a scene's frames, each frame's sensor depth read once and
    each object's hull computed once (shared by every drop of the scene)."""

    def __init__(self, run_dir: Path, scan: Scan, cfg: RasterConfig):
        from pipeline.frame_views import object_shape

        self.scan, self.cfg = scan, cfg
        self.shapes = {o.obj_id: object_shape(o) for o in load_objects(run_dir)}
        self._sensor: dict[int, object] = {}

    def views(self, placement: Placement, frames: Sequence[int]) -> list:
        from pipeline.frame_views import frame_view, sensor_depth
        from pipeline.render_gl import ZNEAR

        def sensor(f: int):
            if f not in self._sensor:
                self._sensor[f] = sensor_depth(self.scan, f)
            return self._sensor[f]

        out = []
        for f in frames:
            K, w, h = scaled_intrinsics(self.scan.K[f], self.scan.width, self.scan.height, self.cfg.image_scale)
            out.append(frame_view(frame=f, K=K, T_c2w=self.scan.T_c2w[f], width=w, height=h, placement=placement,
                                  shapes=self.shapes, sensor=lambda f=f: sensor(f), znear=ZNEAR,
                                  tol_abs=self.cfg.fusion_tol_abs, tol_rel=self.cfg.fusion_tol_rel,
                                  min_area=self.cfg.min_visible_area))
        return out


def plan(ctx: StageContext) -> list[Item]:
    """One item per (scene, drop, frame): a poses file's frames as given; a simulated drop's kept frames
    that :mod:`pipeline.frame_views` predicts to pass the raster checks (``raster.frames_per_drop`` caps
    them)."""
    from pipeline.frame_views import seeing_frames

    cfg = ctx.cfg.raster
    items = []
    for scene in list_scenes(ctx.run_dir):
        scan = load_scan(ctx.run_dir, scene)
        placements = _placements(ctx, scene)
        if not placements:
            log.warning("raster: scene %s has no accepted drop to render (run simulate, or set raster.poses)",
                        scene)
            continue
        default_frames = frames_to_render(ctx.run_dir, scan)
        predictor = None
        for p, frames in placements:
            if frames is None and not cfg.poses:
                predictor = predictor or _FramePredictor(ctx.run_dir, scan, cfg)
                fr = seeing_frames(predictor.views(p, default_frames), cfg.min_visible_area, cfg.frames_per_drop)
                log.info("raster: %s drop %d: %d of %d kept frames see it", scene, p.drop, len(fr),
                         len(default_frames))
            else:
                fr = list(frames) if frames is not None else default_frames
            bad = [f for f in fr if f >= scan.num_frames]
            if bad:
                raise InputError(f"{ctx.cfg.raster.poses}: scene {scene!r} drop {p.drop}: frames {bad[:5]} "
                                 f"are beyond the scan's {scan.num_frames} frames")
            for f in fr:
                items.append(Item(key=str(FrameKey(scene, int(p.drop), int(f))),
                                  data={"scene": scene, "drop": int(p.drop), "frame": int(f)}))
    return items


def _room_key(scan: Scan) -> str:
    st = Path(scan.mesh_path).stat()
    return f"room:{scan.mesh_path}:{st.st_size}:{st.st_mtime_ns}"


def cached_scene_depth(run_dir: Path, scan: Scan, frame: int, K: np.ndarray, width: int, height: int,
                       rasterizer) -> np.ndarray:
    """The room's depth at ``frame``: read from the cache, or rendered and cached (atomically)."""
    path = runfolder.path(run_dir, SCENE_DEPTH_TPATH, scene=scan.name, frame=frame)
    if path.is_file():
        d = load_npz(path)["depth"]
        if d.shape == (height, width):
            return d
    key = _room_key(scan)
    if not rasterizer.has_mesh(key):
        v, f, _ = load_room_mesh(scan)
        rasterizer.add_mesh(key, v, f)
    d = rasterizer.render_depth(K, scan.T_c2w[frame], width, height, [(key, np.eye(4))])
    atomic_save_npz(path, depth=d)
    return d


def cached_real_depth(run_dir: Path, scan: Scan, frame: int, width: int, height: int) -> np.ndarray | None:
    """The sensor depth of ``frame`` in metres at (width, height), or None when the frame has none.

    Decoding and registering the depth image costs more than the rest of a frame's fusion, and every
    drop needs the same frame's depth: it is decoded once and cached like the room depth.
    """
    if not scan.depth_paths[frame]:
        return None
    path = runfolder.path(run_dir, REAL_DEPTH_TPATH, scene=scan.name, frame=frame)
    if path.is_file():
        d = load_npz(path)["depth"]
        if d.shape == (height, width):
            return d
    d = np.ascontiguousarray(resize_nearest(read_depth(scan, frame), width, height), dtype=np.float32)
    atomic_save_npz(path, depth=d)
    return d


def run_item(ctx: StageContext, item: Item) -> dict:
    from pipeline.render_gl import shared_rasterizer

    cfg = ctx.cfg.raster
    scene, drop, frame = item.data["scene"], item.data["drop"], item.data["frame"]
    scan = load_scan(ctx.run_dir, scene)
    objects = {o.obj_id: o for o in load_objects(ctx.run_dir)}
    placement = next((p for p, _ in _placements(ctx, scene, list(objects)) if p.drop == drop), None)
    if placement is None:
        raise InputError(f"scene {scene!r} drop {drop}: placement not found (was the poses file or the "
                         f"simulate output changed after planning?)")
    missing = sorted(set(int(i) for i in placement.obj_ids) - set(objects))
    if missing:
        raise InputError(f"scene {scene!r} drop {drop}: object ids {missing} are not in the ingested library")
    rasterizer = shared_rasterizer()
    keys = ensure_objects(rasterizer, [objects[i] for i in sorted(set(int(i) for i in placement.obj_ids))])
    K, w, h = scaled_intrinsics(scan.K[frame], scan.width, scan.height, cfg.image_scale)

    res = render_frame(rasterizer, K=K, T_c2w=scan.T_c2w[frame], width=w, height=h, placement=placement,
                       mesh_keys=keys,
                       scene_depth=lambda: cached_scene_depth(ctx.run_dir, scan, frame, K, w, h, rasterizer),
                       real_depth=lambda: cached_real_depth(ctx.run_dir, scan, frame, w, h), cfg=cfg,
                       depth_scale=ctx.cfg.export.depth_scale, fill_room=ctx.cfg.composite.depth_fill == "room")
    doc = frame_doc(res, scene=scene, drop=drop, frame=frame, frame_id=int(scan.frame_ids[frame]),
                    fusion=cfg.real_depth_fusion)
    save_frame(FrameKey(scene, drop, frame).path(ctx.run_dir, RASTER_TPATH), res, doc)
    return {"status": res.status, "check": res.check, "reason": res.reason,
            "instances": len(res.instances), "visible": sum(i["visible"] for i in res.instances)}


def finish(ctx: StageContext, results: dict[str, dict]) -> None:
    """``RUN/raster/summary.json``: frames rendered and rejected, by rejection check."""
    ok = sorted(k for k, r in results.items() if r.get("status") == "ok")
    rejected = {k: r.get("reason", "") for k, r in sorted(results.items()) if r.get("status") == "rejected"}
    by_check: dict[str, int] = {}
    for r in results.values():
        if r.get("status") == "rejected":
            by_check[r.get("check", "")] = by_check.get(r.get("check", ""), 0) + 1
    summary = runfolder.path(ctx.run_dir, SUMMARY_TPATH, stage=ctx.stage)
    if rejected:
        log.warning("raster: %d of %d frame(s) rejected (%s); reasons in %s", len(rejected), len(results),
                    ", ".join(f"{c}: {n}" for c, n in sorted(by_check.items())), summary)
    atomic_write_json(summary,
                      {"frames": len(results), "ok": len(ok), "rejected": len(rejected),
                       "rejected_by_check": by_check, "rejected_frames": rejected})


STAGE = Stage("raster", plan, run_item, finish)
