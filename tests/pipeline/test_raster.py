"""Raster passes against an independent ray caster (Open3D), analytic silhouettes and the poses file."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from pipeline import annotate
from pipeline.config import RasterConfig, build_config
from pipeline.errors import InputError
from pipeline.io import npz_bytes
from pipeline.camera import scaled_intrinsics
from pipeline.raster import ensure_objects, frame_doc, load_poses_file, render_frame, save_frame, save_poses_file
from pipeline.runfolder import RASTER_TPATH, FrameKey
from pipeline.tolerances import RASTER_DEPTH_MEDIAN_M, RASTER_MASK_IOU_MIN
from pipeline.types import Placement
from tests.pipeline import raster_scenes as S

W, H = 320, 240


@pytest.fixture(scope="module")
def rasterizer():
    from pipeline.render_gl import shared_rasterizer

    return shared_rasterizer()


@pytest.fixture(scope="module")
def scene(rasterizer):
    K, T = S.camera(W, H)
    room = S.room_mesh(with_legs=True)
    rasterizer.add_mesh("test-room-legs", *room)
    objs = {o.obj_id: o for o in S.library()}
    keys = ensure_objects(rasterizer, list(objs.values()))
    pl = S.placement()
    room_depth = rasterizer.render_depth(K, T, W, H, [("test-room-legs", np.eye(4))])
    meshes = [room] + [S.posed(objs[int(o)], R, t) for o, R, t in zip(pl.obj_ids, pl.R_m2w, pl.t_m2w)]
    return dict(K=K, T=T, room=room, objs=objs, keys=keys, pl=pl, room_depth=room_depth, meshes=meshes)


def _render(rasterizer, sc, *, placement=None, room_depth=None, real=None, cfg=None, K=None, w=W, h=H):
    return render_frame(rasterizer, K=sc["K"] if K is None else K, T_c2w=sc["T"], width=w, height=h,
                        placement=sc["pl"] if placement is None else placement, mesh_keys=sc["keys"],
                        scene_depth=lambda: sc["room_depth"] if room_depth is None else room_depth,
                        real_depth=lambda: real, cfg=cfg or RasterConfig(real_depth_fusion=real is not None))


@pytest.mark.slow  # importing open3d dominates (several seconds on a loaded machine)
def test_masks_and_depth_match_independent_ray_caster(rasterizer, scene):
    res = _render(rasterizer, scene)
    assert res.status == "ok", res.reason
    ref_depth, ref_idx = S.raycast(scene["meshes"], scene["K"], scene["T"], W, H)
    n = len(scene["pl"].obj_ids)
    occluded_any = False
    for i in range(n):
        vis = res.labels == i + 1
        ref_vis = ref_idx == i + 1
        assert S.iou(vis, ref_vis) >= RASTER_MASK_IOU_MIN, f"instance {i} visible mask"
        _, alone = S.raycast([scene["meshes"][i + 1]], scene["K"], scene["T"], W, H)
        assert S.iou(res.amodal[i], alone == 0) >= RASTER_MASK_IOU_MIN, f"instance {i} amodal mask"
        both = vis & ref_vis
        if both.any():
            assert np.median(np.abs(res.depth[both] - ref_depth[both])) <= RASTER_DEPTH_MEDIAN_M
        occluded_any |= res.instances[i]["px_count_visib"] < res.amodal[i].sum()
    assert occluded_any, "the test scene must contain occlusions"
    # Room depth: the cached pass also matches.
    room_d, room_i = S.raycast([scene["room"]], scene["K"], scene["T"], W, H)
    assert S.iou(scene["room_depth"] > 0, room_i == 0) >= RASTER_MASK_IOU_MIN
    hit = (scene["room_depth"] > 0) & (room_i == 0)
    assert np.median(np.abs(scene["room_depth"][hit] - room_d[hit])) <= RASTER_DEPTH_MEDIAN_M


def test_render_ids_matches_per_instance_composition(rasterizer, scene):
    """The one-pass id render (flat 24-bit colours) agrees with composing per-instance depth renders."""
    pl = scene["pl"]
    inst = [(scene["keys"][int(o)], annotate.rigid(R, t)) for o, R, t in zip(pl.obj_ids, pl.R_m2w, pl.t_m2w)]
    depth, ids = rasterizer.render_ids(scene["K"], scene["T"], W, H, inst)
    singles = np.stack([rasterizer.render_depth(scene["K"], scene["T"], W, H, [i]) for i in inst])
    d2, front = annotate.compose_front(singles)
    assert S.iou(ids > 0, front > 0) >= RASTER_MASK_IOU_MIN
    both = (ids > 0) & (front > 0)
    assert np.mean(ids[both] == front[both]) >= 0.999
    assert np.median(np.abs(depth[both] - d2[both])) <= RASTER_DEPTH_MEDIAN_M


def test_renders_reuse_compiled_shader_programs(rasterizer, scene):
    """pyrender's program cache misses on every OSMesa render unless fixed (a leak and most of the cost)."""
    _render(rasterizer, scene)
    sizes = [len(v.renderer._renderer._program_cache._program_cache) for v in rasterizer._views.values()]
    for _ in range(3):
        _render(rasterizer, scene)
    assert [len(v.renderer._renderer._program_cache._program_cache) for v in rasterizer._views.values()] == sizes


def test_truncated_object_counts_its_outside_pixels_like_bop(rasterizer, scene):
    res = _render(rasterizer, scene)
    i = 5  # cut by the left image border
    a = res.instances[i]
    assert 0 < a["px_count_visib"] < a["px_count_all"]
    x0, y0, x1, y1 = annotate.canvas(W, H)
    _, alone = S.raycast([scene["meshes"][i + 1]], scene["K"], scene["T"], x1 - x0, y1 - y0, x0, y0)
    sil = alone == 0
    assert a["px_count_all"] == pytest.approx(sil.sum(), abs=2)
    assert a["bbox_obj"][0] < 0  # BOP does not clip bbox_obj to the image
    box = annotate.bbox_xywh(sil, x0, y0)
    assert np.abs(np.subtract(a["bbox_obj"], box)).max() <= 1
    assert a["visib_fract"] == pytest.approx(a["px_count_visib"] / a["px_count_all"])
    assert a["bbox_visib"][0] == 0


def test_object_larger_than_a_tile_and_cut_by_the_border(rasterizer, scene):
    """A close-up box (window wider than the tile) cut by the image border: the image-sized path."""
    from pipeline.raster import TILE

    obj = S.make_object(2, "box")
    keys = ensure_objects(rasterizer, [obj])
    K = scene["K"]
    R = S.rot((0, 1, 0), 0.3)
    pl = Placement(scene="s", drop=0, obj_ids=np.array([2], np.int32), R_m2w=R[None],
                   t_m2w=np.array([[0.05, 0.02, 0.2]]), at_rest=np.ones(1, bool), max_penetration=0.0,
                   verdict="accepted")
    res = render_frame(rasterizer, K=K, T_c2w=np.eye(4), width=W, height=H, placement=pl, mesh_keys=keys,
                       scene_depth=lambda: np.zeros((H, W), np.float32), real_depth=lambda: None,
                       cfg=RasterConfig())
    a = res.instances[0]
    v = obj.vertices @ R.T + pl.t_m2w[0]
    x0, y0, x1, y1 = annotate.canvas(W, H)
    _, alone = S.raycast([(v, obj.faces)], K, np.eye(4), x1 - x0, y1 - y0, x0, y0)
    sil = alone == 0
    assert a["bbox_obj"][2] > TILE  # wider than a tile
    assert a["px_count_all"] > a["px_count_visib"] > 0  # cut by the border
    assert abs(a["px_count_all"] - int(sil.sum())) <= 0.002 * sil.sum()
    assert S.iou(res.amodal[0], sil[H:2 * H, W:2 * W]) >= RASTER_MASK_IOU_MIN


def test_sphere_silhouette_area_is_analytic(rasterizer):
    obj = S.make_object(1, "sphere")
    keys = ensure_objects(rasterizer, [obj])
    K = np.array([[400.0, 0, 159.5], [0, 400.0, 119.5], [0, 0, 1]])
    d = 1.0
    pl = Placement(scene="s", drop=0, obj_ids=np.array([1], np.int32), R_m2w=np.eye(3)[None],
                   t_m2w=np.array([[0.0, 0.0, d]]), at_rest=np.ones(1, bool), max_penetration=0.0,
                   verdict="accepted")
    res = render_frame(rasterizer, K=K, T_c2w=np.eye(4), width=W, height=H, placement=pl, mesh_keys=keys,
                       scene_depth=lambda: np.zeros((H, W), np.float32), real_depth=lambda: None,
                       cfg=RasterConfig(min_visible_area=0.0))
    # Silhouette of the icosphere's circumscribed sphere: a disc of radius f r / sqrt(d^2 - r^2); the
    # inscribed polyhedron covers a little less (subdivision 3: faces 1.2 % inside the sphere).
    r = 0.08
    disc = np.pi * (400.0 * r / np.sqrt(d * d - r * r)) ** 2
    assert 0.96 * disc <= res.instances[0]["px_count_all"] <= disc
    assert res.depth[res.labels > 0].min() == pytest.approx(d - r, abs=1e-3)


def test_labels_are_uint16_beyond_255_instances(rasterizer):
    obj = S.make_object(2, "box")
    keys = ensure_objects(rasterizer, [obj])
    n = 300
    w, h = 160, 120
    K = np.array([[150.0, 0, 79.5], [0, 150.0, 59.5], [0, 0, 1]])
    xs, ys = np.meshgrid(np.linspace(-1.9, 1.9, 20), np.linspace(-1.4, 1.4, 15))
    t = np.stack([xs.ravel(), ys.ravel(), np.full(n, 4.0)], axis=1)
    pl = Placement(scene="s", drop=0, obj_ids=np.full(n, 2, np.int32), R_m2w=np.repeat(np.eye(3)[None], n, 0),
                   t_m2w=t, at_rest=np.ones(n, bool), max_penetration=0.0, verdict="accepted")
    res = render_frame(rasterizer, K=K, T_c2w=np.eye(4), width=w, height=h, placement=pl, mesh_keys=keys,
                       scene_depth=lambda: np.zeros((h, w), np.float32), real_depth=lambda: None,
                       cfg=RasterConfig())
    assert res.labels.dtype == np.uint16
    assert res.labels.max() == n
    assert len(np.unique(res.labels)) == n + 1
    assert all(a["px_count_visib"] > 0 for a in res.instances)


def test_frames_without_visible_objects_are_rejected_early(rasterizer, scene):
    calls = []

    def room():
        calls.append(1)
        return scene["room_depth"]

    def placed(t):
        return dataclasses.replace(scene["pl"], obj_ids=scene["pl"].obj_ids[:1], R_m2w=scene["pl"].R_m2w[:1],
                                   t_m2w=np.asarray([t], dtype=np.float64), at_rest=np.ones(1, bool))

    def run(t, **kw):
        return render_frame(rasterizer, K=scene["K"], T_c2w=scene["T"], width=W, height=H, placement=placed(t),
                            mesh_keys=scene["keys"], scene_depth=room, real_depth=lambda: None,
                            cfg=RasterConfig(**kw))

    behind = scene["T"][:3, 3] - 1.0 * scene["T"][:3, 2]  # 1 m behind the camera
    res = run(behind)
    assert (res.status, res.check) == ("rejected", "bound") and not calls
    # A sphere in view but small: the projection bound passes at 0.5 %, the rendered silhouette does not.
    res = run((0.0, 0.0, 0.08), min_visible_area=0.009)
    assert (res.status, res.check) == ("rejected", "amodal") and not calls
    # Under the floor: rendered, but hidden by the room.
    res = run((0.0, 0.0, -0.3), min_visible_area=0.001)
    assert (res.status, res.check) == ("rejected", "visible") and calls
    assert "raster.min_visible_area" in res.reason
    doc = frame_doc(res, scene="s", drop=0, frame=3, frame_id=30, fusion=False)
    assert doc["status"] == "rejected" and doc["instances"] == []


def test_real_depth_fusion_restores_thin_occluders(rasterizer, scene):
    """The scan mesh lacks the table legs; the real depth has them: fusion hides the object behind a leg."""
    K, T = scene["K"], scene["T"]
    room_nolegs = S.room_mesh(with_legs=False)
    rasterizer.add_mesh("test-room-nolegs", *room_nolegs)
    mesh_depth = rasterizer.render_depth(K, T, W, H, [("test-room-nolegs", np.eye(4))])
    true = _render(rasterizer, scene)                       # room with legs = truth
    noisy_real = scene["room_depth"] + np.random.default_rng(0).normal(0, 0.004, (H, W)).astype(np.float32)
    noisy_real[scene["room_depth"] == 0] = 0
    plain = _render(rasterizer, scene, room_depth=mesh_depth)
    fused = _render(rasterizer, scene, room_depth=mesh_depth, real=noisy_real)
    i = 6  # the box behind the front-left leg
    wrong_plain = np.logical_xor(plain.labels == i + 1, true.labels == i + 1).sum()
    wrong_fused = np.logical_xor(fused.labels == i + 1, true.labels == i + 1).sum()
    assert wrong_plain > 20
    assert wrong_fused <= 0.1 * wrong_plain
    assert fused.stats["occluded_by_real_px"] >= 0.9 * wrong_plain
    # Objects resting on real surfaces are not eaten by sensor noise: all other instances unchanged.
    for j in range(len(scene["pl"].obj_ids)):
        if j != i:
            assert S.iou(fused.labels == j + 1, true.labels == j + 1) >= RASTER_MASK_IOU_MIN


def test_real_depth_within_tolerance_does_not_occlude(rasterizer, scene):
    res0 = _render(rasterizer, scene)
    obj = res0.labels > 0
    real = np.where(obj, res0.depth - 0.015, 0).astype(np.float32)  # 1.5 cm nearer: inside the tolerance
    res = _render(rasterizer, scene, real=real)
    assert np.array_equal(res.labels, res0.labels)
    real = np.where(obj, res0.depth - 0.10, 0).astype(np.float32)  # 10 cm nearer: occludes everything
    res = _render(rasterizer, scene, real=real, cfg=RasterConfig(min_visible_area=0.0))
    assert res.stats["visible_px"] == 0


def test_scaled_intrinsics_keep_pixel_centres(rasterizer, scene):
    K2, w2, h2 = scaled_intrinsics(scene["K"], W, H, 0.5)
    assert (w2, h2) == (W // 2, H // 2)
    full = _render(rasterizer, scene)
    half = _render(rasterizer, scene, K=K2, w=w2, h=h2, room_depth=scene["room_depth"][::2, ::2] * 0)
    for i in (0, 1, 3):
        a, b = full.instances[i]["px_count_all"] / 4, half.instances[i]["px_count_all"]
        assert b == pytest.approx(a, rel=0.12)
        # centroids agree: (u + 0.5) * s - 0.5
        ys, xs = np.nonzero(full.amodal[i])
        ys2, xs2 = np.nonzero(half.amodal[i])
        assert (xs.mean() + 0.5) * 0.5 - 0.5 == pytest.approx(xs2.mean(), abs=0.3)
        assert (ys.mean() + 0.5) * 0.5 - 0.5 == pytest.approx(ys2.mean(), abs=0.3)


def test_save_load_roundtrip_and_determinism(rasterizer, scene, tmp_path):
    a = _render(rasterizer, scene)
    b = _render(rasterizer, scene)
    pack = annotate.pack_masks
    assert npz_bytes({"d": a.depth, "l": a.labels, "m": pack(a.amodal)}) == \
        npz_bytes({"d": b.depth, "l": b.labels, "m": pack(b.amodal)})
    doc = frame_doc(a, scene="room", drop=2, frame=7, frame_id=70, fusion=False)
    save_frame(tmp_path / "f000007", a, doc)
    doc2, arr = S.load_frame(tmp_path / "f000007")
    assert doc2 == json.loads(json.dumps(doc))
    assert arr["depth"].dtype == np.float32 and arr["labels"].dtype == np.uint16
    assert np.array_equal(arr["labels"], a.labels) and np.array_equal(arr["amodal"], a.amodal)
    a_inst = doc2["instances"][1]
    R = np.asarray(a_inst["R_m2c"])
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-9)


def test_poses_file_roundtrip(tmp_path):
    pl = S.placement(scene="kitchen", drop=3)
    p = save_poses_file(tmp_path / "poses.json", [pl], frames=[[4, 1]])
    (e,) = load_poses_file(p, obj_ids=[1, 2, 3, 4], scenes=["kitchen"])
    assert e.frames == (1, 4)
    assert np.array_equal(e.placement.obj_ids, pl.obj_ids)
    assert np.allclose(e.placement.R_m2w, pl.R_m2w) and np.allclose(e.placement.t_m2w, pl.t_m2w)
    # a single object instead of a list is accepted too
    one = {"scene": "kitchen", "drop": 0, "instances": [{"obj_id": 1, "R_m2w": np.eye(3).tolist(),
                                                          "t_m2w": [0, 0, 1]}]}
    (tmp_path / "one.json").write_text(json.dumps(one))
    (e1,) = load_poses_file(tmp_path / "one.json")
    assert e1.frames is None and e1.placement.drop == 0


def test_poses_file_takes_an_annotation_rounded_rotation_as_the_nearest_rotation(tmp_path, caplog):
    """A BOP ground-truth rotation is orthonormal to ~2e-3 only: it is used as the nearest rotation, with
    a warning; one 5 % off (a scale) is refused."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("xyz", [20, -35, 60], degrees=True).as_matrix()
    rounded = np.round(R, 3)                                   # BOP writes 3 to 6 digits; 3 gives ~1e-3
    rounded[0, 0] += 1e-3                                      # and a little more
    assert 1e-3 < np.abs(rounded.T @ rounded - np.eye(3)).max() < 1e-2
    d = {"scene": "kitchen", "drop": 0, "instances": [{"obj_id": 1, "R_m2w": rounded.tolist(), "t_m2w": [0, 0, 1]}]}
    p = tmp_path / "poses.json"
    p.write_text(json.dumps(d))
    with caplog.at_level("WARNING", logger="pipeline.raster"):
        (e,) = load_poses_file(p, obj_ids=[1], scenes=["kitchen"])
    Rn = e.placement.R_m2w[0]
    np.testing.assert_allclose(Rn.T @ Rn, np.eye(3), atol=1e-12)
    assert np.linalg.det(Rn) == pytest.approx(1.0, abs=1e-12)
    assert np.degrees((Rotation.from_matrix(Rn).inv() * Rotation.from_matrix(R)).magnitude()) < 0.2
    assert "nearest rotation" in caplog.text and str(p) in caplog.text
    d["instances"][0]["R_m2w"] = (1.05 * R).tolist()
    p.write_text(json.dumps(d))
    with pytest.raises(InputError, match="not a rotation"):
        load_poses_file(p, obj_ids=[1], scenes=["kitchen"])


@pytest.mark.parametrize("mutate, match", [
    (lambda d: d["instances"][0].update(R_m2w=(2 * np.eye(3)).tolist()), "not a rotation"),
    (lambda d: d["instances"][0].update(obj_id=99), "obj_id 99 is not in the object library"),
    (lambda d: d.update(scene="attic"), "scene 'attic' is not an ingested scene"),
    (lambda d: d["instances"][0].pop("t_m2w"), "must have 'obj_id'"),
    (lambda d: d["instances"][0].update(t_m2w=[0, 0]), r"shape \(2,\), expected \(3,\)"),
    (lambda d: d["instances"][0].update(t_m2w=[0, float("nan"), 0]), "NaN"),
    (lambda d: d.update(drop=-1), "drop = -1"),
    (lambda d: d.update(frames=[1, "a"]), "'frames' must be a list"),
])
def test_poses_file_errors_name_the_problem(tmp_path, mutate, match):
    d = {"scene": "kitchen", "drop": 0, "instances": [{"obj_id": 1, "R_m2w": np.eye(3).tolist(),
                                                        "t_m2w": [0, 0, 1]}]}
    mutate(d)
    p = tmp_path / "poses.json"
    p.write_text(json.dumps(d, allow_nan=True))
    with pytest.raises(InputError, match=match) as e:
        load_poses_file(p, obj_ids=[1, 2], scenes=["kitchen"])
    assert str(p) in str(e.value)


def test_poses_file_not_json(tmp_path):
    p = tmp_path / "poses.json"
    p.write_text("{not json")
    with pytest.raises(InputError, match="cannot read the poses file"):
        load_poses_file(p)


def test_config_fields():
    cfg = build_config({"raster": {"real_depth_fusion": False, "fusion_tol_abs": 0.05}})
    assert cfg.raster.real_depth_fusion is False and cfg.raster.fusion_tol_abs == 0.05
    assert cfg.raster.visib_threshold == 0.3 and cfg.raster.min_visible_area == 0.01


def test_cli_raster_with_poses_file(tmp_path, rasterizer):
    """``scansynth raster RUN --config C --poses P`` renders the chosen poses through the runner."""
    from pipeline.cli import init_run_dir, main
    from pipeline.runner import item_results

    run = tmp_path / "RUN"
    poses = tmp_path / "RUN-poses.json"
    cfg_file = tmp_path / "c.toml"
    cfg_file.write_text('[raster]\nvisib_threshold = 0.3\n')
    init_run_dir(run, _cfg_with_poses(poses))
    S.make_run(run, rasterizer, frames=2, drops=1)
    assert main(["raster", str(run), "--config", str(cfg_file), "--poses", str(poses), "-q"]) == 0
    done = item_results(run, "raster")
    assert sorted(done) == ["room/drop0000/f000000", "room/drop0000/f000001"]
    assert all(r["status"] == "ok" for r in done.values())
    # an existing run folder cannot switch to another poses file
    other = tmp_path / "other.json"
    other.write_text(poses.read_text())
    assert main(["raster", str(run), "--poses", str(other), "-q"]) == 2


def _cfg_with_poses(poses):
    # The run folder is created first (as 'scansynth raster RUN --config C --poses P' would), so the
    # hand-made ingest outputs can be written into it; the poses path must exist for validation.
    poses.write_text("[]")
    return build_config({"raster": {"poses": str(poses)}})


def test_stage_renders_accepted_simulated_drops_on_selected_frames(tmp_path, rasterizer):
    """Without a poses file the stage reads the simulate stage's drops (rejected ones are skipped) and the
    select stage's kept frames."""
    import pipeline.raster as raster_stage
    from pipeline.io import atomic_write_json
    from pipeline.runfolder import PLACEMENT_TPATH, path, save_placement

    run = tmp_path / "RUN"
    made = S.make_run(run, rasterizer, frames=3, drops=2)
    ok, bad = made["placements"]
    save_placement(path(run, PLACEMENT_TPATH, scene="room", drop=0), ok)
    save_placement(path(run, PLACEMENT_TPATH, scene="room", drop=1), dataclasses.replace(bad, verdict="rejected:left the room"))
    atomic_write_json(run / "select" / "room" / "selection.json", {"kept": [0, 2]})
    res = S.run_stage_direct(raster_stage.STAGE, run, build_config({}))
    assert sorted(res) == ["room/drop0000/f000000", "room/drop0000/f000002"]
    doc, arr = S.load_frame(FrameKey("room", 0, 2).path(run, RASTER_TPATH))
    assert doc["status"] == "ok" and arr["labels"].max() == len(ok.obj_ids)


def test_real_depth_is_decoded_once_and_cached(tmp_path, rasterizer):
    from pipeline.raster import cached_real_depth
    from pipeline.runfolder import REAL_DEPTH_TPATH, load_scan, path
    from pipeline.scanformats.common import read_depth

    run = tmp_path / "RUN"
    S.make_run(run, rasterizer, frames=1, drops=1)
    scan = load_scan(run, "room")
    h, w = scan.height, scan.width
    d = cached_real_depth(run, scan, 0, w, h)
    np.testing.assert_array_equal(d, read_depth(scan, 0))
    cache = path(run, REAL_DEPTH_TPATH, scene="room", frame=0)
    assert cache.is_file()
    # A later drop reads the cache, not the image: removing the image changes nothing.
    Path(scan.depth_paths[0]).unlink()
    np.testing.assert_array_equal(cached_real_depth(run, scan, 0, w, h), d)
