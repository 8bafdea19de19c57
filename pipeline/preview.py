"""``scansynth preview``: a contact sheet drawn from a written BOP dataset.

Everything drawn comes from the files a user would read: the colour images, ``mask_visib/`` outlines,
``scene_gt_info.json`` visible boxes and ``scene_gt.json`` poses projected with ``scene_camera.json``
intrinsics (model axes of half the object's diameter from ``models/models_info.json``). A wrong pose,
box or mask shows up as a misdrawn overlay, so the sheet also checks the annotations by eye.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pipeline.bop_layout import (MASK_VISIB_TPATH, MODELS_INFO_PATH, RGB_DIR, RGB_EXTS, RGB_TPATH, SCENE_CAMERA_PATH,
                                 SCENE_GT_INFO_PATH, SCENE_GT_PATH, SPLIT)
from pipeline.errors import UserError
from pipeline.io import read_json

log = logging.getLogger(__name__)

DEFAULT_NAME = "preview.png"
PALETTE = np.array([(230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48),
                    (145, 30, 180), (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 212)],
                   np.uint8)


def find_dataset(path: Path) -> Path:
    """The BOP dataset folder for a run folder or a dataset folder."""
    for cand in (path, path / "export" / "dataset"):
        if (cand / SPLIT).is_dir():
            return cand
    raise UserError(f"{path}: no BOP dataset found (looked for {SPLIT}/ in it and in export/dataset/); "
                    f"run 'scansynth run CONFIG --out {path}' to the export stage first")


def _images(dataset: Path) -> list[tuple[Path, int]]:
    out = []
    for scene_dir in sorted((dataset / SPLIT).iterdir()):
        gt = scene_dir / SCENE_GT_PATH
        if gt.is_file():
            out += [(scene_dir, int(k)) for k in sorted(read_json(gt), key=int)]
    return out


def draw_annotations(rgb: np.ndarray, scene_dir: Path, im_id: int, gts: list, infos: list, cam: dict,
                     models_info: dict) -> np.ndarray:
    """Overlay visible-mask outlines, visible boxes and projected pose axes on one image.

    Parameters
    ----------
    rgb
        (H, W, 3) uint8 image.
    gts, infos, cam
        This image's entries of scene_gt.json, scene_gt_info.json and scene_camera.json.
    models_info
        models_info.json (mm).
    """
    import cv2

    img = np.ascontiguousarray(rgb[..., ::-1].copy())  # BGR for OpenCV drawing
    K = np.asarray(cam["cam_K"], np.float64).reshape(3, 3)
    for gt_id, (gt, info) in enumerate(zip(gts, infos)):
        colour = tuple(int(c) for c in PALETTE[gt_id % len(PALETTE)][::-1])
        mpath = scene_dir / MASK_VISIB_TPATH.format(im_id=im_id, gt_id=gt_id)
        if mpath.is_file():
            mask = cv2.imread(str(mpath), cv2.IMREAD_GRAYSCALE)
            contours, _ = cv2.findContours((mask > 0).astype(np.uint8), cv2.RETR_EXTERNAL,
                                           cv2.CHAIN_APPROX_SIMPLE)
            cv2.drawContours(img, contours, -1, colour, 1)
        x, y, w, h = info.get("bbox_visib", [-1, -1, -1, -1])
        if w > 0 and h > 0:
            cv2.rectangle(img, (x, y), (x + w, y + h), colour, 1)  # bop_toolkit box: w = x_max - x_min
        R = np.asarray(gt["cam_R_m2c"], np.float64).reshape(3, 3)
        t = np.asarray(gt["cam_t_m2c"], np.float64).reshape(3)
        diameter = float(models_info.get(str(gt["obj_id"]), {}).get("diameter", 100.0))
        pts = np.vstack([np.zeros(3), np.eye(3) * diameter * 0.5]) @ R.T + t  # mm, camera frame
        if np.all(pts[:, 2] > 1e-3):
            uv = (pts @ K.T)[:, :2] / pts[:, 2:3]
            o = tuple(np.round(uv[0]).astype(int))
            for axis, c in zip(uv[1:], ((0, 0, 255), (0, 255, 0), (255, 0, 0))):  # x red, y green, z blue
                cv2.line(img, o, tuple(np.round(axis).astype(int)), c, 1, cv2.LINE_AA)
    return img[..., ::-1]


class Sample(NamedTuple):
    """One dataset image picked for a sheet or report, drawn from its written annotations."""

    scene_dir: Path
    im_id: int
    image: np.ndarray | None    # (H, W, 3) uint8 RGB with overlays; None when it could not be read
    gts: list                   # this image's scene_gt.json entries
    infos: list                 # this image's scene_gt_info.json entries
    problem: str = ""           # why ``image`` is None


def pick(n: int, max_images: int) -> np.ndarray:
    """Indices of up to ``max_images`` of ``n`` images, evenly spread."""
    if n == 0:
        return np.zeros(0, np.int64)
    return np.unique(np.linspace(0, n - 1, min(max_images, n)).round().astype(np.int64))


def annotated_samples(dataset: Path, max_images: int) -> tuple[int, Iterator[Sample]]:
    """The number of images in ``dataset`` and an iterator over up to ``max_images`` of them (evenly
    spread), each with masks, boxes and axes drawn by :func:`draw_annotations`. Shared by the contact
    sheet and the run report (``pipeline/report_html.py``)."""
    images = _images(dataset)
    models_info = {}
    mi = dataset / MODELS_INFO_PATH
    if mi.is_file():
        models_info = read_json(mi)

    def gen() -> Iterator[Sample]:
        import cv2

        cache: dict[Path, tuple] = {}
        for idx in pick(len(images), max_images):
            scene_dir, im_id = images[idx]
            if scene_dir not in cache:
                cache[scene_dir] = tuple(read_json(p) if p.is_file() else {} for p in
                                         (scene_dir / n for n in (SCENE_GT_PATH, SCENE_GT_INFO_PATH,
                                                                  SCENE_CAMERA_PATH)))
            gt, info, cam = cache[scene_dir]
            key = str(im_id)
            gts, infos = gt.get(key, []), info.get(key, [])
            rgb_path = next((p for p in (scene_dir / RGB_TPATH.format(im_id=im_id, ext=ext) for ext in RGB_EXTS)
                             if p.is_file()), None)
            bgr = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR) if rgb_path is not None else None
            if bgr is None:
                yield Sample(scene_dir, im_id, None, gts, infos,
                             f"{scene_dir / RGB_DIR}: image {im_id:06d} is listed in {SCENE_GT_PATH} but missing "
                             f"or unreadable")
                continue
            if key not in cam:
                yield Sample(scene_dir, im_id, None, gts, infos,
                             f"{scene_dir / SCENE_CAMERA_PATH}: no entry for image {im_id:06d}")
                continue
            yield Sample(scene_dir, im_id, draw_annotations(bgr[..., ::-1], scene_dir, im_id, gts, infos,
                                                            cam[key], models_info), gts, infos)

    return len(images), gen()


def contact_sheet(dataset: Path, *, max_images: int = 12, columns: int = 4, tile_width: int = 320) -> np.ndarray:
    """(H, W, 3) uint8 sheet of up to ``max_images`` annotated images, evenly spread over the dataset."""
    import cv2

    n, samples = annotated_samples(dataset, max_images)
    if not n:
        raise UserError(f"{dataset}: the dataset has no images (every frame was rejected?); "
                        f"see run.json for the reasons")
    tiles = []
    for s in samples:
        if s.image is None:
            raise UserError(s.problem)
        tile = s.image
        h = int(round(tile.shape[0] * tile_width / tile.shape[1]))
        tile = cv2.resize(tile, (tile_width, h), interpolation=cv2.INTER_AREA)
        label = f"{s.scene_dir.name}/{s.im_id:06d}"
        cv2.putText(tile, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    th = max(t.shape[0] for t in tiles)
    rows = []
    for r in range(0, len(tiles), columns):
        row = [np.pad(t, ((0, th - t.shape[0]), (0, 0), (0, 0))) for t in tiles[r:r + columns]]
        row += [np.zeros((th, tile_width, 3), np.uint8)] * (columns - len(row))
        rows.append(np.concatenate(row, axis=1))
    return np.concatenate(rows, axis=0)
