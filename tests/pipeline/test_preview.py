"""``scansynth preview`` draws what the written annotations say, and fails clearly without a dataset."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline import export, raster
from pipeline.cli import main
from pipeline.config import build_config
from pipeline.errors import UserError
from pipeline.io import read_json
from pipeline.preview import PALETTE, contact_sheet, draw_annotations, find_dataset
from tests.pipeline import raster_scenes as S


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from pipeline.render_gl import shared_rasterizer

    rd = tmp_path_factory.mktemp("run") / "RUN"
    made = S.make_run(rd, shared_rasterizer())
    cfg = build_config({"raster": {"poses": str(made["poses"])}, "export": {"image_format": "png"}})
    S.run_stage_direct(raster.STAGE, rd, cfg)
    S.write_composites(rd)
    S.run_stage_direct(export.STAGE, rd, cfg)
    return rd


def test_mask_outlines_are_drawn_where_the_written_masks_are(run_dir):
    dataset = find_dataset(run_dir)
    scene = sorted((dataset / "train_pbr").iterdir())[0]
    gt, info, cam = (read_json(scene / n) for n in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"))
    im = int(sorted(gt, key=int)[0])
    rgb = cv2.imread(str(scene / "rgb" / f"{im:06d}.png"))[..., ::-1]
    drawn = draw_annotations(rgb, scene, im, gt[str(im)], info[str(im)], cam[str(im)],
                             read_json(dataset / "models" / "models_info.json"))
    assert drawn.shape == rgb.shape and drawn.dtype == np.uint8
    checked = 0
    for gt_id, inst in enumerate(info[str(im)]):
        if inst["px_count_visib"] == 0:
            continue
        mask = cv2.imread(str(scene / "mask_visib" / f"{im:06d}_{gt_id:06d}.png"), cv2.IMREAD_GRAYSCALE)
        contours, _ = cv2.findContours((mask > 0).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        pts = np.concatenate(contours)[:, 0, :]
        colour = PALETTE[gt_id % len(PALETTE)]
        hit = np.all(drawn[pts[:, 1], pts[:, 0]] == colour, axis=1).mean()
        # Other instances' outlines, boxes and axes may cover part of it; a misplaced outline scores ~0.
        assert hit > 0.5, f"instance {gt_id}: only {hit:.0%} of its mask outline is drawn"
        checked += 1
    assert checked >= 1


def test_command_writes_a_sheet(run_dir, tmp_path, capsys):
    out = tmp_path / "sheet.png"
    assert main(["preview", str(run_dir), "--out", str(out), "--max-images", "3"]) == 0
    sheet = cv2.imread(str(out))
    assert sheet is not None and sheet.shape[1] == 4 * 320
    assert np.array_equal(contact_sheet(find_dataset(run_dir), max_images=3)[..., ::-1], sheet)


def test_no_dataset_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(UserError, match="no BOP dataset"):
        find_dataset(tmp_path)
    assert main(["preview", str(tmp_path)]) == 2
    assert "no BOP dataset" in capsys.readouterr().err
    (tmp_path / "train_pbr").mkdir()
    with pytest.raises(UserError, match="no images"):
        contact_sheet(tmp_path)
