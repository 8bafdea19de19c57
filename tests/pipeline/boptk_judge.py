"""bop_toolkit as the judge of a written BOP dataset. Runs in bop_toolkit's own venv (numpy<2), never
imports scansynth: ``python boptk_judge.py DATASET_ROOT DELTA_MM [SHIFT_PX]``; prints one JSON line of
figures. SHIFT_PX is added to cx and cy when rendering (0.5 compensates the renderer's pixel-centre
convention, see the test).

Every file is read with bop_toolkit's ``inout`` loaders; gt_info and masks are recomputed as
bop_toolkit's ``scripts/calc_gt_info.py`` does (its vispy renderer, depth mode, on a canvas three
times the image size; ``misc.depth_im_to_dist_im_fast``; ``visibility.estimate_visib_mask_gt`` in
"bop19" mode with the given delta; ``misc.calc_2d_bbox``) and compared with what was written.
"""

import glob
import json
import os
import sys

os.environ.setdefault("EGL_PLATFORM", "surfaceless")  # Mesa's software EGL without a display

import numpy as np  # noqa: E402
from bop_toolkit_lib import inout, misc, visibility  # noqa: E402
from bop_toolkit_lib.rendering import renderer  # noqa: E402


def iou(a, b):
    u = np.logical_or(a, b).sum()
    return 1.0 if u == 0 else float(np.logical_and(a, b).sum() / u)


def main(root, delta, shift=0.0):
    cp = inout.load_cam_params(os.path.join(root, "camera.json"))
    W, H = cp["im_size"]
    models_info = inout.load_json(os.path.join(root, "models", "models_info.json"), keys_to_int=True)
    ren = renderer.create_renderer(3 * W, 3 * H, "vispy", mode="depth")
    for obj_id in sorted(models_info):
        path = os.path.join(root, "models", f"obj_{obj_id:06d}.ply")
        inout.load_ply(path)
        ren.add_object(obj_id, path)
    out = {"instances": 0, "images": 0, "max_visib_fract_diff": 0.0, "min_mask_visib_iou": 1.0,
           "min_mask_iou": 1.0, "bbox_obj_mismatch": [], "bbox_visib_mismatch": [], "px_count_valid_diff": 0,
           "px_count_all_max_rel_diff": 0.0, "worst": None}
    for sd in sorted(glob.glob(os.path.join(root, "train_pbr", "*"))):
        cam = inout.load_scene_camera(os.path.join(sd, "scene_camera.json"))
        gt = inout.load_scene_gt(os.path.join(sd, "scene_gt.json"))
        info = inout.load_json(os.path.join(sd, "scene_gt_info.json"), keys_to_int=True)
        for im_id in sorted(gt):
            rgb = glob.glob(os.path.join(sd, "rgb", f"{im_id:06d}.*"))
            assert inout.load_im(rgb[0]).shape[:2] == (H, W)
            depth = inout.load_depth(os.path.join(sd, "depth", f"{im_id:06d}.png"))
            depth *= cam[im_id]["depth_scale"]  # [mm], as calc_gt_info.py
            K = cam[im_id]["cam_K"]
            fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
            dist_im = misc.depth_im_to_dist_im_fast(depth, K)
            out["images"] += 1
            for gt_id, g in enumerate(gt[im_id]):
                large = ren.render_object(g["obj_id"], g["cam_R_m2c"], g["cam_t_m2c"], fx, fy,
                                           cx + W + shift, cy + H + shift)["depth"]
                d_gt = large[H:2 * H, W:2 * W]
                dist_gt = misc.depth_im_to_dist_im_fast(d_gt, K)
                visib = visibility.estimate_visib_mask_gt(dist_im, dist_gt, delta, visib_mode="bop19")
                px_all = int((large > 0).sum())
                px_valid = int((dist_im[dist_gt > 0] > 0).sum())
                px_visib = int(visib.sum())
                vf = px_visib / float(px_all) if px_all > 0 else 0.0
                bbox = [-1, -1, -1, -1]
                if px_visib > 0:
                    ys, xs = (large > 0).nonzero()
                    bbox = [int(v) for v in misc.calc_2d_bbox(xs - W, ys - H, (W, H))]
                bbox_visib = [-1, -1, -1, -1]
                if px_visib > 0:
                    ys, xs = visib.nonzero()
                    bbox_visib = [int(v) for v in misc.calc_2d_bbox(xs, ys, (W, H))]
                e = info[im_id][gt_id]
                name = f"{os.path.basename(sd)}/{im_id:06d}_{gt_id:06d}"
                mask = inout.load_im(os.path.join(sd, "mask", f"{name.split('/')[1]}.png")) > 0
                mask_visib = inout.load_im(os.path.join(sd, "mask_visib", f"{name.split('/')[1]}.png")) > 0
                assert int(mask_visib.sum()) == e["px_count_visib"], name
                out["instances"] += 1
                d_vf = abs(vf - e["visib_fract"])
                i_v, i_m = iou(visib, mask_visib), iou(d_gt > 0, mask)
                if d_vf > out["max_visib_fract_diff"]:
                    out["max_visib_fract_diff"] = d_vf
                if i_v < out["min_mask_visib_iou"]:
                    out["min_mask_visib_iou"], out["worst"] = i_v, name
                out["min_mask_iou"] = min(out["min_mask_iou"], i_m)
                if bbox != e["bbox_obj"]:
                    out["bbox_obj_mismatch"].append([name, bbox, e["bbox_obj"]])
                if bbox_visib != e["bbox_visib"]:
                    out["bbox_visib_mismatch"].append([name, bbox_visib, e["bbox_visib"]])
                out["px_count_valid_diff"] = max(out["px_count_valid_diff"], abs(px_valid - e["px_count_valid"]))
                if px_all:
                    out["px_count_all_max_rel_diff"] = max(out["px_count_all_max_rel_diff"],
                                                           abs(px_all - e["px_count_all"]) / px_all)
    print(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]), float(sys.argv[3]) if len(sys.argv) > 3 else 0.0)
