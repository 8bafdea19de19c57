"""COCO instance-segmentation writer, as bop_toolkit's ``scripts/calc_gt_coco.py`` writes it.

Per BOP scene folder, two files with the same images and annotations, differing only in ``bbox``:

* ``scene_gt_coco.json``: **amodal** boxes, from the object's full mask (``mask/``) inside the image
  (bop_toolkit's default ``bbox_type = "amodal"``);
* ``scene_gt_coco_modal.json``: **modal** boxes, from the visible mask (``mask_visib/``).

``file_name`` is relative to the scene folder (``rgb/000000.jpg``), image ``id`` = BOP ``im_id``, and
annotation ids count 1.. per file in (image, gt_id) order, as bop_toolkit numbers them. The merged
files for the whole dataset (``coco_train_pbr.json``, ``coco_train_pbr_modal.json``) name images
relative to the dataset root and number them 0.. in dataset order (the index in
``scansynth_index.json``).

Every annotation is made as bop_toolkit's ``pycoco_utils.create_annotation_info`` makes it:
``segmentation`` = the visible mask as an uncompressed RLE (``binary_mask_to_rle``: column-major run
lengths, starting with the background run), ``area`` = visible pixel count, ``bbox`` = ``[x, y, w, h]``
with ``w, h`` the pixel extent (``bbox_from_binary_mask``), ``iscrowd`` 0, ``width``/``height`` of the
mask, and ``"ignore": visib_fract < 0.1`` (bop_toolkit's threshold, independent of
``raster.visib_threshold``). An instance with no visible pixel gets no annotation. Two extra keys name
the BOP instance: ``inst_id`` (the ``gt_id`` of ``mask_visib/{im_id}_{gt_id}.png``) and ``visib_fract``.
Categories are the object library (``id`` = ``obj_id``, ``name`` = the object's name). Image entries
leave out bop_toolkit's ``date_captured`` (a timestamp: the same seed gives the same bytes).
"""

from __future__ import annotations

import numpy as np

from pipeline.types import ObjectModel

IGNORE_VISIB_FRACT = 0.1   # bop_toolkit calc_gt_coco.py: "ignore flag for objects smaller than 10% visible"


def rle(mask: np.ndarray) -> dict:
    """Uncompressed COCO RLE of a (H, W) bool mask, as bop_toolkit's ``binary_mask_to_rle``.

    ``{"counts": [run lengths], "size": [H, W]}``; runs go down the columns (Fortran order) and start
    with a background run (0 when the first pixel is set).
    """
    m = np.asarray(mask, dtype=bool)
    flat = m.ravel(order="F")
    counts: list[int] = []
    if flat.size and flat[0]:
        counts.append(0)
    if flat.size:
        change = np.flatnonzero(np.concatenate(([True], flat[:-1] != flat[1:], [True])))
        counts.extend(int(c) for c in np.diff(change))
    return {"counts": counts, "size": [int(m.shape[0]), int(m.shape[1])]}


def bbox(mask: np.ndarray) -> list[int]:
    """``[x, y, w, h]`` of a non-empty mask, ``w, h`` = pixel extent (bop_toolkit ``bbox_from_binary_mask``)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    return [int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)]


def categories(objects: list[ObjectModel]) -> list[dict]:
    """COCO categories from the object library, by ``obj_id``."""
    return [{"id": int(o.obj_id), "name": o.name, "supercategory": "object"}
            for o in sorted(objects, key=lambda o: o.obj_id)]


def image_entry(image_id: int, file_name: str, width: int, height: int) -> dict:
    """An image entry with bop_toolkit's keys (``create_image_info``) except ``date_captured``."""
    return {"id": int(image_id), "file_name": file_name, "width": int(width), "height": int(height),
            "license": 1, "coco_url": "", "flickr_url": ""}


def frame_annotations(instances: list[dict], visib: np.ndarray, amodal: np.ndarray) -> list[dict]:
    """COCO annotations of one image, without ``id``/``image_id`` (assigned when files are merged).

    Each carries both boxes, ``bbox_amodal`` and ``bbox_modal``; :func:`variant` picks one as ``bbox``.

    Parameters
    ----------
    instances : list of dict
        Raster annotations (:func:`pipeline.annotate.instance_annotations`), in ``gt_id`` order.
    visib : (N, H, W) bool
        Visible masks: ``mask_visib``.
    amodal : (N, H, W) bool
        Full silhouettes inside the image: ``mask``.
    """
    out = []
    for g, a in enumerate(instances):
        m = visib[g]
        area = int(m.sum())
        if area < 1 or not amodal[g].any():   # bop_toolkit skips both
            continue
        visib_fract = round(float(a["visib_fract"]), 6)   # the value written to scene_gt_info.json
        out.append({"category_id": int(a["obj_id"]), "iscrowd": 0, "area": area,
                    "bbox_amodal": bbox(amodal[g]), "bbox_modal": bbox(m), "segmentation": rle(m),
                    "width": int(m.shape[1]), "height": int(m.shape[0]),
                    "ignore": bool(visib_fract < IGNORE_VISIB_FRACT), "inst_id": g,
                    "visib_fract": visib_fract})
    return out


def variant(ann: dict, box: str) -> dict:
    """An annotation of :func:`frame_annotations` with ``bbox`` = its ``box`` ("amodal" | "modal") box."""
    out = {k: v for k, v in ann.items() if k not in ("bbox_amodal", "bbox_modal")}
    out["bbox"] = list(ann[f"bbox_{box}"])
    return out


def coco_document(images: list[dict], annotations: list[dict], cats: list[dict], description: str) -> dict:
    """A COCO dataset document; annotations get ids 1.. in the given order (as bop_toolkit numbers them)."""
    anns = [dict(a, id=i + 1) for i, a in enumerate(annotations)]
    return {"info": {"description": description, "version": "1.0"}, "licenses": [],
            "images": images, "annotations": anns, "categories": cats}
