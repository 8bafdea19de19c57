"""COCO files: load in pycocotools, decoded masks equal the written visible masks, file names exist."""

from __future__ import annotations

import contextlib
import io
import json

import cv2
import numpy as np
import pytest

from pipeline import export, raster
from pipeline.config import build_config
from pipeline.export_coco import coco_document, frame_annotations, rle
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
    S.run_stage_direct(export.STAGE, run_dir, cfg)
    return dict(made, run_dir=run_dir, cfg=cfg, root=run_dir / "export" / export.DATASET)


def _coco(path):
    from pycocotools.coco import COCO

    with contextlib.redirect_stdout(io.StringIO()):  # COCO() prints progress
        return COCO(str(path))


@PYCOCO_DECODE
@pytest.mark.parametrize("which", ["scene", "merged"])
def test_coco_loads_and_masks_equal_written_visible_masks(run, which):
    root = run["root"]
    if which == "scene":
        path, base = root / "train_pbr" / "000000" / "scene_gt_coco.json", root / "train_pbr" / "000000"
    else:
        path, base = root / export.MERGED_COCO, root
    coco = _coco(path)
    assert sorted(coco.getCatIds()) == [1, 2, 3, 4]
    assert coco.loadCats(1)[0]["name"] == "sphere"
    imgs = coco.loadImgs(coco.getImgIds())
    assert len(imgs) == 2
    n = 0
    for img in imgs:
        f = base / img["file_name"]
        assert f.is_file() and f.suffix == ".jpg"
        im = cv2.imread(str(f))
        assert im.shape[:2] == (img["height"], img["width"])
        im_id = int(f.stem)
        for ann in coco.loadAnns(coco.getAnnIds(imgIds=img["id"])):
            m = coco.annToMask(ann).astype(bool)
            written = cv2.imread(str(f.parents[1] / "mask_visib" / f"{im_id:06d}_{ann['inst_id']:06d}.png"),
                                 cv2.IMREAD_UNCHANGED) > 0
            assert np.array_equal(m, written)
            assert ann["area"] == int(written.sum())
            ys, xs = np.nonzero(written)
            assert ann["bbox"] == [xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1]
            assert ann["iscrowd"] == 0
            assert ann["ignore"] == (ann["visib_fract"] < run["cfg"].raster.visib_threshold)
            n += 1
    assert n >= 10


def test_invisible_instances_have_no_annotation():
    labels = np.zeros((4, 5), np.uint16)
    labels[1:3, 1:4] = 2
    inst = [{"inst_id": 0, "obj_id": 3, "px_count_visib": 0, "bbox_visib": [-1, -1, -1, -1], "visible": False,
             "visib_fract": 0.0},
            {"inst_id": 1, "obj_id": 4, "px_count_visib": 6, "bbox_visib": [1, 1, 3, 2], "visible": True,
             "visib_fract": 0.9}]
    anns = frame_annotations(inst, labels)
    assert len(anns) == 1 and anns[0]["category_id"] == 4 and anns[0]["area"] == 6
    doc = coco_document([{"id": 0, "file_name": "rgb/000000.png", "width": 5, "height": 4}],
                        [dict(a, image_id=0) for a in anns], [{"id": 4, "name": "x", "supercategory": "object"}],
                        "t")
    assert doc["annotations"][0]["id"] == 1
    json.dumps(doc)  # serialisable


@PYCOCO_DECODE
def test_rle_roundtrip():
    from pycocotools import mask as mask_util

    m = np.random.default_rng(3).random((7, 9)) > 0.6
    r = rle(m)
    assert r["size"] == [7, 9] and isinstance(r["counts"], str)
    back = mask_util.decode({"size": r["size"], "counts": r["counts"].encode("ascii")})
    assert np.array_equal(back.astype(bool), m)
