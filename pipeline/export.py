"""Export stage: the raster outputs (and composites) as a BOP dataset and COCO files.

Layout under ``RUN/export/dataset/``: see :mod:`pipeline.export_bop`; COCO files per BOP scene folder
(``train_pbr/XXXXXX/scene_gt_coco.json``) and merged (``coco_train_pbr.json``); ``scansynth_index.json``
maps each BOP (scene_id, im_id) back to the scan scene, drop and frame, and says where its colour
image came from.

Resumable: one item per image writes its rgb/depth/mask files and a small per-image JSON
(``RUN/export/_frames/<scene_id>/<im_id>.json``), each atomically. ``finish`` merges those into the
dataset's JSON files (numeric key order: same bytes every time). Image numbering is a pure function of
the raster outputs (sorted by scene, drop, frame; each scan scene starts a new BOP scene folder;
``export.chunk_size`` images per folder); the item key names both the source frame and its BOP slot,
so a changed numbering redoes the affected images instead of mixing them up.

Colour images come from ``RUN/composite/<scene>/drop<NNNN>/f<frame:06d>.png`` when the compositor
wrote one; otherwise the real photo is exported (without the inserted objects) and a warning says so.
Depth likewise comes from the compositor's ``f<frame:06d>_depth.npz``, else it is composed here: the
objects' depth where they are visible, the real depth (or the room's rendered depth) elsewhere.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline import annotate, export_bop, export_coco
from pipeline.io import atomic_write_json, read_json
from pipeline.runner import Item, Stage, StageContext

log = logging.getLogger(__name__)

DATASET = "dataset"
SPLIT = "train_pbr"
FRAMES_DIR = "_frames"
MERGED_COCO = "coco_train_pbr.json"
INDEX = "scansynth_index.json"


@dataclass(frozen=True)
class Slot:
    """Where one raster frame goes in the dataset."""

    scene: str
    drop: int
    frame: int
    bop_scene: int
    im_id: int
    global_id: int   # COCO image id in the merged file (0-based position in the dataset)


def raster_frames(run_dir: str | Path) -> list[tuple[str, int, int]]:
    """``(scene, drop, frame)`` of every raster frame with status ok, sorted."""
    root = Path(run_dir) / "raster"
    out = []
    if not root.is_dir():
        return out
    for p in sorted(root.glob("*/drop*/f*.json")):
        if ".tmp-" in p.name:
            continue
        doc = read_json(p)
        if doc.get("status") == "ok" and p.with_suffix(".npz").is_file():
            out.append((doc["scene"], int(doc["drop"]), int(doc["frame"])))
    return sorted(out)


def assign_slots(frames: list[tuple[str, int, int]], chunk_size: int) -> list[Slot]:
    """BOP scene folders and image ids: each scan scene starts a new folder; ``chunk_size`` per folder."""
    slots, bop_scene, k = [], -1, 0
    prev_scene = None
    for gid, (scene, drop, frame) in enumerate(sorted(frames)):
        if scene != prev_scene or k == chunk_size:
            bop_scene += 1
            k = 0
            prev_scene = scene
        slots.append(Slot(scene=scene, drop=drop, frame=frame, bop_scene=bop_scene, im_id=k, global_id=gid))
        k += 1
    return slots


def _key(s: Slot) -> str:
    return f"{s.scene}/drop{s.drop:04d}/f{s.frame:06d}/{s.bop_scene:06d}_{s.im_id:06d}"


def composite_path(run_dir: Path, scene: str, drop: int, frame: int) -> Path:
    """Composite colour image written by the composite stage (same path as pipeline.composite.image_path)."""
    return run_dir / "composite" / scene / f"drop{drop:04d}" / f"f{frame:06d}.png"


def composite_depth_path(run_dir: Path, scene: str, drop: int, frame: int) -> Path:
    """Composite depth (NPZ key ``depth``, metres) written by the composite stage."""
    return run_dir / "composite" / scene / f"drop{drop:04d}" / f"f{frame:06d}_depth.npz"


def plan(ctx: StageContext) -> list[Item]:
    slots = assign_slots(raster_frames(ctx.run_dir), ctx.cfg.export.chunk_size)
    missing = sum(not composite_path(ctx.run_dir, s.scene, s.drop, s.frame).is_file() for s in slots)
    if missing:
        log.warning("export: no composite image for %d of %d frame(s) (the compositor has not run or is not "
                    "built yet): exporting the REAL PHOTO WITHOUT THE INSERTED OBJECTS as rgb for those; "
                    "masks, depth and poses are those of the rendered objects", missing, len(slots))
    return [Item(key=_key(s), data=s.__dict__.copy()) for s in slots]


def scene_dir(run_dir: Path, bop_scene: int) -> Path:
    return run_dir / "export" / DATASET / SPLIT / f"{bop_scene:06d}"


def run_item(ctx: StageContext, item: Item) -> dict:
    import cv2

    from pipeline.ingest import load_scan, read_color, read_depth
    from pipeline.raster import frame_stem, load_frame, resize_nearest, scene_depth_path
    from pipeline.io import load_npz

    s = Slot(**item.data)
    cfg = ctx.cfg.export
    doc, arr = load_frame(frame_stem(ctx.run_dir, s.scene, s.drop, s.frame))
    if arr is None:
        raise RuntimeError(f"raster frame {s.scene}/{s.drop}/{s.frame} is not ok: {doc.get('reason')}")
    w, h = int(doc["width"]), int(doc["height"])
    scan = load_scan(ctx.run_dir, s.scene)
    comp = composite_path(ctx.run_dir, s.scene, s.drop, s.frame)
    if comp.is_file():
        bgr = cv2.imread(str(comp), cv2.IMREAD_COLOR)
        rgb, source = bgr[..., ::-1], "composite"
    else:
        rgb, source = read_color(scan, s.frame), "photo"
    if rgb.shape[:2] != (h, w):
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
    comp_depth = composite_depth_path(ctx.run_dir, s.scene, s.drop, s.frame)
    depth = load_npz(comp_depth)["depth"] if comp_depth.is_file() else None
    if depth is None or depth.shape != (h, w):
        if scan.depth_paths[s.frame]:
            background = resize_nearest(read_depth(scan, s.frame), w, h)
        else:
            background = load_npz(scene_depth_path(ctx.run_dir, s.scene, s.frame))["depth"]
        depth = annotate.compose_depth(arr["labels"], arr["depth"], background)
    sd = scene_dir(ctx.run_dir, s.bop_scene)
    export_bop.write_image_files(sd, s.im_id, rgb=rgb, depth_m=depth, amodal=arr["amodal"], labels=arr["labels"],
                                 ext=cfg.image_format, depth_scale=cfg.depth_scale, jpeg_quality=cfg.jpeg_quality)
    K = np.asarray(doc["K"], dtype=np.float64)
    part = {"scene_camera": export_bop.scene_camera_entry(K, np.asarray(doc["T_c2w"]), cfg.depth_scale),
            "scene_gt": export_bop.scene_gt_entries(doc["instances"]),
            "scene_gt_info": export_bop.scene_gt_info_entries(doc["instances"]),
            "coco": export_coco.frame_annotations(doc["instances"], arr["labels"]) if "coco" in cfg.formats else [],
            "width": w, "height": h, "rgb_source": source, "frame_id": int(doc["frame_id"])}
    atomic_write_json(ctx.stage_dir / FRAMES_DIR / f"{s.bop_scene:06d}" / f"{s.im_id:06d}.json", part)
    return {"rgb_source": source, "instances": len(doc["instances"])}


def finish(ctx: StageContext, results: dict[str, dict]) -> None:
    """Merge the per-image parts into the BOP JSON files and COCO files; write models and camera.json."""
    from pipeline.ingest import load_objects

    cfg = ctx.cfg.export
    slots = assign_slots(raster_frames(ctx.run_dir), cfg.chunk_size)
    root = ctx.stage_dir / DATASET
    parts: dict[int, dict[int, dict]] = {}
    missing = []
    for s in slots:
        p = ctx.stage_dir / FRAMES_DIR / f"{s.bop_scene:06d}" / f"{s.im_id:06d}.json"
        if p.is_file():
            parts.setdefault(s.bop_scene, {})[s.im_id] = read_json(p)
        else:
            missing.append(_key(s))
    if missing:
        log.error("export: %d image(s) not exported (failed items), left out of the JSON files: %s",
                  len(missing), ", ".join(missing[:5]))
    if not slots:
        log.warning("export: no rendered frame to export (raster produced none)")
        return
    objects = load_objects(ctx.run_dir)
    cats = export_coco.categories(objects)
    ext = cfg.image_format
    merged_images, merged_anns, index = [], [], []
    by_slot = {(s.bop_scene, s.im_id): s for s in slots}
    for bop_scene in sorted(parts):
        sp = parts[bop_scene]
        sd = scene_dir(ctx.run_dir, bop_scene)
        if "bop" in cfg.formats:
            export_bop.write_scene_files(sd, {i: sp[i]["scene_camera"] for i in sp},
                                         {i: sp[i]["scene_gt"] for i in sp},
                                         {i: sp[i]["scene_gt_info"] for i in sp})
        images, anns = [], []
        for im_id in sorted(sp):
            s = by_slot[(bop_scene, im_id)]
            part = sp[im_id]
            images.append(export_coco.image_entry(im_id, f"rgb/{im_id:06d}.{ext}", part["width"], part["height"]))
            anns += [dict(a, image_id=im_id) for a in part["coco"]]
            merged_images.append(export_coco.image_entry(
                s.global_id, f"{SPLIT}/{bop_scene:06d}/rgb/{im_id:06d}.{ext}", part["width"], part["height"]))
            merged_anns += [dict(a, image_id=s.global_id) for a in part["coco"]]
            index.append({"scene_id": bop_scene, "im_id": im_id, "scene": s.scene, "drop": s.drop,
                          "frame": s.frame, "frame_id": part["frame_id"], "rgb_source": part["rgb_source"]})
        if "coco" in cfg.formats:
            atomic_write_json(sd / "scene_gt_coco.json",
                              export_coco.coco_document(images, anns, cats, f"scansynth {SPLIT}/{bop_scene:06d}"),
                              indent=None)
    if "coco" in cfg.formats:
        atomic_write_json(root / MERGED_COCO,
                          export_coco.coco_document(merged_images, merged_anns, cats, f"scansynth {SPLIT}"),
                          indent=None)
    if "bop" in cfg.formats:
        first = parts[min(parts)][min(parts[min(parts)])]
        K = np.asarray(first["scene_camera"]["cam_K"], dtype=np.float64).reshape(3, 3)
        atomic_write_json(root / "camera.json", export_bop.camera_json(K, first["width"], first["height"],
                                                                        cfg.depth_scale))
        export_bop.write_models(root, objects)
    atomic_write_json(root / INDEX, {"images": index})
    photos = sum(1 for e in index if e["rgb_source"] == "photo")
    if photos:
        log.warning("export: %d of %d rgb image(s) are the real photo without the inserted objects "
                    "(no composite yet); see %s", photos, len(index), root / INDEX)


STAGE = Stage("export", plan, run_item, finish)
