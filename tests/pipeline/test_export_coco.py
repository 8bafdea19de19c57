"""COCO files: load in pycocotools, decoded masks equal the written visible masks, file names exist."""

from __future__ import annotations

import contextlib
import io
import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline import export, raster
from pipeline.config import build_config
from pipeline.export_coco import coco_document, frame_annotations, rle, variant
from tests.pipeline import raster_scenes as S

# pycocotools' Cython decode calls __array__(copy=False) on numpy 2 (its bug, not ours; encode is clean).
PYCOCO_DECODE = pytest.mark.filterwarnings(
    "ignore:__array__ implementation doesn't accept a copy keyword:DeprecationWarning")


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from pipeline.render_gl import shared_rasterizer

    run_dir = tmp_path_factory.mktemp("run") / "RUN"
    made = S.make_run(run_dir, shared_rasterizer(), frames=2, drops=1)
    cfg = build_config({"raster": {"poses": str(made["poses"])}, "export": {"image_format": "jpg"}})
    S.run_stage_direct(raster.STAGE, run_dir, cfg)
    S.write_composites(run_dir)
    S.run_stage_direct(export.STAGE, run_dir, cfg)
    return dict(made, run_dir=run_dir, cfg=cfg, root=run_dir / "export" / export.DATASET)


def _coco(path):
    from pycocotools.coco import COCO

    with contextlib.redirect_stdout(io.StringIO()):  # COCO() prints progress
        return COCO(str(path))


def _read_mask(path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED) > 0


def _box(mask) -> list[int]:
    ys, xs = np.nonzero(mask)
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]


COCO_FILES = {  # (which, box) -> (path relative to the dataset root, base folder of file_name)
    ("scene", "amodal"): ("train_pbr/000000/scene_gt_coco.json", "train_pbr/000000"),
    ("scene", "modal"): ("train_pbr/000000/scene_gt_coco_modal.json", "train_pbr/000000"),
    ("merged", "amodal"): (export.MERGED_COCO, ""),
    ("merged", "modal"): (export.MERGED_COCO_MODAL, ""),
}


@PYCOCO_DECODE
@pytest.mark.parametrize("which, box", list(COCO_FILES))
def test_coco_files_as_bop_toolkit_defines_them(run, which, box):
    """Per bop_toolkit's calc_gt_coco.py: masks = mask_visib, bbox amodal (mask/) or modal (mask_visib/),
    ignore = visib_fract < 0.1 (from scene_gt_info.json), area = visible pixels, ids as it numbers them."""
    root = run["root"]
    rel, base_rel = COCO_FILES[(which, box)]
    coco = _coco(root / rel)
    base = root / base_rel
    assert sorted(coco.getCatIds()) == [1, 2, 3, 4]
    assert coco.loadCats(1)[0]["name"] == "sphere"
    imgs = coco.loadImgs(coco.getImgIds())
    assert len(imgs) == 2
    n, ann_ids = 0, []
    for img in sorted(imgs, key=lambda i: i["id"]):
        f = base / img["file_name"]
        assert f.is_file() and f.suffix == ".jpg"
        im = cv2.imread(str(f))
        assert im.shape[:2] == (img["height"], img["width"])
        im_id = int(f.stem)
        assert img["id"] == im_id   # one scene folder: the global ids equal the im_ids too
        gt_info = json.loads((f.parents[1] / "scene_gt_info.json").read_text())[str(im_id)]
        for ann in coco.loadAnns(coco.getAnnIds(imgIds=img["id"])):
            g = ann["inst_id"]
            visib = _read_mask(f.parents[1] / "mask_visib" / f"{im_id:06d}_{g:06d}.png")
            full = _read_mask(f.parents[1] / "mask" / f"{im_id:06d}_{g:06d}.png")
            assert np.array_equal(coco.annToMask(ann).astype(bool), visib)
            assert ann["area"] == int(visib.sum())
            assert ann["bbox"] == _box(full if box == "amodal" else visib)
            assert ann["iscrowd"] == 0 and (ann["width"], ann["height"]) == (img["width"], img["height"])
            assert ann["visib_fract"] == gt_info[g]["visib_fract"]
            assert ann["ignore"] == (gt_info[g]["visib_fract"] < 0.1)
            ann_ids.append(ann["id"])
            n += 1
        # every instance with a visible pixel has its annotation
        n_vis = sum(1 for gi in gt_info if gi["px_count_visib"] > 0)
        assert len(coco.getAnnIds(imgIds=img["id"])) == n_vis
    assert sorted(ann_ids) == list(range(1, n + 1))
    assert n >= 10


def test_amodal_and_modal_boxes_differ_where_objects_are_occluded(run):
    sd = run["root"] / "train_pbr" / "000000"
    amodal = json.loads((sd / "scene_gt_coco.json").read_text())["annotations"]
    modal = json.loads((sd / "scene_gt_coco_modal.json").read_text())["annotations"]
    assert [a["id"] for a in amodal] == [a["id"] for a in modal]
    assert [{k: v for k, v in a.items() if k != "bbox"} for a in amodal] == \
        [{k: v for k, v in a.items() if k != "bbox"} for a in modal]
    assert any(a["bbox"] != m["bbox"] for a, m in zip(amodal, modal))   # the scene has occlusions


@PYCOCO_DECODE
@pytest.mark.parametrize("box", ["amodal", "modal"])
def test_ground_truth_as_detections_gives_ap_1(run, box):
    from pycocotools import mask as mask_util
    from pycocotools.cocoeval import COCOeval

    rel = export.MERGED_COCO if box == "amodal" else export.MERGED_COCO_MODAL
    gt = _coco(run["root"] / rel)
    dets = []
    for a in gt.loadAnns(gt.getAnnIds()):
        r = mask_util.frPyObjects(a["segmentation"], *a["segmentation"]["size"])  # uncompressed -> compressed
        dets.append({"image_id": a["image_id"], "category_id": a["category_id"], "bbox": a["bbox"],
                     "segmentation": r, "score": 1.0})
    for iou_type in ("bbox", "segm"):
        with contextlib.redirect_stdout(io.StringIO()):
            dt = gt.loadRes([dict(d) for d in dets])
            ev = COCOeval(gt, dt, iou_type)
            ev.evaluate()
            ev.accumulate()
            ev.summarize()
        assert ev.stats[0] == pytest.approx(1.0), (iou_type, ev.stats[:3])   # AP @[.5:.95]
        assert ev.stats[1] == pytest.approx(1.0)                               # AP @.5


BOP_TOOLKIT = Path(__file__).resolve().parents[2].parent / "shared" / "tools" / "bop_toolkit"


def _bop_pycoco_utils():
    import sys

    if not (BOP_TOOLKIT / "bop_toolkit_lib" / "pycoco_utils.py").is_file():
        pytest.skip(f"bop_toolkit not found at {BOP_TOOLKIT} (shared tools absent)")
    sys.path.insert(0, str(BOP_TOOLKIT))
    try:
        with warnings.catch_warnings():   # its transform.py has an invalid escape in a docstring (SyntaxWarning)
            warnings.simplefilter("ignore", SyntaxWarning)
            warnings.simplefilter("ignore", DeprecationWarning)
            from bop_toolkit_lib import pycoco_utils
    except ImportError as e:
        pytest.skip(f"bop_toolkit_lib.pycoco_utils does not import in this venv ({e})")
    finally:
        sys.path.remove(str(BOP_TOOLKIT))
    return pycoco_utils


def test_annotations_equal_bop_toolkits_field_by_field(run):
    """Rebuild scene_gt_coco(_modal).json's annotations with bop_toolkit's own functions, as
    calc_gt_coco.py calls them, from the written masks and scene_gt_info.json."""
    pu = _bop_pycoco_utils()
    sd = run["root"] / "train_pbr" / "000000"
    gt = json.loads((sd / "scene_gt.json").read_text())
    gt_info = json.loads((sd / "scene_gt_info.json").read_text())
    for name, box in (("scene_gt_coco.json", "amodal"), ("scene_gt_coco_modal.json", "modal")):
        ours = json.loads((sd / name).read_text())
        expected, seg_id = [], 1
        for im_id in sorted(map(int, gt)):
            for idx, inst in enumerate(gt[str(im_id)]):
                visib = _read_mask(sd / "mask_visib" / f"{im_id:06d}_{idx:06d}.png")
                if visib.sum() < 1:
                    continue
                full = _read_mask(sd / "mask" / f"{im_id:06d}_{idx:06d}.png")
                bb = pu.bbox_from_binary_mask(full if box == "amodal" else visib)
                expected.append(pu.create_annotation_info(
                    seg_id, im_id, inst["obj_id"], visib, bb, tolerance=2,
                    ignore=gt_info[str(im_id)][idx]["visib_fract"] < 0.1))
                seg_id += 1
        assert len(ours["annotations"]) == len(expected) >= 10
        for a, e in zip(ours["annotations"], expected):
            e = json.loads(json.dumps(e, default=int))   # as bop_toolkit's save_json writes it
            assert {k: a[k] for k in e} == e
        for img in ours["images"]:
            e = pu.create_image_info(img["id"], f"rgb/{img['id']:06d}.jpg", (img["width"], img["height"]))
            del e["date_captured"]   # a timestamp; left out so that the same seed gives the same bytes
            assert {k: img[k] for k in e} == e


def test_invisible_instances_have_no_annotation_and_ignore_is_bop_toolkits_threshold():
    labels = np.zeros((4, 5), np.uint16)
    labels[1:3, 1:4] = 2
    labels[0, 0] = 3
    amodal = np.zeros((3, 4, 5), bool)
    amodal[1, 0:3, 0:4] = True   # larger than the visible part: amodal box differs
    amodal[2, 0, 0:2] = True
    inst = [{"obj_id": 3, "visib_fract": 0.0}, {"obj_id": 4, "visib_fract": 0.9},
            {"obj_id": 5, "visib_fract": 0.0999}]
    anns = frame_annotations(inst, np.stack([labels == g + 1 for g in range(3)]), amodal)
    assert [a["category_id"] for a in anns] == [4, 5] and anns[0]["area"] == 6
    assert anns[0]["bbox_amodal"] == [0, 0, 4, 3] and anns[0]["bbox_modal"] == [1, 1, 3, 2]
    assert [a["ignore"] for a in anns] == [False, True]   # 10 %, not raster.visib_threshold
    assert [a["inst_id"] for a in anns] == [1, 2]
    doc = coco_document([{"id": 0, "file_name": "rgb/000000.png", "width": 5, "height": 4}],
                        [variant(dict(a, image_id=0), "amodal") for a in anns],
                        [{"id": 4, "name": "x", "supercategory": "object"}], "t")
    assert doc["annotations"][0]["id"] == 1 and doc["annotations"][0]["bbox"] == [0, 0, 4, 3]
    assert "bbox_modal" not in doc["annotations"][0]
    json.dumps(doc)  # serialisable


@PYCOCO_DECODE
def test_rle_is_uncompressed_and_decodes_in_pycocotools():
    from pycocotools import mask as mask_util

    for seed in range(3):
        m = np.random.default_rng(seed).random((7, 9)) > 0.6
        m[0, 0] = bool(seed % 2)   # both starts: background run first, or a 0-length one
        r = rle(m)
        assert r["size"] == [7, 9] and isinstance(r["counts"], list) and sum(r["counts"]) == 63
        assert (r["counts"][0] == 0) == bool(m[0, 0])
        back = mask_util.decode(mask_util.frPyObjects(r, 7, 9))
        assert np.array_equal(back.astype(bool), m)
