"""YOLO (Ultralytics) writer: ``RUN/export/dataset/yolo/``.

::

    yolo/data.yaml                       train/val folders, nc, names (class index -> object name)
    yolo/images/{train,val}/{scene_id:06d}_{im_id:06d}.jpg|png    the BOP rgb image (hard link or copy)
    yolo/labels/{train,val}/{scene_id:06d}_{im_id:06d}.txt        one line per visible instance

Class index = position of the object in the library sorted by ``obj_id`` (``data.yaml`` lists the
``obj_id`` of each in a comment). ``export.yolo_task`` picks the label lines:

``detect``
    ``class cx cy w h``, normalised to [0, 1] by the image size: the **modal** box (of ``mask_visib``,
    the box of what can be seen, which is what a detector is trained to find), equal to the ``bbox`` of
    ``scene_gt_coco_modal.json``: ``cx = (x + w / 2) / W`` with ``w`` the pixel extent.
``segment``
    ``class x1 y1 x2 y2 ...``: the outline of ``mask_visib`` as Ultralytics'
    ``convert_segment_masks_to_yolo_seg`` makes it (``cv2.findContours``, external outline, vertices at
    boundary pixel centres, divided by the image size). An instance in several pieces (split by an
    occluder) is one polygon: the pieces joined by zero-width bridges (as Ultralytics' ``convert_coco``
    merges multi-part COCO masks); holes are outlined the same way and stay holes under the even-odd
    fill that Ultralytics and supervision use (``cv2.fillPoly``).

Instances without visible pixels get no line; an image with none gets an empty label file (a
background image for Ultralytics). The train/val split is by drop (``export.yolo_split = "drop"``) or
by scan scene, never by frame: neighbouring frames of one drop are near-duplicates and would leak across
the split. Which units go to val is drawn from ``run.seed`` (the share ``export.yolo_val_fraction``,
rounded, at least one unit when the share is above 0 and there are two or more units). ``data.yaml``
has no ``path`` key, so Ultralytics resolves ``images/...`` against the folder of ``data.yaml``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from pipeline.io import TMP_MARK, atomic_write_bytes
from pipeline.seeding import item_rng
from pipeline.types import ObjectModel

YOLO_DIR = "yolo"
SPLITS = ("train", "val")


def _fmt(v: float) -> str:
    return f"{min(max(float(v), 0.0), 1.0):.6f}"


def box_line(cls: int, box: list[int], width: int, height: int) -> str:
    """``class cx cy w h`` of a COCO ``[x, y, w, h]`` pixel box (``w, h`` = pixel extent), normalised."""
    x, y, w, h = (float(v) for v in box)
    return " ".join([str(int(cls)), _fmt((x + w / 2) / width), _fmt((y + h / 2) / height),
                     _fmt(w / width), _fmt(h / height)])


def polygon_line(cls: int, polygon: list[list[int]], width: int, height: int) -> str:
    """``class x1 y1 x2 y2 ...`` of a pixel polygon (vertices at pixel centres), normalised."""
    coords = []
    for x, y in polygon:
        coords += [_fmt(x / width), _fmt(y / height)]
    return " ".join([str(int(cls))] + coords)


def _join(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """One closed outline through ``a`` and ``b``: a zero-width bridge between their closest points."""
    d = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    i, j = np.unravel_index(int(np.argmin(d)), d.shape)
    a_roll = np.roll(a, -i, axis=0)
    b_roll = np.roll(b, -j, axis=0)
    return np.concatenate([a_roll, a_roll[:1], b_roll, b_roll[:1]])


def mask_polygon(mask: np.ndarray) -> list[list[int]]:
    """Outline of a non-empty (H, W) bool mask as one polygon, ``[[x, y], ...]`` in pixel-centre coordinates.

    All contours of ``cv2.findContours`` (``RETR_CCOMP``: outer outlines and the outlines of holes,
    ``CHAIN_APPROX_SIMPLE``), largest first, joined into one by zero-width bridges: filled with the
    even-odd rule (``cv2.fillPoly``, as Ultralytics and supervision rasterise polygons) the holes stay
    holes, and pieces thinner than three vertices (a one-pixel line) are still drawn.
    """
    import cv2

    contours, _ = cv2.findContours(np.ascontiguousarray(mask, dtype=np.uint8), cv2.RETR_CCOMP,
                                   cv2.CHAIN_APPROX_SIMPLE)
    parts = [c.reshape(-1, 2).astype(np.int64) for c in contours if len(c)]
    # deterministic order: largest enclosed area first, then longest, then by first vertex
    parts.sort(key=lambda c: (-abs(float(cv2.contourArea(c.astype(np.float32)))) if len(c) >= 3 else 0.0,
                              -len(c), c[0].tolist()))
    poly = parts[0]
    for p in parts[1:]:
        poly = _join(poly, p)
    if len(poly) < 3:   # one pixel or a two-pixel line: repeat vertices to make a valid polygon line
        poly = np.concatenate([poly, poly[::-1], poly])[:max(3, len(poly))]
    return poly.tolist()


def frame_labels(instances: list[dict], visib: np.ndarray) -> list[dict]:
    """Per visible instance: ``obj_id``, modal ``bbox`` (COCO pixel box) and visible-mask ``polygon``."""
    from pipeline.export_coco import bbox

    out = []
    for g, a in enumerate(instances):
        m = visib[g]
        if not m.any():
            continue
        out.append({"obj_id": int(a["obj_id"]), "bbox": bbox(m), "polygon": mask_polygon(m)})
    return out


def split_units(units: list[tuple], val_fraction: float, seed: int) -> set[tuple]:
    """The units (drops or scenes) that go to val: a seeded draw of ``round(val_fraction * n)`` of them."""
    units = sorted(set(units))
    n = len(units)
    k = int(round(val_fraction * n))
    if val_fraction > 0 and n >= 2:
        k = max(k, 1)
    k = min(k, n)
    order = item_rng(seed, "export", "yolo-split").permutation(n)
    return {units[i] for i in sorted(order[:k].tolist())}


def data_yaml(objects: list[ObjectModel]) -> str:
    """``data.yaml``: splits and class names (JSON-quoted, valid YAML), class index -> obj_id in comments."""
    objs = sorted(objects, key=lambda o: o.obj_id)
    lines = ["# scansynth YOLO export (Ultralytics layout); no 'path': folders are relative to this file",
             "train: images/train", "val: images/val", f"nc: {len(objs)}", "names:"]
    lines += [f"  {i}: {json.dumps(o.name)}  # obj_id {o.obj_id}" for i, o in enumerate(objs)]
    return "\n".join(lines) + "\n"


def class_index(objects: list[ObjectModel]) -> dict[int, int]:
    """obj_id -> YOLO class index (position in the library sorted by obj_id)."""
    return {int(o.obj_id): i for i, o in enumerate(sorted(objects, key=lambda o: o.obj_id))}


def link_or_copy(src: Path, dst: Path) -> None:
    """``dst`` = the bytes of ``src``: a hard link where the file system allows it, else a copy (atomic)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f"{dst.name}{TMP_MARK}{os.getpid()}")   # the atomic writers' temp name
    try:
        if tmp.exists():
            tmp.unlink()
        os.link(src, tmp)
        os.replace(tmp, dst)
    except OSError:
        if tmp.exists():
            tmp.unlink()
        atomic_write_bytes(dst, Path(src).read_bytes())


def write_dataset(root: Path, images: list[dict], objects: list[ObjectModel], task: str) -> dict:
    """Write ``root/yolo``: ``images`` = dicts with ``name``, ``split``, ``rgb`` (source path), ``width``,
    ``height`` and ``labels`` (:func:`frame_labels`). Files of earlier exports that are not in ``images``
    are removed, so the folder holds this export only. Returns counts per split."""
    out = Path(root) / YOLO_DIR
    cls = class_index(objects)
    keep: set[Path] = set()
    counts = {s: 0 for s in SPLITS}
    for im in images:
        img_dst = out / "images" / im["split"] / f"{im['name']}{Path(im['rgb']).suffix}"
        lab_dst = out / "labels" / im["split"] / f"{im['name']}.txt"
        link_or_copy(Path(im["rgb"]), img_dst)
        w, h = int(im["width"]), int(im["height"])
        if task == "segment":
            lines = [polygon_line(cls[a["obj_id"]], a["polygon"], w, h) for a in im["labels"]]
        else:
            lines = [box_line(cls[a["obj_id"]], a["bbox"], w, h) for a in im["labels"]]
        atomic_write_bytes(lab_dst, "".join(line + "\n" for line in lines).encode("ascii"))
        keep |= {img_dst, lab_dst}
        counts[im["split"]] += 1
    for sub in ("images", "labels"):
        for s in SPLITS:
            d = out / sub / s
            d.mkdir(parents=True, exist_ok=True)
            for p in d.iterdir():
                if p.is_file() and p not in keep:
                    p.unlink()
    atomic_write_bytes(out / "data.yaml", data_yaml(objects).encode("utf-8"))
    return counts
