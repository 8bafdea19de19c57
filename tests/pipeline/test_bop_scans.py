"""BOP scene folders as scans (issue 20): written by make-scan in the BOP layout, read back by the
pipeline (and by bop_toolkit's own reader), through ingest and the real CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.scanformats.common import read_depth
from pipeline.scanformats.detect import read_scan, scan_units
from pipeline.synthscan import make_scan
from pipeline.synthscan.generate import GT_DIR

ROOT = Path(__file__).resolve().parents[2]
BOPTK_PY = ROOT / ".cache" / "boptk-venv" / "bin" / "python"


@pytest.fixture(scope="module")
def bop_scan(tmp_path_factory) -> Path:
    return make_scan(tmp_path_factory.mktemp("bop") / "000002", layout="bop", seed=5, width=160, height=120,
                     frames=6)


def _copy(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def _cams(scan: Path) -> dict:
    return json.loads((scan / "scene_camera.json").read_text())


def _truth(scan: Path) -> dict:
    with np.load(scan / GT_DIR / "cameras.npz") as z:
        return {k: z[k] for k in z.files}


def test_poses_intrinsics_and_depth_scale_read_back(bop_scan, tmp_path):
    truth = _truth(bop_scan)
    s = read_scan(bop_scan)
    assert s.format == "bop" and s.num_frames == 6 and s.depth_registered
    np.testing.assert_array_equal(s.K, np.broadcast_to(truth["K"], s.K.shape))     # cam_K as written
    np.testing.assert_allclose(s.T_c2w, truth["T_c2w"], atol=1e-12, rtol=0)
    assert s.depth_scale == 0.001
    # Another depth scale (YCB-V and T-LESS store 0.1 mm units): the same metres come back.
    scaled = _copy(bop_scan, tmp_path / "scaled")
    cams = _cams(scaled)
    for k in cams:
        cams[k]["depth_scale"] = 0.5
        p = scaled / "depth" / f"{int(k):06d}.png"
        cv2.imwrite(str(p), (cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.int64) * 2).astype(np.uint16))
    (scaled / "scene_camera.json").write_text(json.dumps(cams))
    s2 = read_scan(scaled)
    assert s2.depth_scale == 0.0005
    for i in (0, 5):
        np.testing.assert_array_equal(read_depth(s2, i), read_depth(s, i))


def test_bop_toolkit_reads_what_make_scan_writes(bop_scan):
    """The layout is the real one: bop_toolkit's inout.load_scene_camera / load_depth read our files and
    give the true cameras and the depth in millimetres."""
    if not BOPTK_PY.is_file():
        pytest.skip(f"bop_toolkit is not installed in {BOPTK_PY.parent.parent} (bin/setup --test installs it "
                    f"from ../shared/tools/bop_toolkit)")
    code = (
        "import sys, json, numpy as np\n"
        "from bop_toolkit_lib import inout\n"
        "c = inout.load_scene_camera(sys.argv[1] + '/scene_camera.json')\n"
        "d = inout.load_depth(sys.argv[1] + '/depth/000003.png')\n"
        "print(json.dumps({'K': c[3]['cam_K'].tolist(), 'R': c[3]['cam_R_w2c'].tolist(),\n"
        "                  't': c[3]['cam_t_w2c'].ravel().tolist(), 'scale': c[3]['depth_scale'],\n"
        "                  'd': d.tolist()}))\n")
    out = subprocess.run([str(BOPTK_PY), "-c", code, str(bop_scan)], capture_output=True, text=True, timeout=120,
                         env={"PATH": "/usr/bin:/bin"})
    if out.returncode != 0 and "No module named" in out.stderr:
        pytest.skip(f"bop_toolkit does not import: {out.stderr.strip().splitlines()[-1]}")
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout)
    truth = _truth(bop_scan)
    np.testing.assert_allclose(got["K"], truth["K"], atol=1e-9)
    T_w2c = np.linalg.inv(truth["T_c2w"][3])
    np.testing.assert_allclose(got["R"], T_w2c[:3, :3], atol=1e-9)
    np.testing.assert_allclose(np.array(got["t"]) / 1000, T_w2c[:3, 3], atol=1e-9)
    mm = np.asarray(got["d"], float) * got["scale"]
    np.testing.assert_allclose(mm / 1000, read_depth(read_scan(bop_scan), 3), atol=1e-6)


def _unposed(src: Path, dst: Path, keep_pose=()) -> Path:
    scan = _copy(src, dst)
    cams = _cams(scan)
    for k, c in cams.items():
        if int(k) not in keep_pose:
            del c["cam_R_w2c"], c["cam_t_w2c"]
    (scan / "scene_camera.json").write_text(json.dumps(cams))
    return scan


def test_scene_without_world_poses_is_one_scan_per_image(bop_scan, tmp_path):
    scan = _unposed(bop_scan, tmp_path / "000002")
    assert scan_units(scan) == [0, 1, 2, 3, 4, 5]
    one = read_scan(scan, frame=4)
    assert one.num_frames == 1 and int(one.frame_ids[0]) == 4 and one.meta["bop_image"] == 4
    np.testing.assert_array_equal(one.T_c2w[0], np.eye(4))          # its camera is the world frame
    np.testing.assert_array_equal(one.K[0], _truth(bop_scan)["K"])
    mixed = _unposed(bop_scan, tmp_path / "mixed", keep_pose=(0, 2, 3))
    assert scan_units(mixed) == [None, 1, 4, 5]
    posed = read_scan(mixed)
    np.testing.assert_array_equal(posed.frame_ids, [0, 2, 3])
    np.testing.assert_allclose(posed.T_c2w, _truth(bop_scan)["T_c2w"][[0, 2, 3]], atol=1e-12)


def _cli(cfg_text: str, tmp_path: Path, *extra: str) -> subprocess.CompletedProcess:
    cfg = tmp_path / "run.toml"
    cfg.write_text(cfg_text)
    return subprocess.run([sys.executable, "-m", "pipeline", "run", str(cfg), "--out", str(tmp_path / "run"),
                           "--progress", "off", *extra], capture_output=True, text=True, timeout=600, cwd=ROOT)


def test_unposed_scene_ingests_one_scene_per_image_and_bad_images_cost_only_themselves(bop_scan, tmp_path):
    """Through the CLI: a scene without world poses whose image 1 has no depth and whose scene_camera.json
    lost nothing else; and a second scene folder without scene_camera.json. Each bad unit is one line;
    the other images become scenes of one frame each."""
    scan = _unposed(bop_scan, tmp_path / "000002")
    (scan / "depth" / "000001.png").unlink()
    broken = _copy(bop_scan, tmp_path / "000003")
    (broken / "scene_camera.json").unlink()
    r = _cli(f"""[run]\nseed = 0\nworkers = 1\n[scan]\npaths = [{json.dumps(str(scan))}, {json.dumps(str(broken))}]
[ingest]\ntsdf_voxel = 0.08\ntsdf_trunc = 0.3\n""", tmp_path, "--to", "ingest")
    assert r.returncode == 1, r.stderr[-3000:]
    failed = [ln for ln in r.stderr.splitlines() if ln.startswith("FAILED ingest")]
    assert len(failed) == 2, r.stderr[-3000:]
    assert any("000002-000001" in ln and "depth/000001.png: the depth of image 1 is missing" in ln
               for ln in failed), failed
    assert any("000003" in ln and "without scene_camera.json" in ln for ln in failed), failed
    assert "Traceback" not in r.stderr
    done = sorted(p.parent.name for p in (tmp_path / "run" / "ingest").glob("*/scan.json"))
    assert done == ["000002-000000", "000002-000002", "000002-000003", "000002-000004", "000002-000005"]
    s = json.loads((tmp_path / "run" / "ingest" / "000002-000004" / "scan.json").read_text())
    assert s["format"] == "bop" and s["meta"]["bop_image"] == 4


def test_a_rotation_that_is_no_rotation_costs_its_image(bop_scan, tmp_path):
    scan = _copy(bop_scan, tmp_path / "000002")
    cams = _cams(scan)
    cams["2"]["cam_R_w2c"] = [1, 2, 3, 4, 5, 6, 7, 8, 9]
    (scan / "scene_camera.json").write_text(json.dumps(cams))
    with pytest.warns(UserWarning, match=r"skipped 1 of 6 frame\(s\).*image 2.*not a rigid transform"):
        s = read_scan(scan)
    np.testing.assert_array_equal(s.frame_ids, [0, 1, 3, 4, 5])


def test_a_malformed_camera_costs_its_image(bop_scan, tmp_path):
    scan = _copy(bop_scan, tmp_path / "000002")
    cams = _cams(scan)
    cams["4"]["cam_K"] = [500, 0, 80]
    cams["1"]["depth_scale"] = -1
    (scan / "scene_camera.json").write_text(json.dumps(cams))
    with pytest.warns(UserWarning, match=r"skipped 2 of 6 image\(s\) whose camera is malformed \(first: .*image 1: "
                                         r"depth_scale is -1"):
        s = read_scan(scan)
    np.testing.assert_array_equal(s.frame_ids, [0, 2, 3, 5])
    assert s.meta["skipped"]["bad_camera"] == 2


def test_unposed_bop_images_become_datasets_of_their_own(tmp_path):
    """A BOP scene of two images without world poses, end to end: each image is a scene of one frame;
    objects dropped on what its depth shows are composited onto that image and exported."""
    src = make_scan(tmp_path / "src", layout="bop", seed=2, width=320, height=240, frames=2)
    scan = _unposed(src, tmp_path / "000007")
    r = _cli(f"""[run]\nseed = 0\nworkers = 1\n[scan]\npaths = [{json.dumps(str(scan))}]
[objects]\npaths = ["builtin:shapes"]\n[simulate]\ndrops = 2\nobjects_per_drop = 3
[ingest]\ntsdf_voxel = 0.03\n[export]\nformats = ["bop", "coco"]\n""", tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    run = tmp_path / "run"
    assert sorted(p.name for p in (run / "ingest").glob("000007-*")) == ["000007-000000", "000007-000001"]
    scenes = json.loads((run / "export" / "dataset" / "scansynth_index.json").read_text())
    gt_files = sorted((run / "export" / "dataset" / "train_pbr").glob("*/scene_gt.json"))
    assert len(gt_files) == 2, (scenes, gt_files)
    for p in gt_files:
        gt = json.loads(p.read_text())
        assert gt and all(len(v) >= 1 for v in gt.values())
