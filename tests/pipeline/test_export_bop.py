"""Raster and export stages end to end on a hand-built run folder; the BOP output read back and checked
against an independent re-rendering of the written poses and models."""

from __future__ import annotations

import json
import logging
import os
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline import export, raster, runfolder
from pipeline.config import build_config
from pipeline.export_bop import bop_json_text, depth_png, models_info_mm, ply_bytes_mm, read_ply_mm
from pipeline.runfolder import COMPOSITE_DEPTH_TPATH, COMPOSITE_TPATH, RASTER_TPATH, FrameKey
from pipeline.tolerances import RASTER_MASK_IOU_MIN
from tests.pipeline import raster_scenes as S

BOPTK_VENV = Path(__file__).resolve().parents[2] / ".cache" / "boptk-venv"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from pipeline.render_gl import shared_rasterizer

    run_dir = tmp_path_factory.mktemp("run") / "RUN"
    made = S.make_run(run_dir, shared_rasterizer())
    cfg = build_config({"raster": {"poses": str(made["poses"])}, "export": {"image_format": "png"}})
    r_res = S.run_stage_direct(raster.STAGE, run_dir, cfg)
    S.write_composites(run_dir)
    e_res = S.run_stage_direct(export.STAGE, run_dir, cfg)
    return dict(made, run_dir=run_dir, cfg=cfg, raster=r_res, export=e_res,
                root=run_dir / "export" / export.DATASET)


def test_raster_stage_outputs_and_shared_scene_depth_cache(run):
    rd = run["run_dir"]
    assert len(run["raster"]) == 6 and all(r["status"] == "ok" for r in run["raster"].values())
    cache = sorted((rd / "raster" / "room" / "scene_depth").glob("*.npz"))
    assert [p.name for p in cache] == ["f000000.npz", "f000001.npz", "f000002.npz"]  # one per frame, not per drop
    inodes = [p.stat().st_ino for p in cache]
    # Redo drop 1 frame 2: its scene depth comes from the cache (file not rewritten).
    stem = FrameKey("room", 1, 2).path(rd, RASTER_TPATH)
    before = stem.with_suffix(".npz").read_bytes()
    stem.with_suffix(".npz").unlink()
    ctx = raster.StageContext(run_dir=rd, cfg=run["cfg"], stage="raster")
    raster.run_item(ctx, raster.Item(key="room/drop0001/f000002", data={"scene": "room", "drop": 1, "frame": 2}))
    assert [p.stat().st_ino for p in cache] == inodes
    assert stem.with_suffix(".npz").read_bytes() == before  # same bytes when redone
    doc, arr = S.load_frame(stem)
    assert arr["labels"].dtype == np.uint16 and arr["depth"].dtype == np.float32
    assert arr["amodal"].shape == (7, S.H_RUN, S.W_RUN)
    assert doc["frame_id"] == 20 and doc["real_depth_fusion"] is True
    assert doc["stats"]["occluded_by_real_px"] > 0  # the legs missing from the scan mesh occlude via real depth
    summary = json.loads((rd / "raster" / "summary.json").read_text())
    assert summary["ok"] == 6 and summary["rejected"] == 0


def test_bop_layout_and_json_files(run):
    root = run["root"]
    sd = root / "train_pbr" / "000000"
    assert sorted(p.name for p in (root / "models").iterdir()) == \
        ["models_info.json"] + [f"obj_{i:06d}.ply" for i in (1, 2, 3, 4)]
    cam = json.loads((root / "camera.json").read_text())
    assert set(cam) == {"cx", "cy", "fx", "fy", "width", "height", "depth_scale"}
    gt = json.loads((sd / "scene_gt.json").read_text())
    info = json.loads((sd / "scene_gt_info.json").read_text())
    camj = json.loads((sd / "scene_camera.json").read_text())
    assert sorted(map(int, gt)) == list(range(6)) == sorted(map(int, info)) == sorted(map(int, camj))
    assert len(list((sd / "rgb").glob("*.png"))) == 6
    assert len(list((sd / "mask").glob("*.png"))) == 6 * 7 == len(list((sd / "mask_visib").glob("*.png")))
    # metres -> millimetres; the pose matches the raster annotation
    doc, _ = S.load_frame(FrameKey("room", 0, 1).path(run["run_dir"], RASTER_TPATH))
    g = gt["1"][3]
    assert g["obj_id"] == doc["instances"][3]["obj_id"]
    assert np.allclose(g["cam_t_m2c"], np.asarray(doc["instances"][3]["t_m2c"]) * 1000, atol=1e-3)
    assert np.allclose(np.reshape(g["cam_R_m2c"], (3, 3)), doc["instances"][3]["R_m2c"], atol=1e-8)
    c = camj["1"]
    T_w2c = np.eye(4)
    T_w2c[:3, :3] = np.reshape(c["cam_R_w2c"], (3, 3))
    T_w2c[:3, 3] = np.asarray(c["cam_t_w2c"]) / 1000
    assert np.allclose(np.linalg.inv(T_w2c), doc["T_c2w"], atol=1e-6)
    assert set(info["1"][0]) == {"bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib",
                                 "visib_fract"}
    # masks on disk agree with the counts
    for gt_id, e in enumerate(info["1"]):
        m = cv2.imread(str(sd / "mask_visib" / f"000001_{gt_id:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert m.dtype == np.uint8 and set(np.unique(m)) <= {0, 255}
        assert int((m > 0).sum()) == e["px_count_visib"]
        if e["px_count_visib"] > 0:  # bop_toolkit's calc_2d_bbox: [x_min, y_min, x_max - x_min, y_max - y_min]
            ys, xs = np.nonzero(m)
            assert e["bbox_visib"] == [xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()]
        else:
            assert e["bbox_visib"] == [-1, -1, -1, -1]


def test_depth_png_units(run):
    sd = run["root"] / "train_pbr" / "000000"
    d = cv2.imread(str(sd / "depth" / "000000.png"), cv2.IMREAD_UNCHANGED)
    assert d.dtype == np.uint16
    scale = json.loads((sd / "scene_camera.json").read_text())["0"]["depth_scale"]
    doc, arr = S.load_frame(FrameKey("room", 0, 0).path(run["run_dir"], RASTER_TPATH))
    real = cv2.imread(run["scan"].depth_paths[0], cv2.IMREAD_UNCHANGED).astype(np.float64)  # mm
    mm = d.astype(np.float64) * scale
    vis = arr["labels"] > 0
    assert np.abs(mm[vis] - arr["depth"][vis] * 1000).max() <= scale / 2 + 1e-3  # objects' depth where visible
    assert np.abs(mm[~vis] - real[~vis]).max() <= scale / 2 + 1e-3  # real depth elsewhere
    assert depth_png(np.array([[0.0, 7.0, 1.23456]]), 0.1).tolist() == [[0, 0, 12346]]  # out of range -> 0


def test_gt_rerendered_from_written_poses_matches_written_masks(run):
    """Independent check of the written dataset: ray-cast the written models (mm) at the written poses."""
    root = run["root"]
    sd = root / "train_pbr" / "000000"
    gt = json.loads((sd / "scene_gt.json").read_text())
    camj = json.loads((sd / "scene_camera.json").read_text())
    info = json.loads((sd / "scene_gt_info.json").read_text())
    models = {i: read_ply_mm(root / "models" / f"obj_{i:06d}.ply") for i in (1, 2, 3, 4)}
    checked = 0
    for im_id in ("0", "4"):
        K = np.reshape(camj[im_id]["cam_K"], (3, 3))
        for gt_id, g in enumerate(gt[im_id]):
            m = models[g["obj_id"]]
            R = np.reshape(g["cam_R_m2c"], (3, 3))
            t = np.asarray(g["cam_t_m2c"]) / 1000
            v = m["pts"] / 1000 @ R.T + t
            _, idx = S.raycast([(v, m["faces"])], K, np.eye(4), S.W_RUN, S.H_RUN)
            mask = cv2.imread(str(sd / "mask" / f"{int(im_id):06d}_{gt_id:06d}.png"), cv2.IMREAD_UNCHANGED) > 0
            if mask.sum() == 0 and (idx == 0).sum() == 0:
                continue
            assert S.iou(mask, idx == 0) >= RASTER_MASK_IOU_MIN, (im_id, gt_id)
            vis = cv2.imread(str(sd / "mask_visib" / f"{int(im_id):06d}_{gt_id:06d}.png"), cv2.IMREAD_UNCHANGED) > 0
            assert not (vis & ~mask).any()
            assert info[im_id][gt_id]["px_count_all"] >= mask.sum()
            checked += 1
    assert checked >= 10


def test_models_in_millimetres(run):
    root = run["root"]
    info = json.loads((root / "models" / "models_info.json").read_text())
    for obj in run["library"]:
        m = read_ply_mm(root / "models" / f"obj_{obj.obj_id:06d}.ply")
        assert np.allclose(m["pts"], obj.vertices * 1000, atol=1e-3)
        assert np.array_equal(m["faces"], obj.faces)
        e = info[str(obj.obj_id)]
        assert e["size_x"] == pytest.approx(np.ptp(obj.vertices[:, 0]) * 1000, abs=1e-3)
        assert e["min_z"] == pytest.approx(obj.vertices[:, 2].min() * 1000, abs=1e-3)
    assert info["1"]["diameter"] == pytest.approx(160.0, abs=0.5)  # sphere of radius 8 cm


def test_ply_header_uses_types_bop_toolkit_reads():
    obj = S.make_object(2, "box")
    head = ply_bytes_mm(obj).split(b"end_header\n")[0].decode()
    assert "format binary_little_endian 1.0" in head
    assert "property list uchar int vertex_indices" in head
    types = {line.split()[1] for line in head.splitlines() if line.startswith("property ") and "list" not in line}
    assert types <= {"float", "double", "int", "uchar"}
    info = models_info_mm(obj)
    assert info["size_x"] == pytest.approx(160.0) and info["diameter"] == pytest.approx(
        np.linalg.norm([160, 100, 70]), abs=1e-3)


def test_bop_json_numeric_key_order():
    assert bop_json_text({10: [1], 2: {"a": 1}}) == '{\n  "2": {"a": 1},\n  "10": [1]\n}\n'


def test_export_is_deterministic_and_resumable(run, caplog):
    rd, cfg = run["run_dir"], run["cfg"]
    sd = run["root"] / "train_pbr" / "000000"
    files = sorted(p for p in run["root"].rglob("*") if p.is_file())
    before = {p: p.read_bytes() for p in files}
    # redo one item and the finish: same bytes everywhere
    (sd / "rgb" / "000003.png").unlink()
    ctx = export.StageContext(run_dir=rd, cfg=cfg, stage="export")
    items = export.plan(ctx)
    export.run_item(ctx, items[3])
    with caplog.at_level(logging.WARNING, logger="pipeline.export"):
        export.finish(ctx, {})
    after = {p: p.read_bytes() for p in files}
    assert after == before
    assert "left out" not in caplog.text
    index = json.loads((run["root"] / export.INDEX).read_text())["images"]
    assert {e["rgb_source"] for e in index} == {"composite"}
    summary = json.loads(runfolder.path(rd, runfolder.SUMMARY_TPATH, stage="export").read_text())
    assert summary == {"images": 6, "left_out": {}}


def test_chunking_assigns_new_folders():
    frames = [("a", 0, f) for f in range(5)] + [("b", 0, 0)]
    slots = export.assign_slots(frames, chunk_size=2)
    assert [(s.bop_scene, s.im_id) for s in slots] == [(0, 0), (0, 1), (1, 0), (1, 1), (2, 0), (3, 0)]
    assert [s.global_id for s in slots] == list(range(6))


def _boptk_python() -> Path | None:
    py = BOPTK_VENV / "bin" / "python"
    if not py.is_file():
        return None
    ok = subprocess.run([str(py), "-c", "import bop_toolkit_lib.inout"], capture_output=True, timeout=60)
    return py if ok.returncode == 0 else None


BOPTK_MISSING = (f"bop_toolkit is not installed in {BOPTK_VENV} (it is not on PyPI): bin/setup --test installs "
                 f"it from ../shared/tools/bop_toolkit, which is absent or failed to install")


def test_bop_toolkit_recomputes_gt_info_and_masks(run):
    """bop_toolkit as the judge: its calc_gt_info.py computation (its vispy renderer on Mesa's software EGL,
    its distance images, estimate_visib_mask_gt "bop19" with our delta, calc_2d_bbox) on the written
    poses, models and depth reproduces the written scene_gt_info, masks and mask_visib."""
    from pipeline.tolerances import BOP_VISIB_DELTA_M

    py = _boptk_python()
    if py is None:
        pytest.skip(BOPTK_MISSING)
    judge = Path(__file__).with_name("boptk_judge.py")
    # bop_toolkit's vispy renderer samples pixel (r, c) at u = c + 0.5, v = r + 0.5 (OpenGL pixel centres);
    # we (OpenCV) sample at u = c, v = r. Rendering with cx + 0.5, cy + 0.5 gives our convention: without
    # it, 37 of 42 boxes differ by a pixel and small instances' IoU drops to 0.56 (docs/output.md: Coordinates).
    out = subprocess.run([str(py), str(judge), str(run["root"]), str(BOP_VISIB_DELTA_M * 1000), "0.5"],
                         capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONPATH": ""})
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    print(f"bop_toolkit judge: {r['instances']} instances in {r['images']} images; max |visib_fract diff| "
          f"{r['max_visib_fract_diff']:.4f}; min mask_visib IoU {r['min_mask_visib_iou']:.4f} ({r['worst']}); "
          f"min mask IoU {r['min_mask_iou']:.4f}; px_count_valid max diff {r['px_count_valid_diff']}; "
          f"bbox mismatches obj {len(r['bbox_obj_mismatch'])}, visib {len(r['bbox_visib_mismatch'])}")
    assert r["instances"] == 6 * 7 and r["images"] == 6
    assert r["max_visib_fract_diff"] <= 0.01
    assert r["min_mask_visib_iou"] >= 0.99 and r["min_mask_iou"] >= 0.99
    assert r["bbox_obj_mismatch"] == [] and r["bbox_visib_mismatch"] == []


@pytest.fixture(scope="module")
def run_holes(tmp_path_factory):
    """The same scene with the sensor depth missing on the right half of every frame (where the room mesh
    hides objects) and without real-depth fusion: the cases where the written depth used to contradict
    mask_visib (issue 18)."""
    from pipeline.render_gl import shared_rasterizer

    run_dir = tmp_path_factory.mktemp("holes") / "RUN"
    made = S.make_run(run_dir, shared_rasterizer())
    for p in made["scan"].depth_paths:
        d = cv2.imread(p, cv2.IMREAD_UNCHANGED)
        d[:, d.shape[1] // 2:] = 0
        cv2.imwrite(p, d)
    cfg = build_config({"raster": {"poses": str(made["poses"]), "real_depth_fusion": False},
                        "export": {"image_format": "png"}})
    S.run_stage_direct(raster.STAGE, run_dir, cfg)
    S.write_composites(run_dir)
    S.run_stage_direct(export.STAGE, run_dir, cfg)
    return dict(made, run_dir=run_dir, cfg=cfg, root=run_dir / "export" / export.DATASET)


def test_bop_toolkit_judges_missing_sensor_depth(run_holes):
    """Where the room mesh hides an object and the sensor has no depth, the written depth is the room's,
    so bop_toolkit (missing depth counts as visible) agrees with mask_visib and px_count_valid."""
    from pipeline.tolerances import BOP_VISIB_DELTA_M

    root = run_holes["root"]
    sd = root / "train_pbr" / "000000"
    filled = 0
    for im_id in range(6):
        d = cv2.imread(str(sd / "depth" / f"{im_id:06d}.png"), cv2.IMREAD_UNCHANGED)
        any_obj = np.zeros(d.shape, bool)
        any_vis = np.zeros(d.shape, bool)
        for g in range(7):
            any_obj |= cv2.imread(str(sd / "mask" / f"{im_id:06d}_{g:06d}.png"), cv2.IMREAD_UNCHANGED) > 0
            any_vis |= cv2.imread(str(sd / "mask_visib" / f"{im_id:06d}_{g:06d}.png"), cv2.IMREAD_UNCHANGED) > 0
        filled += int((any_obj & ~any_vis & (d > 0))[:, d.shape[1] // 2:].sum())
    assert filled > 0  # objects hidden by the room where the sensor has no depth: the room's depth, not 0
    py = _boptk_python()
    if py is None:
        pytest.skip(BOPTK_MISSING)
    judge = Path(__file__).with_name("boptk_judge.py")
    out = subprocess.run([str(py), str(judge), str(root), str(BOP_VISIB_DELTA_M * 1000), "0.5"],
                         capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONPATH": ""})
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    print(f"bop_toolkit judge (sensor depth missing on the right half, {filled} hidden pixels there): "
          f"{r['instances']} instances; max |visib_fract diff| {r['max_visib_fract_diff']:.4f}; min mask_visib "
          f"IoU {r['min_mask_visib_iou']:.4f}; px_count_valid max diff {r['px_count_valid_diff']}")
    assert r["instances"] == 42 and r["max_visib_fract_diff"] <= 0.01 and r["min_mask_visib_iou"] >= 0.99
    assert r["px_count_valid_diff"] == 0
    assert r["bbox_obj_mismatch"] == [] and r["bbox_visib_mismatch"] == []


def test_bop_toolkit_reads_the_dataset(run):
    """bop_toolkit's own loaders (numpy<2, so in its own venv) read every file we wrote."""
    py = _boptk_python()
    if py is None:
        pytest.skip(BOPTK_MISSING)
    root = run["root"]
    script = f"""
import json, numpy as np
from bop_toolkit_lib import inout
root = {str(root)!r}
sd = root + '/train_pbr/000000'
gt = inout.load_scene_gt(sd + '/scene_gt.json')
info = inout.load_json(sd + '/scene_gt_info.json', keys_to_int=True)
cam = inout.load_scene_camera(sd + '/scene_camera.json')
cp = inout.load_cam_params(root + '/camera.json')
m = inout.load_ply(root + '/models/obj_000001.ply')
d = inout.load_depth(sd + '/depth/000000.png') * cam[0]['depth_scale']
mask = inout.load_im(sd + '/mask_visib/000000_000000.png')
print(json.dumps({{'n_im': len(gt), 'n_gt': len(gt[0]), 't': gt[0][0]['cam_t_m2c'].ravel().tolist(),
                  'K': cam[0]['cam_K'].ravel().tolist(), 'pts': m['pts'].shape[0],
                  'visib': int((mask > 0).sum()), 'px': info[0][0]['px_count_visib'], 'dmax': float(d.max())}}))
"""
    out = subprocess.run([str(py), "-c", script], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": ""})
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["n_im"] == 6 and r["n_gt"] == 7 and r["visib"] == r["px"]
    assert r["pts"] == len(run["library"][0].vertices)


def test_export_takes_rgb_and_depth_from_the_compositor(run):
    rd, cfg = run["run_dir"], run["cfg"]
    ctx = export.StageContext(run_dir=rd, cfg=cfg, stage="export")
    items = export.plan(ctx)
    item = next(it for it in items if it.data["drop"] == 1 and it.data["frame"] == 2)
    sd = run["root"] / "train_pbr" / "000000"
    im = item.data["im_id"]
    img = np.zeros((S.H_RUN, S.W_RUN, 3), np.uint8)
    img[..., 1] = 200
    cpath = FrameKey("room", 1, 2).path(rd, COMPOSITE_TPATH)
    dpath = FrameKey("room", 1, 2).path(rd, COMPOSITE_DEPTH_TPATH)
    cpath.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(cpath), img[..., ::-1])
    from pipeline.io import atomic_save_npz

    before = cpath.read_bytes()
    atomic_save_npz(dpath, depth=np.full((S.H_RUN, S.W_RUN), 1.5, np.float32))
    try:
        assert export.run_item(ctx, item)["rgb_source"] == "composite"
        rgb = cv2.imread(str(sd / "rgb" / f"{im:06d}.png"))[..., ::-1]
        assert np.array_equal(rgb, img)
        d = cv2.imread(str(sd / "depth" / f"{im:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert np.all(d == round(1500 / cfg.export.depth_scale))
    finally:
        cpath.write_bytes(before)
        dpath.unlink()
        export.run_item(ctx, item)


def test_chunks_split_into_bop_scene_folders(run, tmp_path):
    import shutil

    rd = tmp_path / "RUN"
    shutil.copytree(run["run_dir"], rd, ignore=shutil.ignore_patterns("export"))
    cfg = build_config({"raster": {"poses": str(run["poses"])},
                        "export": {"chunk_size": 4, "formats": ["bop"], "image_format": "png"}})
    S.run_stage_direct(export.STAGE, rd, cfg)
    root = rd / "export" / export.DATASET
    folders = sorted(p.name for p in (root / "train_pbr").iterdir())
    assert folders == ["000000", "000001"]
    sizes = [len(json.loads((root / "train_pbr" / f / "scene_gt.json").read_text())) for f in folders]
    assert sizes == [4, 2]
    assert not (root / export.MERGED_COCO).exists()  # formats = bop only
    assert not (root / "train_pbr" / "000000" / "scene_gt_coco.json").exists()
    assert sorted(p.name for p in (root / "train_pbr" / "000001" / "rgb").iterdir()) == ["000000.png", "000001.png"]


# ---------------------------------------------------------------------------------------------------
# models_info.json round trip: load (mm -> m) then export (m -> mm) gives the original back
# ---------------------------------------------------------------------------------------------------

LMO_MODELS = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "objects" / "lmo" / "models"
INFO_NUMBERS = ("diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z")


def _assert_models_info_roundtrip(original: dict, exported: dict) -> None:
    assert sorted(exported, key=int) == sorted(original, key=int)
    for k, o in original.items():
        e = exported[k]
        for key in INFO_NUMBERS:  # recomputed from the float32 PLY vertices
            assert e[key] == pytest.approx(o[key], abs=1e-3), (k, key)
        for key in ("symmetries_discrete", "symmetries_continuous"):
            assert (key in e) == (key in o), (k, key)
        # symmetries in millimetres, as given (the eggbox offset 0.232611 mm stays 0.232611)
        for me, mo in zip(e.get("symmetries_discrete", []), o.get("symmetries_discrete", [])):
            assert me == pytest.approx(mo, abs=1e-9)
        assert len(e.get("symmetries_discrete", [])) == len(o.get("symmetries_discrete", []))
        for se, so in zip(e.get("symmetries_continuous", []), o.get("symmetries_continuous", [])):
            assert se["axis"] == pytest.approx(so["axis"], abs=1e-9)
            assert se["offset"] == pytest.approx(so["offset"], abs=1e-9)
        assert len(e.get("symmetries_continuous", [])) == len(o.get("symmetries_continuous", []))


def _write_box_ply_mm(path: Path, ext=(80.0, 50.0, 30.0)) -> None:
    import trimesh

    trimesh.creation.box(extents=ext).export(path)


def test_models_info_symmetries_roundtrip_synthetic(tmp_path):
    from pipeline.export_bop import write_models
    from pipeline.objects import load_library

    lib = tmp_path / "models"
    lib.mkdir()
    for oid in (3, 4, 5):
        _write_box_ply_mm(lib / f"obj_{oid:06d}.ply")
    base = {"diameter": float(np.linalg.norm([80, 50, 30])), "min_x": -40.0, "min_y": -25.0, "min_z": -15.0,
            "size_x": 80.0, "size_y": 50.0, "size_z": 30.0}
    original = {
        "3": dict(base, symmetries_discrete=[[-1, 0, 0, 0.232611, 0, -1, 0, 0.694388, 0, 0, 1, -0.0792063,
                                              0, 0, 0, 1]]),
        "4": dict(base, symmetries_continuous=[{"axis": [0, 0, 1], "offset": [1.5, -2.25, 12.0]}]),
        "5": dict(base),  # no symmetry keys: no symmetry, and none written
    }
    (lib / "models_info.json").write_text(json.dumps(original))
    out = tmp_path / "out"
    write_models(out, load_library([str(lib)]))
    exported = json.loads((out / "models" / "models_info.json").read_text())
    _assert_models_info_roundtrip(original, exported)
    assert exported["3"]["symmetries_discrete"][0][3] == 0.232611  # mm, not 0.000233


@pytest.mark.skipif(not (LMO_MODELS / "models_info.json").is_file(),
                    reason=f"LM-O models not found at {LMO_MODELS} (shared data absent)")
def test_models_info_symmetries_roundtrip_lmo(tmp_path):
    from pipeline.export_bop import write_models
    from pipeline.objects import load_library

    original = json.loads((LMO_MODELS / "models_info.json").read_text())
    write_models(tmp_path, load_library([str(LMO_MODELS)]))
    exported = json.loads((tmp_path / "models" / "models_info.json").read_text())
    _assert_models_info_roundtrip(original, exported)
    assert exported["10"]["symmetries_discrete"][0][3] == pytest.approx(0.232611, abs=1e-9)  # the eggbox


@pytest.mark.parametrize("sym, words", [
    ({"symmetries_discrete": [[1, 0, 0, 0]]}, "not 16 numbers"),
    ({"symmetries_discrete": "none"}, "not a list"),
    ({"symmetries_continuous": [{"axis": [0, 0, 1]}]}, "needs \"axis\" and \"offset\""),
    ({"symmetries_continuous": [{"axis": [0, "z", 1], "offset": [0, 0, 0]}]}, "needs \"axis\" and \"offset\""),
    ({"symmetries_continuous": ["z"]}, "needs \"axis\" and \"offset\""),
])
def test_malformed_symmetries_are_a_one_line_error(tmp_path, sym, words):
    from pipeline.errors import InputError
    from pipeline.objects import load_library

    _write_box_ply_mm(tmp_path / "obj_000009.ply")
    (tmp_path / "models_info.json").write_text(json.dumps({"9": dict({"diameter": 100.0}, **sym)}))
    with pytest.raises(InputError) as ei:
        load_library([str(tmp_path)])
    msg = str(ei.value)
    assert "\n" not in msg and str(tmp_path / "models_info.json") in msg and "object 9" in msg
    assert words in msg and "fix or remove it" in msg


# ---------------------------------------------------------------------------------------------------
# A frame without its composite is left out of every format; another run's dataset is not touched
# ---------------------------------------------------------------------------------------------------

def _all_files(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_frame_without_composite_is_left_out_of_every_format(run, tmp_path, caplog, capsys):
    import shutil

    from pipeline import report

    rd = tmp_path / "RUN"
    shutil.copytree(run["run_dir"], rd, ignore=shutil.ignore_patterns("export"))
    cfg = build_config({"raster": {"poses": str(run["poses"])},
                        "export": {"image_format": "png", "formats": ["bop", "coco", "yolo"]}})
    S.run_stage_direct(export.STAGE, rd, cfg)
    root = rd / "export" / export.DATASET
    sd = root / "train_pbr" / "000000"
    assert len(json.loads((sd / "scene_gt.json").read_text())) == 6
    # drop 1, frame 2 (the last image) loses its composite: as if its composite item had failed
    FrameKey("room", 1, 2).path(rd, COMPOSITE_TPATH).unlink()
    with caplog.at_level(logging.WARNING, logger="pipeline.export"):
        S.run_stage_direct(export.STAGE, rd, cfg)
    assert "LEFT OUT" in caplog.text and "room/drop0001/f000002" in caplog.text
    for name in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"):
        assert sorted(map(int, json.loads((sd / name).read_text()))) == list(range(5)), name
    assert sorted(p.name for p in (sd / "rgb").iterdir()) == [f"{i:06d}.png" for i in range(5)]
    assert not list((sd / "mask").glob("000005_*")) and not list((sd / "depth").glob("000005*"))
    for coco_file in (sd / "scene_gt_coco.json", sd / "scene_gt_coco_modal.json", root / export.MERGED_COCO,
                      root / export.MERGED_COCO_MODAL):
        doc = json.loads(coco_file.read_text())
        assert len(doc["images"]) == 5 and {a["image_id"] for a in doc["annotations"]} <= {0, 1, 2, 3, 4}
    index = json.loads((root / export.INDEX).read_text())["images"]
    assert (1, 2) not in {(e["drop"], e["frame"]) for e in index} and len(index) == 5
    yolo_imgs = sorted(p.name for p in (root / "yolo" / "images").rglob("*.png"))
    yolo_labels = sorted(p.name for p in (root / "yolo" / "labels").rglob("*.txt"))
    assert yolo_imgs == [f"000000_{i:06d}.png" for i in range(5)]
    assert yolo_labels == [f"000000_{i:06d}.txt" for i in range(5)]
    summary = json.loads(runfolder.path(rd, runfolder.SUMMARY_TPATH, stage="export").read_text())
    assert summary["images"] == 5 and list(summary["left_out"]) == ["room/drop0001/f000002"]
    assert "no composite image" in summary["left_out"]["room/drop0001/f000002"]
    assert report.rejected(rd)["export"] == summary["left_out"]   # what run.json's "rejected" holds
    assert report.images(rd) == 5
    # the same through the command line: run.json and the console name the frame
    from pipeline.cli import CONFIG_NAME, main
    from pipeline.config import dump_config

    (rd / CONFIG_NAME).write_text(dump_config(cfg), encoding="utf-8")
    capsys.readouterr()
    assert main(["export", str(rd), "--progress", "off"]) == 0
    err = capsys.readouterr().err
    assert "NOT IN DATASET room/drop0001/f000002: no composite image" in err
    assert json.loads((rd / "run.json").read_text())["rejected"]["export"] == summary["left_out"]


def test_dataset_folder_of_another_run_is_a_clear_error_and_left_as_is(run, tmp_path):
    import shutil

    from pipeline.errors import InputError

    rd = tmp_path / "RUN"
    shutil.copytree(run["run_dir"], rd)
    root = rd / "export" / export.DATASET
    before = _all_files(rd / "export")
    other = build_config({"run": {"seed": 7}, "raster": {"poses": str(run["poses"])},
                          "export": {"image_format": "png"}})
    ctx = export.StageContext(run_dir=rd, cfg=other, stage="export")
    with pytest.raises(InputError) as ei:
        export.plan(ctx)
    msg = str(ei.value)
    assert "\n" not in msg and str(root) in msg and "another run" in msg
    # no marker but files (e.g. a dataset copied in by hand): also refused
    (root / export.MARKER).unlink()
    shutil.rmtree(rd / "export" / export.FRAMES_DIR)   # (with them: this run's export from before the marker)
    with pytest.raises(InputError, match="did not write"):
        export.plan(export.StageContext(run_dir=rd, cfg=run["cfg"], stage="export"))
    after = _all_files(rd / "export")
    del before[f"{export.DATASET}/{export.MARKER}"]
    before = {k: v for k, v in before.items() if not k.startswith(export.FRAMES_DIR + "/")}
    assert after == before   # nothing lost or changed


def test_models_info_entry_that_is_not_an_object_is_a_one_line_error(tmp_path):
    from pipeline.errors import InputError
    from pipeline.objects import load_library

    _write_box_ply_mm(tmp_path / "obj_000009.ply")
    (tmp_path / "models_info.json").write_text(json.dumps({"9": [1, 2, 3]}))
    with pytest.raises(InputError, match=r"models_info.json \(object 9\): entry is \[1, 2, 3\]"):
        load_library([str(tmp_path)])
    (tmp_path / "models_info.json").write_text("[]")
    with pytest.raises(InputError, match="not BOP's"):
        load_library([str(tmp_path)])
