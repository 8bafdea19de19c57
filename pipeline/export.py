"""Export stage: the raster outputs and composites as a BOP dataset, COCO files and a YOLO dataset.

Layout under ``RUN/export/dataset/``: see :mod:`pipeline.export_bop`; COCO files per BOP scene folder
(``train_pbr/XXXXXX/scene_gt_coco.json`` with amodal boxes, ``scene_gt_coco_modal.json`` with modal
boxes, see :mod:`pipeline.export_coco`) and merged (``coco_train_pbr.json``, ``coco_train_pbr_modal.json``);
``yolo/`` (:mod:`pipeline.export_yolo`) when ``export.formats`` has "yolo"; ``scansynth_index.json``
maps each BOP (scene_id, im_id) back to the scan scene, drop and frame.

Resumable: one item per image writes its rgb/depth/mask files and a small per-image JSON
(``RUN/export/_frames/<scene_id>/<im_id>.json``, naming its item key), each atomically. ``finish``
merges those into the dataset's JSON files (numeric key order: same bytes every time). Image numbering
is a pure function of the raster and composite outputs (sorted by scene, drop, frame; each scan scene
starts a new BOP scene folder; ``export.chunk_size`` images per folder); the item key names both the
source frame and its BOP slot, so a changed numbering redoes the affected images instead of mixing them
up, and ``finish`` removes image files of slots that are no longer in the dataset.

Colour images come from ``RUN/composite/<scene>/drop<NNNN>/f<frame:06d>.png``. A frame without one (its
composite item failed, or the compositor has not run) is **left out of every format**: the photo without
the inserted objects, with their annotations, would be a mislabelled training sample. Left-out frames
are listed with the reason in ``RUN/export/summary.json`` (and so in ``run.json``'s ``rejected``) and
counted in the log. Depth comes from the compositor's ``f<frame:06d>_depth.npz``, else from the raster
stage's ``written_depth`` (the same array: raster composes it and judges ``mask_visib`` on it, see
:func:`pipeline.annotate.written_depth`); ``mask_visib`` is raster's ``visib`` (bop_toolkit's rule).

The dataset folder holds one run's export only: ``dataset/scansynth_run.json`` names the run (a hash of
its config); an export into a dataset folder with another run's marker, or with files and no marker,
stops with an error naming the folder before anything is written.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline import export_bop, export_coco, export_yolo
from pipeline.bop_layout import (CAMERA_PATH, IMAGE_DIRS, RGB_TPATH, SCENE_GT_COCO_MODAL_PATH, SCENE_GT_COCO_PATH,
                                 SCENE_TPATH, SPLIT)
from pipeline.errors import InputError
from pipeline.io import atomic_write_json, dumps_json, read_json
from pipeline.runfolder import (COMPOSITE_DEPTH_TPATH, COMPOSITE_TPATH, DATASET_DIR, SUMMARY_TPATH, FrameKey,
                                load_objects, load_raster_frame, path, raster_frames)
from pipeline.stages import Item, Stage, StageContext

log = logging.getLogger(__name__)

DATASET = Path(DATASET_DIR).name   # under RUN/export
FRAMES_DIR = "_frames"
MERGED_COCO = "coco_train_pbr.json"
MERGED_COCO_MODAL = "coco_train_pbr_modal.json"
MARKER = "scansynth_run.json"
NO_COMPOSITE = "no composite image (its composite item failed or the composite stage has not run)"
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

    @property
    def key(self) -> FrameKey:
        return FrameKey(self.scene, self.drop, self.frame)


def assign_slots(frames: list[FrameKey], chunk_size: int) -> list[Slot]:
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
    return f"{s.key}/{s.bop_scene:06d}_{s.im_id:06d}"


def run_id(cfg) -> str:
    """Identity of a run: SHA-256 of its config without the execution-only keys (workers, executor...)."""
    import hashlib

    from pipeline.config import config_to_dict

    d = config_to_dict(cfg)
    d["run"] = {k: v for k, v in d.get("run", {}).items() if k not in ("workers", "executor", "ray_address",
                                                                          "progress")}
    return hashlib.sha256(dumps_json(d, indent=None).encode("utf-8")).hexdigest()[:16]


def claim_dataset(ctx: StageContext) -> None:
    """Write the dataset folder's run marker, or stop if the folder holds another run's files."""
    root = ctx.stage_dir / DATASET
    marker = root / MARKER
    rid = run_id(ctx.cfg)
    if marker.is_file():
        try:
            other = read_json(marker).get("run")
        except (OSError, ValueError, AttributeError):
            other = None
        if other != rid:
            raise InputError(f"{root} holds another run's dataset ({MARKER} names run {other!r}, this run is "
                             f"{rid!r}); move that folder away or export into a new run folder")
        return
    if root.is_dir() and any(root.iterdir()) and not (ctx.stage_dir / FRAMES_DIR).is_dir():
        # (files with this run's per-image parts beside them: an export of this run from before the marker)
        raise InputError(f"{root} holds files that this run's export did not write (no {MARKER}); move them "
                         f"away or export into a new run folder")
    atomic_write_json(marker, {"run": rid})


def exported_frames(run_dir: Path) -> tuple[list[FrameKey], dict[str, str]]:
    """Raster frames that have a composite image, and the left-out ones ``{"scene/dropNNNN/fNNNNNN": reason}``."""
    keep, left_out = [], {}
    for k in raster_frames(run_dir):
        if k.path(run_dir, COMPOSITE_TPATH).is_file():
            keep.append(k)
        else:
            left_out[str(k)] = NO_COMPOSITE
    return keep, left_out


def plan(ctx: StageContext) -> list[Item]:
    claim_dataset(ctx)
    frames, left_out = exported_frames(ctx.run_dir)
    if left_out:
        log.warning("export: %d of %d frame(s) have no composite image (composite item failed or not run) and "
                    "are LEFT OUT of the dataset (listed in %s): %s", len(left_out), len(frames) + len(left_out),
                    summary_path(ctx), ", ".join(list(left_out)[:5]))
    slots = assign_slots(frames, ctx.cfg.export.chunk_size)
    return [Item(key=_key(s), data=s.__dict__.copy()) for s in slots]


def summary_path(ctx: StageContext) -> Path:
    return path(ctx.run_dir, SUMMARY_TPATH, stage=ctx.stage)


def scene_dir(run_dir: Path, bop_scene: int) -> Path:
    return Path(run_dir) / DATASET_DIR / SCENE_TPATH.format(scene_id=bop_scene)


def run_item(ctx: StageContext, item: Item) -> dict:
    import cv2

    from pipeline.io import load_npz

    s = Slot(**item.data)
    cfg = ctx.cfg.export
    raster = load_raster_frame(ctx.run_dir, s.key)
    if raster.status != "ok":
        raise RuntimeError(f"raster frame {s.key} is not ok: {raster.reason}")
    doc, arr = raster.doc, raster.arrays()
    w, h = raster.camera.width, raster.camera.height
    comp = s.key.path(ctx.run_dir, COMPOSITE_TPATH)
    if not comp.is_file():
        raise RuntimeError(f"{comp} is missing (it was there when the export was planned); run the export again")
    bgr = cv2.imread(str(comp), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputError(f"{comp}: not a readable image; delete it and run the composite stage again")
    rgb, source = bgr[..., ::-1], "composite"
    if rgb.shape[:2] != (h, w):
        rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
    comp_depth = s.key.path(ctx.run_dir, COMPOSITE_DEPTH_TPATH)
    depth = load_npz(comp_depth)["depth"] if comp_depth.is_file() else None
    if depth is None or depth.shape != (h, w):
        depth = arr["written_depth"]   # the depth raster judged visibility on (the compositor writes it too)
    sd = scene_dir(ctx.run_dir, s.bop_scene)
    export_bop.write_image_files(sd, s.im_id, rgb=rgb, depth_m=depth, amodal=arr["amodal"], visib=arr["visib"],
                                 ext=cfg.image_format, depth_scale=cfg.depth_scale, jpeg_quality=cfg.jpeg_quality)
    part = {"scene_camera": export_bop.scene_camera_entry(raster.camera.K, raster.camera.T_c2w, cfg.depth_scale),
            "scene_gt": export_bop.scene_gt_entries(doc["instances"]),
            "scene_gt_info": export_bop.scene_gt_info_entries(doc["instances"]),
            "coco": (export_coco.frame_annotations(doc["instances"], arr["visib"], arr["amodal"])
                     if "coco" in cfg.formats else []),
            "yolo": export_yolo.frame_labels(doc["instances"], arr["visib"]) if "yolo" in cfg.formats else [],
            "width": w, "height": h, "rgb_source": source, "frame_id": int(doc["frame_id"]), "key": item.key}
    atomic_write_json(ctx.stage_dir / FRAMES_DIR / f"{s.bop_scene:06d}" / f"{s.im_id:06d}.json", part)
    return {"rgb_source": source, "instances": len(doc["instances"])}


def remove_stale_images(ctx: StageContext, parts: dict[int, dict[int, dict]]) -> int:
    """Delete image files (rgb, depth, mask, mask_visib) and scene folders of slots not in ``parts``.

    They are left from an earlier export of this run whose numbering differed (more frames, or a frame's
    composite that has since failed): without this they would sit in the dataset, unlisted, beside the
    images that are. Returns the number of files removed.
    """
    import re
    import shutil

    split = ctx.stage_dir / DATASET / SPLIT
    if not split.is_dir():
        return 0
    n = 0
    rx = re.compile(r"(\d{6})(?:_\d{6})?\.(?:png|jpg)")
    for sd in sorted(split.iterdir()):
        if not (sd.is_dir() and re.fullmatch(r"\d{6}", sd.name)):
            continue
        keep = parts.get(int(sd.name))
        if keep is None:
            n += sum(1 for p in sd.rglob("*") if p.is_file())
            shutil.rmtree(sd)
            continue
        for sub in IMAGE_DIRS:
            for p in sorted((sd / sub).glob("*")) if (sd / sub).is_dir() else []:
                m = rx.fullmatch(p.name)
                if m and int(m.group(1)) not in keep:
                    p.unlink()
                    n += 1
    return n


def finish(ctx: StageContext, results: dict[str, dict]) -> None:
    """Merge the per-image parts into the BOP, COCO and YOLO files; write models, camera.json, summary.json."""
    cfg = ctx.cfg.export
    frames, left_out = exported_frames(ctx.run_dir)
    slots = assign_slots(frames, cfg.chunk_size)
    root = ctx.stage_dir / DATASET
    parts: dict[int, dict[int, dict]] = {}
    failed = []
    for s in slots:
        p = ctx.stage_dir / FRAMES_DIR / f"{s.bop_scene:06d}" / f"{s.im_id:06d}.json"
        part = read_json(p) if p.is_file() else None
        if part is not None and part.get("key") == _key(s):   # a part of an older numbering is not this slot's
            parts.setdefault(s.bop_scene, {})[s.im_id] = part
        else:
            failed.append(_key(s))
            left_out[str(s.key)] = "export item failed"
    if failed:
        log.error("export: %d image(s) not exported (failed items), left out of the dataset: %s",
                  len(failed), ", ".join(failed[:5]))
    removed = remove_stale_images(ctx, parts)
    if removed:
        log.warning("export: removed %d image file(s) of an earlier export of this run that are no longer in "
                    "the dataset", removed)
    n_images = sum(len(v) for v in parts.values())
    atomic_write_json(summary_path(ctx), {"images": n_images, "left_out": dict(sorted(left_out.items()))})
    if left_out:
        log.warning("export: %d frame(s) left out of the dataset, %d exported; reasons in %s",
                    len(left_out), n_images, summary_path(ctx))
    if not parts:
        log.warning("export: no frame to export (raster produced none, or none has a composite image)")
        return
    objects = load_objects(ctx.run_dir)
    cats = export_coco.categories(objects)
    ext = cfg.image_format
    merged_images, merged_anns, index, yolo_images = [], [], [], []
    by_slot = {(s.bop_scene, s.im_id): s for s in slots}
    if "yolo" in cfg.formats:
        unit = (lambda s: (s.scene,)) if cfg.yolo_split == "scene" else (lambda s: (s.scene, s.drop))
        val_units = export_yolo.split_units([unit(by_slot[(b, i)]) for b in parts for i in parts[b]],
                                            cfg.yolo_val_fraction, ctx.cfg.run.seed)
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
            rgb = RGB_TPATH.format(im_id=im_id, ext=ext)   # relative to the scene folder
            images.append(export_coco.image_entry(im_id, rgb, part["width"], part["height"]))
            anns += [dict(a, image_id=im_id) for a in part["coco"]]
            merged_images.append(export_coco.image_entry(
                s.global_id, f"{SCENE_TPATH.format(scene_id=bop_scene)}/{rgb}", part["width"], part["height"]))
            merged_anns += [dict(a, image_id=s.global_id) for a in part["coco"]]
            index.append({"scene_id": bop_scene, "im_id": im_id, "scene": s.scene, "drop": s.drop,
                          "frame": s.frame, "frame_id": part["frame_id"], "rgb_source": part["rgb_source"]})
            if "yolo" in cfg.formats:
                yolo_images.append({"name": f"{bop_scene:06d}_{im_id:06d}",
                                    "split": "val" if unit(s) in val_units else "train",
                                    "rgb": sd / rgb, "width": part["width"],
                                    "height": part["height"], "labels": part["yolo"]})
        if "coco" in cfg.formats:
            for name, box in ((SCENE_GT_COCO_PATH, "amodal"), (SCENE_GT_COCO_MODAL_PATH, "modal")):
                doc = export_coco.coco_document(images, [export_coco.variant(a, box) for a in anns], cats,
                                                f"scansynth {SCENE_TPATH.format(scene_id=bop_scene)} ({box} boxes)")
                atomic_write_json(sd / name, doc, indent=None)
    if "coco" in cfg.formats:
        for name, box in ((MERGED_COCO, "amodal"), (MERGED_COCO_MODAL, "modal")):
            doc = export_coco.coco_document(merged_images, [export_coco.variant(a, box) for a in merged_anns],
                                            cats, f"scansynth {SPLIT} ({box} boxes)")
            atomic_write_json(root / name, doc, indent=None)
    if "yolo" in cfg.formats:
        counts = export_yolo.write_dataset(root, yolo_images, objects, cfg.yolo_task)
        log.info("export: YOLO dataset (%s) with %d train and %d val image(s) in %s", cfg.yolo_task,
                 counts["train"], counts["val"], root / export_yolo.YOLO_DIR)
    if "bop" in cfg.formats:
        first = parts[min(parts)][min(parts[min(parts)])]
        K = np.asarray(first["scene_camera"]["cam_K"], dtype=np.float64).reshape(3, 3)
        atomic_write_json(root / CAMERA_PATH, export_bop.camera_json(K, first["width"], first["height"],
                                                                        cfg.depth_scale))
        export_bop.write_models(root, objects)
    atomic_write_json(root / INDEX, {"images": index})


STAGE = Stage("export", plan, run_item, finish)
