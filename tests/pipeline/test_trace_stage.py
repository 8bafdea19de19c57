"""Tests of the trace stage (pipeline/trace/stage.py), the shadow-ratio pass and the denoiser.

The run folder is built here from the agreed save APIs (ingest's scan and library writers, raster's
frame files) with small analytic meshes, so these tests do not depend on TSDF fusion or physics.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.config import build_config
from pipeline.errors import InputError
from pipeline.io import atomic_save_npz, atomic_write_bytes, atomic_write_json, load_npz
from pipeline.runfolder import TRACE_TPATH, FrameKey
from pipeline.stages import StageContext
from pipeline.trace.denoise import denoise, denoise_ao, joint_bilateral, oidn_available
from pipeline.camera import Camera
from pipeline.trace.scene import ObjectInstance, build_scene
from pipeline.trace.shadow import shadow_ratio
from pipeline.types import ObjectModel, Scan
from tests.pipeline.shapes import box_room, look_at, uv_sphere

# --------------------------------------------------------------------------------------------------
# Shadow ratio
# --------------------------------------------------------------------------------------------------


def _shadow_scene(albedo: float):
    rv, rf = box_room((-3, -3, 0), (3, 3, 3), n=6)
    v, f, n = uv_sphere(0.3, (0, 0, 1.0), n_lat=24, n_lon=48)
    ob = ObjectInstance(vertices=v, faces=f, normals=n, albedo=np.full((len(v), 3), albedo, np.float32))
    sc = build_scene(rv, rf, None, [ob], room_linear_radiance=np.ones((len(rv), 3)))
    K = np.array([[80.0, 0, 31.5], [0, 80.0, 23.5], [0, 0, 1]])
    cam = Camera(K=K, T_c2w=look_at((0, -2.9, 0.25), (0, 0, 0)), width=64, height=48)
    return sc, cam


def _pixel_of(cam: Camera, p) -> tuple[int, int]:
    T = np.linalg.inv(cam.T_c2w)
    q = T[:3, :3] @ np.asarray(p, float) + T[:3, 3]
    x = cam.K @ (q / q[2])
    return int(round(x[1])), int(round(x[0]))


@pytest.mark.parametrize("albedo", [0.0, 0.5])
def test_shadow_ratio_under_a_sphere_matches_the_blocked_solid_angle(albedo):
    sc, cam = _shadow_scene(albedo)
    y, x = _pixel_of(cam, (0, 0, 0))
    labels = np.ones((48, 64), np.uint16)
    labels[y, x] = 0  # trace only the floor point under the sphere
    sr = shadow_ratio(sc, cam, labels, np.random.default_rng(0), samples=20_000)
    share = (0.3 / 1.0) ** 2  # cosine-weighted share of the hemisphere a sphere right above covers
    assert sr[y, x] == pytest.approx(1 - (1 - albedo) * share, abs=0.01)


def test_shadow_ratio_counts_overlapping_cones_once():
    """A second sphere hidden behind the first (its cone inside the first's) changes nothing."""
    sc1, cam = _shadow_scene(0.0)
    v, f, n = uv_sphere(0.4, (0, 0, 2.0), n_lat=24, n_lon=48)
    far = ObjectInstance(vertices=v, faces=f, normals=n, albedo=np.zeros((len(v), 3), np.float32))
    v1, f1, n1 = uv_sphere(0.3, (0, 0, 1.0), n_lat=24, n_lon=48)
    near = ObjectInstance(vertices=v1, faces=f1, normals=n1, albedo=np.zeros((len(v1), 3), np.float32))
    nr = sc1.num_room_tris
    sc = build_scene(sc1.vertices[: sc1.faces[:nr].max() + 1], sc1.faces[:nr], None, [near, far],
                     room_linear_radiance=np.ones((sc1.faces[:nr].max() + 1, 3)))
    y, x = _pixel_of(cam, (0, 0, 0))
    labels = np.ones((48, 64), np.uint16)
    labels[y, x] = 0
    sr = shadow_ratio(sc, cam, labels, np.random.default_rng(0), samples=20_000)
    assert sr[y, x] == pytest.approx(1 - 0.09, abs=0.01)


def test_shadow_ratio_is_one_far_away_and_without_objects():
    sc, cam = _shadow_scene(0.0)
    labels = np.zeros((48, 64), np.uint16)
    sr = shadow_ratio(sc, cam, labels, np.random.default_rng(0), samples=8, min_effect=0.05)
    y, x = _pixel_of(cam, (1.2, 1.0, 0.0))  # floor point 1.85 m from the sphere: (r/d)^2 < 0.05
    assert sr[y, x] == 1.0 and (sr == 1.0).mean() > 0.5 and sr.min() < 0.99
    lab = np.ones((48, 64), np.uint16)  # every pixel an object pixel: nothing to trace
    assert (shadow_ratio(sc, cam, lab, np.random.default_rng(0)) == 1).all()
    empty = build_scene(sc.vertices[: len(sc.vertices)], sc.faces[: sc.num_room_tris], None, [])
    assert (shadow_ratio(empty, cam, labels, np.random.default_rng(0)) == 1).all()


def test_room_points_cast_only_near_rays_yet_find_every_near_point():
    """The pass casts only rays passing within an object's reach; the points it keeps are exactly those a
    ray from every pixel would find (the reference: every pixel's hit, then the cover test)."""
    from pipeline.trace.scene import instance_spheres, sphere_cover
    from pipeline.trace.shadow import reach_mask, room_points

    sc, cam = _shadow_scene(0.5)
    every = np.ones(48 * 64, bool)
    for min_effect in (0.02, 0.05, 0.2):
        pts = room_points(sc, cam, every, min_effect)
        o, d = cam.rays(np.arange(48 * 64), np.full((48 * 64, 2), 0.5))
        h = sc.intersector.intersect(o, d)
        room = h.hit & (sc.tri_inst[np.maximum(h.prim, 0)] == 0)
        p = o + h.t[:, None] * d
        near = room & (sphere_cover(np.where(room[:, None], p, 0), instance_spheres(sc)) >= min_effect).any(axis=1)
        assert np.array_equal(pts.pix, np.flatnonzero(near)) and 0 < near.sum() < room.sum()
        c, r = instance_spheres(sc)
        cast = reach_mask(o, d, c, r / np.sqrt(min_effect))
        if min_effect == 0.2:   # a reach of 0.67 m: most of the frame is never cast
            assert cast.sum() < 0.6 * cast.size
    # a ray passing 1 m beside a centre is kept for a reach of 1 m and dropped for 0.9 m; behind the camera never
    o1, d1 = np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32)
    assert reach_mask(o1, d1, np.array([[1.0, 0, 5]]), np.array([1.0]))[0]
    assert not reach_mask(o1, d1, np.array([[1.0, 0, 5]]), np.array([0.9]))[0]
    assert not reach_mask(o1, d1, np.array([[0.0, 0, -5]]), np.array([1.0]))[0]


def test_contact_shadow_keeps_its_strength_beside_the_object():
    """Issue 16: a sphere resting on the floor. Within 3 px of its silhouette the default (stride 2,
    smoothed) ratio has the mean of a full-resolution reference; object pixels must not pull it towards 1
    (they did: the band's mean was ~0.04 too bright)."""
    from scipy import ndimage

    rv, rf = box_room((-2, -2, 0), (2, 2, 2.6), n=8)
    v, f, n = uv_sphere(0.12, (0, 0, 0.12), n_lat=24, n_lon=48)
    ob = ObjectInstance(vertices=v, faces=f, normals=n, albedo=np.full((len(v), 3), 0.5, np.float32))
    sc = build_scene(rv, rf, None, [ob], room_linear_radiance=np.ones((len(rv), 3)))
    K = np.array([[260.0, 0, 79.5], [0, 260.0, 59.5], [0, 0, 1]])
    cam = Camera(K=K, T_c2w=look_at((0.05, -0.6, 0.45), (0.0, 0.0, 0.06)), width=160, height=120)
    o, d = cam.rays(np.arange(160 * 120), np.full((160 * 120, 2), 0.5))
    h = sc.intersector.intersect(o, d)
    labels = np.where(h.hit, sc.tri_inst[np.maximum(h.prim, 0)], 0).astype(np.uint16).reshape(120, 160)
    band = ndimage.binary_dilation(labels > 0, iterations=3) & (labels == 0)
    ref = shadow_ratio(sc, cam, labels, np.random.default_rng(1), samples=256, min_effect=0.04)
    assert ref[band].min() < 0.6           # a real contact shadow to keep
    sr = shadow_ratio(sc, cam, labels, np.random.default_rng(2), samples=16, min_effect=0.04, stride=2, smooth=1.0)
    assert abs(sr[band].mean() - ref[band].mean()) < 0.015
    assert np.abs(sr - ref)[band].mean() < 0.05
    assert (sr[labels > 0] == 1).all()


# --------------------------------------------------------------------------------------------------
# Denoiser
# --------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("method", ["bilateral", "oidn"])
def test_denoise_lowers_noise_and_touches_only_the_mask(method):
    if method == "oidn" and not oidn_available():
        pytest.skip("pyoidn is not installed (optional denoiser)")
    rng = np.random.default_rng(0)
    H, W = 40, 50
    truth = np.zeros((H, W, 3), np.float32)
    truth[..., 0] = np.linspace(0.2, 0.8, W)[None]
    truth[..., 1] = 0.5
    truth[..., 2] = 0.3
    noisy = (truth * rng.gamma(4.0, 0.25, (H, W, 1))).astype(np.float32)
    albedo = np.full((H, W, 3), 0.5, np.float32)
    normal = np.zeros((H, W, 3), np.float32)
    normal[..., 2] = 1
    mask = np.zeros((H, W), bool)
    mask[5:35, 5:45] = True
    out = denoise(noisy, albedo, normal, mask, method=method)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out[~mask], noisy[~mask])
    err_in = np.sqrt(np.mean((noisy[mask] - truth[mask]) ** 2))
    err_out = np.sqrt(np.mean((out[mask] - truth[mask]) ** 2))
    assert err_out < 0.5 * err_in


@pytest.mark.parametrize("method", ["bilateral", "oidn"])
def test_denoise_ao_lowers_noise_stays_in_range_and_touches_only_the_mask(method):
    if method == "oidn" and not oidn_available():
        pytest.skip("pyoidn is not installed (optional denoiser)")
    rng = np.random.default_rng(1)
    H, W = 40, 50
    truth = np.tile(np.linspace(0.3, 0.9, W, dtype=np.float32), (H, 1))
    noisy = (rng.random((H, W, 8)) < truth[..., None]).mean(axis=2).astype(np.float32)  # 8 binary AO rays
    normal = np.zeros((H, W, 3), np.float32)
    normal[..., 2] = 1
    mask = np.zeros((H, W), bool)
    mask[5:35, 5:45] = True
    out = denoise_ao(noisy, normal, mask, method=method)
    assert out.dtype == np.float32 and out.min() >= 0 and out.max() <= 1
    np.testing.assert_array_equal(out[~mask], noisy[~mask])
    assert np.sqrt(np.mean((out[mask] - truth[mask]) ** 2)) < 0.5 * np.sqrt(np.mean((noisy[mask] - truth[mask]) ** 2))


def test_joint_bilateral_keeps_albedo_edges():
    H, W = 20, 20
    albedo = np.full((H, W, 3), 0.2, np.float32)
    albedo[:, 10:] = 0.9
    color = albedo * 1.5  # noise-free: uniform light
    normal = np.zeros((H, W, 3), np.float32)
    normal[..., 2] = 1
    np.testing.assert_allclose(joint_bilateral(color, albedo, normal), color, rtol=1e-5)


def test_denoise_rejects_unknown_method():
    z = np.zeros((4, 4, 3), np.float32)
    with pytest.raises(ValueError, match="denoise method"):
        denoise(z, z, z, np.ones((4, 4), bool), method="magic")


# --------------------------------------------------------------------------------------------------
# Stage
# --------------------------------------------------------------------------------------------------

def _make_run(run: Path, *, obj_id_in_frame: int = 1, photo_level: int | None = None) -> None:
    """A run folder with one ingested scene (a box room), a library of one sphere, one raster frame.

    ``photo_level``: the frame gets a uniform colour photo of that grey level (else none).
    """
    from pipeline.runfolder import save_scan
    from pipeline.objects import save_library
    from pipeline.scanformats.mesh import ply_bytes

    scene_dir = run / "ingest" / "room"
    rv, rf = box_room((-2, -2, 0), (2, 2, 2.5), n=6)
    col = np.full((len(rv), 3), 180, np.uint8)
    col[rv[:, 2] > 2.49] = 255  # clipped ceiling: detected as a light
    atomic_write_bytes(scene_dir / "room.ply", ply_bytes(rv, rf, col))
    W, H = 40, 30
    K = np.array([[36.0, 0, 19.5], [0, 36.0, 14.5], [0, 0, 1]])
    T = look_at((0, -1.8, 0.6), (0, 0, 0.25))
    color = ""
    if photo_level is not None:
        from pipeline.io import atomic_write_image

        color = str(scene_dir / "frame-000000.color.png")
        atomic_write_image(Path(color), np.full((H, W, 3), photo_level, np.uint8))
    scan = Scan(name="room", root=str(scene_dir), format="7scenes", frame_ids=np.arange(1), color_paths=(color,),
                depth_paths=("",), width=W, height=H, K=K[None], T_c2w=T[None], depth_width=W, depth_height=H,
                depth_K=K[None], depth_scale=0.001, depth_registered=True, up_w=np.array([0, 0, 1.0]),
                mesh_path=str(scene_dir / "room.ply"))
    save_scan(scene_dir, scan)
    v, f, n = uv_sphere(0.25, n_lat=16, n_lon=32)
    model = ObjectModel(obj_id=1, name="ball", source_path="", vertices=v, faces=f, normals=n,
                        vertex_colors=np.full((len(v), 3), 200, np.uint8), uv=None, texture=None)
    save_library(run / "ingest" / "objects", [model])
    # raster frame: labels from the true silhouette (ball resting on the floor)
    t_m2w = np.array([0.0, 0.0, 0.25])
    ob = ObjectInstance(vertices=v + t_m2w, faces=f, normals=n, albedo=np.ones((len(v), 3), np.float32))
    sc = build_scene(rv, rf, None, [ob])
    cam = Camera(K=K, T_c2w=T, width=W, height=H)
    o, d = cam.rays(np.arange(W * H), np.full((W * H, 2), 0.5))
    h = sc.intersector.intersect(o, d)
    labels = np.where(h.hit, sc.tri_inst[np.maximum(h.prim, 0)], 0).astype(np.uint16).reshape(H, W)
    T_w2c = np.linalg.inv(T)
    stem = run / "raster" / "room" / "drop0000" / "f000000"
    atomic_save_npz(stem.with_suffix(".npz"), labels=labels, depth=np.zeros((H, W), np.float32),
                    written_depth=np.zeros((H, W), np.float32))
    atomic_write_json(stem.with_suffix(".json"), {
        "status": "ok", "width": W, "height": H, "K": K.tolist(), "T_c2w": T.tolist(),
        "instances": [{"inst_id": 0, "obj_id": obj_id_in_frame, "R_m2c": T_w2c[:3, :3].tolist(),
                       "t_m2c": (T_w2c[:3, :3] @ t_m2w + T_w2c[:3, 3]).tolist(),
                       "R_m2w": np.eye(3).tolist(), "t_m2w": np.asarray(t_m2w, float).tolist()}]})


def _ctx(run: Path, **trace) -> StageContext:
    return StageContext(run_dir=run, cfg=build_config({"trace": trace}), stage="trace")


def test_stage_writes_every_pass_with_the_agreed_names_and_is_deterministic(tmp_path):
    from pipeline.trace.stage import STAGE

    run = tmp_path / "run"
    _make_run(run)
    ctx = _ctx(run, spp=8, shadow_samples=8)
    items = STAGE.plan(ctx)
    assert [it.key for it in items] == ["room/drop0000/f000000-f000000"] and items[0].data["frames"] == [0]
    res = STAGE.run_item(ctx, items[0])["frames"]["f000000"]
    out = FrameKey("room", 0, 0).path(run, TRACE_TPATH)
    a = load_npz(out)
    assert set(a) == {"pbr", "ao", "coverage", "shadow_ratio", "albedo", "normal", "spp", "exposure"}
    assert a["exposure"] == 1.0   # no photo: the mesh's own exposure
    labels = load_npz(run / "raster/room/drop0000/f000000.npz")["labels"]
    H, W = labels.shape
    assert a["pbr"].shape == (H, W, 3) and a["pbr"].dtype == np.float32
    for k in ("ao", "coverage", "shadow_ratio"):
        assert a[k].shape == (H, W) and a[k].dtype == np.float32
    from scipy.ndimage import binary_dilation

    band = binary_dilation(labels > 0, np.ones((3, 3), bool))
    assert (a["pbr"][~band] == 0).all() and (a["coverage"][~band] == 0).all()
    assert (a["coverage"][labels > 0] > 0.5).mean() > 0.9
    assert a["pbr"][labels > 0].mean() > 0.05 and np.isfinite(a["pbr"]).all()
    assert (a["ao"] == 1).all()   # the full blend (the default) does not read the AO pass: not traced
    assert (a["shadow_ratio"][labels > 0] == 1).all() and a["shadow_ratio"].min() < 0.9  # contact shadow
    assert res["object_px"] == int((labels > 0).sum()) and res["rays"] > 0
    first = out.read_bytes()
    STAGE.run_item(ctx, items[0])
    assert out.read_bytes() == first
    # the published blend (PBR x AO) reads it: traced
    pub = StageContext(run_dir=run, cfg=build_config({"trace": {"spp": 8, "shadow_samples": 8},
                                                      "composite": {"mode": "published"}}), stage="trace")
    STAGE.run_item(pub, items[0])
    ao = load_npz(out)["ao"]
    assert 0 <= ao.min() and ao.max() <= 1 and ao[labels > 0].mean() < 1  # the floor occludes


def test_stage_prefers_preps_room_trace_mesh(tmp_path):
    from pipeline.scanformats.mesh import ply_bytes
    from pipeline.runfolder import load_scan, room_trace_mesh
    from pipeline.trace.stage import STAGE

    run = tmp_path / "run"
    _make_run(run)
    scan = load_scan(run, "room")
    assert room_trace_mesh(run, scan) == scan.mesh_path
    rv, rf = box_room((-2, -2, 0), (2, 2, 2.5), n=2)
    atomic_write_bytes(run / "prep/room/room_trace.ply", ply_bytes(rv, rf, np.zeros((len(rv), 3), np.uint8)))
    assert room_trace_mesh(run, scan) == str(run / "prep/room/room_trace.ply")
    assert room_trace_mesh(run, scan, "ingest") == scan.mesh_path
    ctx = _ctx(run, spp=4, shadow_samples=0, ao_samples=0, env_radiance=0.0, denoise="off")
    STAGE.run_item(ctx, STAGE.plan(ctx)[0])
    a = load_npz(run / "trace/room/drop0000/f000000.npz")
    assert a["pbr"].max() == 0  # the black trace room lights nothing


def test_frames_are_chunked_into_items_and_the_chunking_does_not_change_the_bytes(tmp_path):
    """Items are chunks of trace.frames_per_item frames of one drop (load balance over workers); every
    frame's seed comes from its own name, so the chunk size cannot change what is written."""
    import shutil

    from pipeline.trace.stage import STAGE

    run = tmp_path / "run"
    _make_run(run)
    stem = run / "raster" / "room" / "drop0000" / "f000000"
    for k in (1, 2):
        for ext in (".npz", ".json"):
            shutil.copy(stem.with_suffix(ext), stem.with_name(f"f{k:06d}{ext}"))
    written = {}
    for n in (1, 2, 3):
        ctx = _ctx(run, spp=2, shadow_samples=2, frames_per_item=n)
        items = STAGE.plan(ctx)
        assert [len(it.data["frames"]) for it in items] == {1: [1, 1, 1], 2: [2, 1], 3: [3]}[n]
        assert sum((it.data["frames"] for it in items), []) == [0, 1, 2]
        for it in items:
            STAGE.run_item(ctx, it)
        written[n] = [FrameKey("room", 0, k).path(run, TRACE_TPATH).read_bytes() for k in range(3)]
    assert written[1] == written[2] == written[3]
    assert written[1][0] != written[1][1]  # frames draw their own samples


def test_the_largest_items_are_planned_first(tmp_path):
    """Workers take items in plan order: the short remainder chunks come last, where they fill the gaps a
    full chunk running alone at the end would leave (longest first; drop order among equals)."""
    import shutil

    from pipeline.trace.stage import STAGE

    run = tmp_path / "run"
    _make_run(run)
    src = run / "raster" / "room" / "drop0000"
    (run / "raster" / "room" / "drop0001").mkdir()
    for k in range(3):   # drop 0: one frame; drop 1: three
        for ext in (".npz", ".json"):
            shutil.copy((src / "f000000").with_suffix(ext), (src.parent / "drop0001" / f"f{k:06d}").with_suffix(ext))
    items = STAGE.plan(_ctx(run, frames_per_item=2))
    assert [it.key for it in items] == ["room/drop0001/f000000-f000001", "room/drop0000/f000000-f000000",
                                        "room/drop0001/f000002-f000002"]


def test_a_room_mesh_without_colours_is_traced_and_warmed(tmp_path):
    """A scan mesh without vertex colours (a bare reconstruction) plans, warms a worker and traces."""
    from pipeline.runfolder import load_scan
    from pipeline.scanformats.mesh import ply_bytes, read_room_ply
    from pipeline.trace import stage
    from pipeline.trace.stage import STAGE

    run = tmp_path / "run"
    _make_run(run)
    mesh = load_scan(run, "room").mesh_path
    rv, rf, _ = read_room_ply(mesh)
    atomic_write_bytes(mesh, ply_bytes(rv, rf, None))
    ctx = _ctx(run, spp=2, shadow_samples=2)
    stage.warm(ctx)
    assert stage._room_mesh(str(run), "room", "prep", stage._stamps(ctx, "room"))[3] is None
    STAGE.run_item(ctx, STAGE.plan(ctx)[0])
    assert load_npz(run / "trace/room/drop0000/f000000.npz")["pbr"].max() > 0


def test_stage_names_an_unknown_object_id(tmp_path):
    from pipeline.trace.stage import STAGE

    run = tmp_path / "run"
    _make_run(run, obj_id_in_frame=7)
    ctx = _ctx(run)
    with pytest.raises(InputError, match="object id 7"):
        STAGE.run_item(ctx, STAGE.plan(ctx)[0])


def test_stage_plans_nothing_without_raster_output(tmp_path):
    from pipeline.trace.stage import STAGE

    assert STAGE.plan(_ctx(tmp_path)) == []


def test_photo_lighting_lights_what_the_photos_see_clipped_and_is_off_with_zero_frames(tmp_path):
    from pipeline.trace.stage import STAGE

    out = {}
    for name, level, frames in (("none", None, 24), ("grey", 180, 24), ("clipped", 255, 24), ("off", 255, 0)):
        run = tmp_path / name
        _make_run(run, photo_level=level)
        ctx = _ctx(run, spp=8, shadow_samples=4, photo_frames=frames, lighting="scan")   # the scan mode's photo lights
        STAGE.run_item(ctx, STAGE.plan(ctx)[0])
        out[name] = FrameKey("room", 0, 0).path(run, TRACE_TPATH).read_bytes()
        a = load_npz(FrameKey("room", 0, 0).path(run, TRACE_TPATH))
        out[name + "_pbr"] = float(a["pbr"].mean())
        STAGE.run_item(ctx, STAGE.plan(ctx)[0])
        assert FrameKey("room", 0, 0).path(run, TRACE_TPATH).read_bytes() == out[name]   # deterministic
    # no photo, or photo lighting off: the mesh colours alone
    assert out["off"] == out["none"]
    # a photo the mesh agrees with (no clipping, the closed room leaves no hole) changes nothing either
    assert out["grey"] == out["none"]
    # every surface the photo saw is clipped: those become lights and the object gets brighter
    assert out["clipped_pbr"] > 1.5 * out["none_pbr"]


@pytest.mark.parametrize("level,want", [(180, 1.0), (104, 0.3033)])
def test_stage_measures_the_photos_exposure_against_the_mesh_colours(tmp_path, level, want):
    """Room mesh colour 180 everywhere but the clipped ceiling: a uniform photo of 180 is the mesh's exposure;
    one of 104 is darker by linear(104) / linear(180)."""
    from pipeline.color import srgb_to_linear
    from pipeline.trace.stage import STAGE

    run = tmp_path / "run"
    _make_run(run, photo_level=level)
    ctx = _ctx(run, spp=4, shadow_samples=0)
    STAGE.run_item(ctx, STAGE.plan(ctx)[0])
    exp = float(load_npz(FrameKey("room", 0, 0).path(run, TRACE_TPATH))["exposure"])
    ratio = float(srgb_to_linear(np.uint8(level)) / srgb_to_linear(np.uint8(180)))
    assert ratio == pytest.approx(want, abs=1e-3) and exp == pytest.approx(ratio, rel=1e-4)


def test_the_fits_cache_key_covers_every_module_the_fit_computes_with():
    """A resumed run reads back lights.npz only while the code that made it is unchanged: the key hashes
    every module of the lightfit package and every pipeline module they import (reading and writing files
    aside)."""
    import ast

    import pipeline
    from pipeline.trace import stage

    root = Path(pipeline.__file__).parent
    package = sorted((root / "trace" / "lightfit").glob("*.py"))
    own = {p.relative_to(root).as_posix() for p in package}
    used = {n.module for p in package for n in ast.walk(ast.parse(p.read_text()))
            if isinstance(n, ast.ImportFrom) and (n.module or "").startswith("pipeline.")}

    def source(module: str) -> str:
        rel = module.removeprefix("pipeline.").replace(".", "/")
        return f"{rel}/__init__.py" if (root / rel).is_dir() else f"{rel}.py"

    files = {source(m) for m in used} - {"io.py", "errors.py"}
    assert files and files <= set(stage.FIT_SOURCES)
    assert "trace/lightfit/fit.py" in own and own <= set(stage.FIT_SOURCES)
    assert all((root / f).is_file() for f in stage.FIT_SOURCES)


def test_fitted_lights_are_kept_per_scan_and_fitted_again_when_the_fit_changes(tmp_path, monkeypatch):
    from pipeline.runfolder import load_scan, room_trace_mesh
    from pipeline.scanformats.mesh import read_room_ply
    from pipeline.trace import stage
    from pipeline.trace.lightfit import RoomLights

    run = tmp_path / "run"
    _make_run(run, photo_level=150)
    cfg = _ctx(run, fit_points=400).cfg
    scan = load_scan(run, "room")
    rv, rf, rc = read_room_ply(room_trace_mesh(run, scan))
    stamps = stage._stamps(StageContext(run_dir=run, cfg=cfg, stage="trace"), "room")
    out = run / "trace" / "room" / "lights.npz"

    def fit():
        stage.room_lights(str(run), scan, rv, rf, rc, cfg.trace, 0, stamps)
        return RoomLights.load(out).summary["key"], out.stat().st_mtime_ns

    key, made = fit()
    assert fit() == (key, made)                    # read back, not fitted again
    monkeypatch.setattr(stage, "fit_code", lambda: "another version of the light fit")
    key2, made2 = fit()
    assert key2 != key and made2 != made           # an earlier version's lights are not read back
