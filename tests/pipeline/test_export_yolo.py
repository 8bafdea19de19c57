"""YOLO export (Ultralytics layout) read back by an independent reader, ``supervision``: boxes equal the
COCO modal boxes, polygons cover ``mask_visib`` (IoU >= 0.95), the split keeps drops whole, same bytes."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline import export, export_yolo, raster
from pipeline.config import build_config
from tests.pipeline import raster_scenes as S

sv = pytest.importorskip("supervision", reason="supervision (test dependency, requirements-test.lock) missing")

POLYGON_IOU_MIN = 0.95


def _export(run_dir: Path, poses: Path, **export_cfg) -> Path:
    cfg = build_config({"raster": {"poses": str(poses)},
                        "export": dict({"image_format": "png", "formats": ["bop", "coco", "yolo"]}, **export_cfg)})
    S.run_stage_direct(export.STAGE, run_dir, cfg)
    return run_dir / "export" / export.DATASET


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from pipeline.render_gl import shared_rasterizer

    base = tmp_path_factory.mktemp("yolo")
    run_dir = base / "RUN"
    made = S.make_run(run_dir, shared_rasterizer())   # 3 frames x 2 drops
    cfg = build_config({"raster": {"poses": str(made["poses"])}})
    S.run_stage_direct(raster.STAGE, run_dir, cfg)
    S.write_composites(run_dir)
    seg_dir = base / "RUN-seg"
    shutil.copytree(run_dir, seg_dir)
    root = _export(run_dir, made["poses"])
    seg_root = _export(seg_dir, made["poses"], yolo_task="segment")
    return dict(made, run_dir=run_dir, root=root, seg_dir=seg_dir, seg_root=seg_root)


def _dataset(root: Path, split: str, masks: bool = False):
    y = root / "yolo"
    with contextlib.redirect_stdout(io.StringIO()):
        return sv.DetectionDataset.from_yolo(str(y / "images" / split), str(y / "labels" / split),
                                             str(y / "data.yaml"), force_masks=masks)


def _index(root: Path) -> dict:
    """YOLO file stem -> the index entry (scene, drop, frame) of that BOP image."""
    return {f"{e['scene_id']:06d}_{e['im_id']:06d}": e
            for e in json.loads((root / export.INDEX).read_text())["images"]}


def test_layout_data_yaml_and_split_by_drop(run):
    y = run["root"] / "yolo"
    ds = _dataset(run["root"], "train")
    assert ds.classes == [o.name for o in sorted(run["library"], key=lambda o: o.obj_id)]
    index = _index(run["root"])
    split_of_drop: dict = {}
    n = 0
    for split in ("train", "val"):
        imgs = sorted(p.stem for p in (y / "images" / split).iterdir())
        assert imgs == sorted(p.stem for p in (y / "labels" / split).iterdir())
        for stem in imgs:
            e = index[stem]
            assert split_of_drop.setdefault((e["scene"], e["drop"]), split) == split   # drops stay whole
            img = y / "images" / split / f"{stem}.png"
            bop = run["root"] / "train_pbr" / f"{e['scene_id']:06d}" / "rgb" / f"{e['im_id']:06d}.png"
            assert img.read_bytes() == bop.read_bytes()
            n += 1
    assert n == 6 and sorted(split_of_drop.values()) == ["train", "val"]   # 2 drops, share 0.2 -> 1 in val


def test_boxes_equal_coco_modal_boxes(run):
    root = run["root"]
    coco = json.loads((root / export.MERGED_COCO_MODAL).read_text())
    names = {c["id"]: c["name"] for c in coco["categories"]}
    by_file = {Path(i["file_name"]): i for i in coco["images"]}
    checked = 0
    for split in ("train", "val"):
        ds = _dataset(root, split)
        for path, _image, det in ds:
            e = _index(root)[Path(path).stem]
            img = by_file[Path(export.SPLIT) / f"{e['scene_id']:06d}" / "rgb" / f"{e['im_id']:06d}.png"]
            anns = [a for a in coco["annotations"] if a["image_id"] == img["id"]]
            want = np.array([[x, y, x + w, y + h] for x, y, w, h in (a["bbox"] for a in anns)], dtype=float)
            assert len(det) == len(anns) > 0
            np.testing.assert_allclose(det.xyxy, want, atol=1e-3)
            assert [ds.classes[c] for c in det.class_id] == [names[a["category_id"]] for a in anns]
            checked += len(anns)
    assert checked >= 20


def test_polygons_cover_visible_masks(run):
    root = run["seg_root"]
    ious = []
    for split in ("train", "val"):
        ds = _dataset(root, split, masks=True)
        for path, _image, det in ds:
            e = _index(root)[Path(path).stem]
            sd = root / "train_pbr" / f"{e['scene_id']:06d}"
            gt = json.loads((sd / "scene_gt_info.json").read_text())[str(e["im_id"])]
            visible = [g for g, gi in enumerate(gt) if gi["px_count_visib"] > 0]
            assert len(det) == len(visible) and det.mask is not None
            for m, g in zip(det.mask, visible):
                want = cv2.imread(str(sd / "mask_visib" / f"{e['im_id']:06d}_{g:06d}.png"), cv2.IMREAD_UNCHANGED) > 0
                ious.append((m & want).sum() / (m | want).sum())
    assert len(ious) >= 20
    assert min(ious) >= POLYGON_IOU_MIN, sorted(ious)[:5]


def test_same_seed_same_bytes_and_stale_files_removed(run, tmp_path):
    y = run["root"] / "yolo"
    before = {p.relative_to(y): p.read_bytes() for p in sorted(y.rglob("*")) if p.is_file()}
    stray = y / "labels" / "train" / "999999_999999.txt"
    stray.write_text("0 0.5 0.5 0.1 0.1\n")
    shutil.rmtree(y / "images")
    ctx = export.StageContext(run_dir=run["run_dir"], cfg=build_config(
        {"raster": {"poses": str(run["poses"])},
         "export": {"image_format": "png", "formats": ["bop", "coco", "yolo"]}}), stage="export")
    export.finish(ctx, {})
    after = {p.relative_to(y): p.read_bytes() for p in sorted(y.rglob("*")) if p.is_file()}
    assert after == before and not stray.exists()


def test_split_units_deterministic_and_seeded():
    units = [("a", d) for d in range(10)]
    v1 = export_yolo.split_units(units, 0.3, seed=0)
    assert v1 == export_yolo.split_units(list(reversed(units)), 0.3, seed=0) and len(v1) == 3
    assert any(export_yolo.split_units(units, 0.3, seed=s) != v1 for s in range(1, 5))
    assert export_yolo.split_units(units, 0.0, seed=0) == set()
    assert export_yolo.split_units([("a", 0)], 0.5, seed=0) == set()   # a single unit stays in train


def test_mask_with_pieces_holes_and_thin_lines_is_one_polygon():
    m = np.zeros((40, 60), bool)
    m[5:20, 5:20] = True
    m[9:15, 9:15] = False    # a hole (a ring-shaped object, or one seen through a handle)
    m[25:35, 40:55] = True   # a second piece (object split by an occluder)
    m[30, 5:9] = True        # a one-pixel-high sliver
    poly = export_yolo.mask_polygon(m)
    line = export_yolo.polygon_line(2, poly, 60, 40)
    assert line.startswith("2 ") and len(line.split()) == 1 + 2 * len(poly)
    back = sv.polygon_to_mask(np.round(np.array(poly)).astype(np.int32), (60, 40)).astype(bool)
    assert (back & m).sum() == m.sum()   # every pixel drawn; the only extra pixels are the bridges' lines
    assert (back & m).sum() / (back | m).sum() >= 0.9   # 30 bridge pixels here (pieces far apart, tiny mask)
    assert back[6, 6] and back[30, 45] and back[30, 6] and not back[12, 12]
    one = np.zeros((5, 5), bool)
    one[2, 3] = True
    assert export_yolo.mask_polygon(one) == [[3, 2]] * 3
