"""The BOP dataset's layout: every file name of a written dataset, in one place.

Path templates in bop_toolkit's ``dataset_params`` style (``obj_{obj_id:06d}.ply``), filled with
``str.format``; ``*_TPATH`` are templates, ``*_PATH`` and ``*_DIR`` fixed names. The first group is
relative to the dataset folder (``RUN/export/dataset``), the second to one scene folder
(``DATASET/SCENE_TPATH``)::

    camera.json
    models/obj_{obj_id:06d}.ply, obj_{obj_id:06d}.png, models_info.json
    train_pbr/{scene_id:06d}/
        rgb/{im_id:06d}.{ext}  depth/{im_id:06d}.png  mask/ and mask_visib/{im_id:06d}_{gt_id:06d}.png
        scene_camera.json  scene_gt.json  scene_gt_info.json  scene_gt_coco.json  scene_gt_coco_modal.json

What the files hold is said by their writers (:mod:`pipeline.export_bop`, :mod:`pipeline.export_coco`);
readers (:mod:`pipeline.preview`, :mod:`pipeline.report`) find them through the same names.
"""

from __future__ import annotations

# --- relative to the dataset folder -------------------------------------------------------------------
SPLIT = "train_pbr"                                   # the one split written: physically based renders
CAMERA_PATH = "camera.json"
MODELS_DIR = "models"
MODEL_TPATH = MODELS_DIR + "/obj_{obj_id:06d}.ply"
MODEL_TEXTURE_TPATH = MODELS_DIR + "/obj_{obj_id:06d}.png"   # named by file name in its PLY's header
MODELS_INFO_PATH = MODELS_DIR + "/models_info.json"
SCENE_TPATH = SPLIT + "/{scene_id:06d}"              # a scene folder: up to ``export.chunk_size`` images

# --- relative to a scene folder -----------------------------------------------------------------------
RGB_DIR, DEPTH_DIR, MASK_DIR, MASK_VISIB_DIR = "rgb", "depth", "mask", "mask_visib"
IMAGE_DIRS = (RGB_DIR, DEPTH_DIR, MASK_DIR, MASK_VISIB_DIR)   # the folders of per-image files
RGB_EXTS = ("jpg", "png")                             # ``export.image_format``
RGB_TPATH = RGB_DIR + "/{im_id:06d}.{ext}"            # ext: one of RGB_EXTS
DEPTH_TPATH = DEPTH_DIR + "/{im_id:06d}.png"
MASK_TPATH = MASK_DIR + "/{im_id:06d}_{gt_id:06d}.png"             # gt_id: index in the image's scene_gt
MASK_VISIB_TPATH = MASK_VISIB_DIR + "/{im_id:06d}_{gt_id:06d}.png"
SCENE_CAMERA_PATH = "scene_camera.json"
SCENE_GT_PATH = "scene_gt.json"
SCENE_GT_INFO_PATH = "scene_gt_info.json"
SCENE_GT_COCO_PATH = "scene_gt_coco.json"             # COCO, amodal boxes (bop_toolkit's calc_gt_coco name)
SCENE_GT_COCO_MODAL_PATH = "scene_gt_coco_modal.json"  # COCO, modal (visible) boxes
