"""COCO instance-segmentation writer (RLE masks through pycocotools).

One ``scene_gt_coco.json`` per BOP scene folder (``file_name`` relative to that folder, e.g.
``rgb/000000.jpg``, as bop_toolkit's ``calc_gt_coco.py`` writes it) and one merged file for the whole
dataset (``file_name`` relative to the dataset root). Categories are the object library (``id`` =
``obj_id``). An annotation is written for every instance with at least one visible pixel; instances
below ``raster.visib_threshold`` carry ``"ignore": true`` (and stay ``iscrowd: 0``), so evaluation
can skip barely visible objects without losing them.
"""

from __future__ import annotations

import numpy as np

from pipeline.types import ObjectModel


def rle(mask: np.ndarray) -> dict:
    """COCO RLE of a (H, W) bool mask: ``{"size": [H, W], "counts": str}``."""
    from pycocotools import mask as mask_util

    r = mask_util.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"size": [int(r["size"][0]), int(r["size"][1])], "counts": r["counts"].decode("ascii")}


def categories(objects: list[ObjectModel]) -> list[dict]:
    """COCO categories from the object library, by ``obj_id``."""
    return [{"id": int(o.obj_id), "name": o.name, "supercategory": "object"}
            for o in sorted(objects, key=lambda o: o.obj_id)]


def image_entry(image_id: int, file_name: str, width: int, height: int) -> dict:
    return {"id": int(image_id), "file_name": file_name, "width": int(width), "height": int(height)}


def frame_annotations(instances: list[dict], labels: np.ndarray) -> list[dict]:
    """COCO annotations of one image, without ``id``/``image_id`` (assigned when files are merged).

    Parameters
    ----------
    instances : list of dict
        Raster annotations (:func:`pipeline.annotate.instance_annotations`).
    labels : (H, W) uint16
        Visible instance labels (index + 1).
    """
    from pycocotools import mask as mask_util

    out = []
    for a in instances:
        if a["px_count_visib"] <= 0:
            continue
        m = labels == a["inst_id"] + 1
        seg = rle(m)
        x, y, w, h = a["bbox_visib"]
        area = int(mask_util.area({"size": seg["size"], "counts": seg["counts"].encode("ascii")}))
        out.append({"category_id": int(a["obj_id"]), "segmentation": seg, "area": area,
                    "bbox": [float(x), float(y), float(w), float(h)], "iscrowd": 0,
                    "ignore": not bool(a["visible"]), "inst_id": int(a["inst_id"]),
                    "visib_fract": round(float(a["visib_fract"]), 6)})
    return out


def coco_document(images: list[dict], annotations: list[dict], cats: list[dict], description: str) -> dict:
    """A COCO dataset document; annotations get ids 1.. in the given order (COCO ids start at 1)."""
    anns = [dict(a, id=i + 1) for i, a in enumerate(annotations)]
    return {"info": {"description": description, "version": "1.0"}, "licenses": [],
            "images": images, "annotations": anns, "categories": cats}
