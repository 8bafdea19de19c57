"""The raster plan's frame prediction (pipeline.frame_views) against the raster stage's own verdicts."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.config import RasterConfig, build_config
from pipeline.frame_views import FrameView, SensorDepth, frame_view, object_shape, seeing_frames
from pipeline.geometry import look_at
from pipeline.raster import ensure_objects, render_frame
from pipeline.render_gl import ZNEAR
from tests.pipeline import raster_scenes as S

W, H = 160, 120


@pytest.fixture(scope="module")
def rasterizer():
    from pipeline.render_gl import shared_rasterizer

    return shared_rasterizer()


@pytest.fixture(scope="module")
def room(rasterizer):
    mesh = S.room_mesh(with_legs=True)
    rasterizer.add_mesh("frame-views-room", *mesh)
    return "frame-views-room"


def _cameras() -> list[np.ndarray]:
    """Poses around the table and the floor objects: looking at them from near and far, from below the
    table top, along the floor, away from them, and so close that an object crosses the near plane."""
    poses = []
    for k in range(12):
        a = 2 * np.pi * k / 12
        for r, z in ((0.8, 0.9), (1.8, 1.6), (1.2, 0.25)):
            eye = (0.1 + r * np.cos(a), 0.15 + r * np.sin(a), z)
            poses.append(look_at(eye, (0.1, 0.15, 0.2)))
            poses.append(look_at(eye, (0.1 + 2 * r * np.cos(a), 0.15 + 2 * r * np.sin(a), z)))  # away
    poses.append(look_at((0.0, -0.05, 0.09), (0.0, 1.0, 0.09)))     # inside the sphere at the origin
    poses.append(look_at((0.0, -0.085, 0.08), (0.0, 1.0, 0.08)))    # its surface across the near plane
    poses.append(look_at((0.2, 0.0, 0.08), (0.2, -1.0, 0.08)))      # the sphere beside the camera
    return poses


def _verdicts(rasterizer, room, cfg: RasterConfig) -> list[tuple[FrameView, object]]:
    objs = {o.obj_id: o for o in S.library()}
    keys = ensure_objects(rasterizer, list(objs.values()))
    shapes = {i: object_shape(o) for i, o in objs.items()}
    pl = S.placement()
    K = S.intrinsics(W, H, 0.9 * W)
    out = []
    for f, T in enumerate(_cameras()):
        depth = rasterizer.render_depth(K, T, W, H, [(room, np.eye(4))])
        view = frame_view(frame=f, K=K, T_c2w=T, width=W, height=H, placement=pl, shapes=shapes,
                          sensor=lambda d=depth: SensorDepth(depth=d, K=K, T_c2d=np.eye(4)), znear=rasterizer.znear,
                          tol_abs=cfg.fusion_tol_abs, tol_rel=cfg.fusion_tol_rel)
        res = render_frame(rasterizer, K=K, T_c2w=T, width=W, height=H, placement=pl, mesh_keys=keys,
                           scene_depth=lambda d=depth: d, real_depth=lambda d=depth: d, cfg=cfg)
        out.append((view, res))
    return out


def test_prediction_agrees_with_the_raster_verdicts(rasterizer, room):
    """"bound" is predicted exactly; frames well clear of the threshold either way are predicted right."""
    cfg = RasterConfig(min_visible_area=0.01)
    a = cfg.min_visible_area
    rows = _verdicts(rasterizer, room, cfg)
    checks = [res.check for _, res in rows]
    assert {"", "bound", "visible"} <= set(checks)       # the cameras exercise the checks
    for view, res in rows:
        predicted = view.check(a)
        assert (predicted == "bound") == (res.check == "bound"), (view, res.reason)
        if res.status == "ok" and res.stats["visible_px"] >= 2 * a * W * H:
            assert predicted == "", (view, res.stats)
        shares = {"amodal": res.stats.get("object_px", 0), "visible": res.stats.get("visible_px", 0)}
        if res.check in shares and shares[res.check] <= 0.5 * a * W * H:
            assert predicted, (view, res.stats)
    planned = [res for view, res in rows if not view.check(a)]
    assert sum(res.status != "ok" for res in planned) <= 0.1 * len(planned)


def test_objects_across_the_near_plane(rasterizer, room):
    """An object cut by the near plane projects onto the whole canvas (the "bound" check cannot reject
    it); the prediction clips it to what the camera draws."""
    cfg = RasterConfig(min_visible_area=0.01)
    rows = _verdicts(rasterizer, room, cfg)
    for view, res in rows[-3:-1]:            # the camera inside or touching the sphere: it fills the view
        assert view.bound >= 1.0 and res.status == "ok" and not view.check(cfg.min_visible_area)
    view, res = rows[-1]                     # the sphere beside the camera: out of view
    assert view.bound >= 1.0 and res.check == "amodal" == view.check(cfg.min_visible_area)


def test_seeing_frames_ranks_by_visible_share():
    views = [FrameView(frame=0, bound=0.5, amodal=0.3, visible=0.02), FrameView(frame=1, bound=0.0, amodal=0, visible=0),
             FrameView(frame=2, bound=0.5, amodal=0.3, visible=0.2), FrameView(frame=3, bound=0.5, amodal=0.3,
                                                                                 visible=0.02)]
    assert seeing_frames(views, 0.01) == [0, 2, 3]
    assert seeing_frames(views, 0.01, limit=2) == [0, 2]       # the best, then the lower index of a tie
    assert seeing_frames(views, 0.05) == [2]


def _run_with_drop(tmp_path, rasterizer):
    """make_run's scan with its middle frame turned away from the objects, one accepted simulated drop and
    every frame kept."""
    from pipeline.io import atomic_write_json
    from pipeline.runfolder import PLACEMENT_TPATH, path, save_placement, save_scan

    run = tmp_path / "RUN"
    made = S.make_run(run, rasterizer, frames=3, drops=1)
    scan = made["scan"]
    T = scan.T_c2w.copy()
    T[1] = look_at(T[1][:3, 3], T[1][:3, 3] - 2.0 * T[1][:3, 2])   # the opposite way
    save_scan(run / "ingest" / "room", dataclasses.replace(scan, T_c2w=T))
    save_placement(path(run, PLACEMENT_TPATH, scene="room", drop=0), made["placements"][0])
    atomic_write_json(run / "select" / "room" / "selection.json", {"kept": [0, 1, 2]})
    return run


def test_plan_leaves_out_a_frame_looking_away_and_renders_those_that_see_the_drop(tmp_path, rasterizer):
    import pipeline.raster as raster_stage
    from pipeline.stages import StageContext

    run = _run_with_drop(tmp_path, rasterizer)
    cfg = build_config({})
    keys = [i.key for i in raster_stage.plan(StageContext(run_dir=run, cfg=cfg, stage="raster"))]
    assert keys == ["room/drop0000/f000000", "room/drop0000/f000002"]
    assert keys == [i.key for i in raster_stage.plan(StageContext(run_dir=run, cfg=cfg, stage="raster"))]
    res = S.run_stage_direct(raster_stage.STAGE, run, cfg)
    assert sorted(res) == keys and all(r["status"] == "ok" for r in res.values())
    # The frame left out is one the raster stage rejects by its projection bound.
    from pipeline.runfolder import load_scan

    scan = load_scan(run, "room")
    objs = {o.obj_id: o for o in S.library()}
    out = render_frame(rasterizer, K=scan.K[1], T_c2w=scan.T_c2w[1], width=scan.width, height=scan.height,
                       placement=S.placement(), mesh_keys=ensure_objects(rasterizer, list(objs.values())),
                       scene_depth=lambda: None, real_depth=lambda: None, cfg=cfg.raster)
    assert out.check == "bound"


def test_frames_per_drop_keeps_the_best_seeing_frames(tmp_path, rasterizer):
    import pipeline.raster as raster_stage
    from pipeline.stages import StageContext

    run = _run_with_drop(tmp_path, rasterizer)
    cfg = build_config({"raster": {"frames_per_drop": 1}})
    keys = [i.key for i in raster_stage.plan(StageContext(run_dir=run, cfg=cfg, stage="raster"))]
    assert len(keys) == 1 and keys[0] in ("room/drop0000/f000000", "room/drop0000/f000002")


def test_a_poses_file_keeps_its_frames(tmp_path, rasterizer):
    """Frames given by the poses file are rendered as given, even one that sees nothing."""
    import pipeline.raster as raster_stage
    from pipeline.raster import save_poses_file
    from pipeline.stages import StageContext

    run = _run_with_drop(tmp_path, rasterizer)
    poses = save_poses_file(tmp_path / "poses.json", [S.placement()], frames=[[0, 1]])
    cfg = build_config({"raster": {"poses": str(poses)}})
    keys = [i.key for i in raster_stage.plan(StageContext(run_dir=run, cfg=cfg, stage="raster"))]
    assert keys == ["room/drop0000/f000000", "room/drop0000/f000001"]


def test_the_hull_and_near_plane_are_the_rasterizers(rasterizer):
    """The "bound" prediction is exact only with the rasterizer's own hull and near plane."""
    for o in S.library():
        key = ensure_objects(rasterizer, [o])[o.obj_id]
        np.testing.assert_array_equal(object_shape(o).hull, rasterizer.hull_vertices(key))
    assert rasterizer.znear == ZNEAR
