"""Tests of pipeline/composite.py: the published and full blends, depth output, the stage.

Frames are built here analytically: a disk object whose coverage is its exact pixel area share (by
supersampling), a premultiplied radiance pass, and a textured photo.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline import camera_look as cl, color
from pipeline.composite import composite_full, composite_published, unpremultiply
from pipeline.runfolder import COMPOSITE_DEPTH_TPATH, COMPOSITE_TPATH, FrameKey

H, W = 60, 80


def _disk(cx: float, cy: float, r: float, h: int = H, w: int = W) -> tuple[np.ndarray, np.ndarray]:
    """Coverage (4x4 supersampled area share) and labels (pixel centre inside) of a disk."""
    s = (np.arange(4) + 0.5) / 4 - 0.5
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    cov = np.zeros((h, w))
    for dy in s:
        for dx in s:
            cov += ((xx + dx - cx) ** 2 + (yy + dy - cy) ** 2 <= r * r)
    cov /= 16.0
    labels = ((xx - cx) ** 2 + (yy - cy) ** 2 <= r * r).astype(np.uint16)
    return cov.astype(np.float32), labels


def _photo(h: int = H, w: int = W, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    base = 110 + 50 * np.sin(xx / 5.0) * np.cos(yy / 7.0)
    img = np.stack([base, base * 0.9, base * 0.8], axis=-1) + 2.0 * rng.standard_normal((h, w, 3))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _frame(cx=40.0, cy=30.0, r=12.0, colour=(0.5, 0.2, 0.1), h=H, w=W):
    cov, labels = _disk(cx, cy, r, h, w)
    pbr = np.asarray(colour, np.float32) * cov[..., None]
    sr = np.ones((h, w), np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    ring = (labels == 0) & ((xx - cx) ** 2 + (yy - cy - 4) ** 2 <= (r + 5) ** 2)
    sr[ring] = 0.6
    return pbr, cov, labels, sr


def _full(photo, pbr, cov, sr, labels, seed=0, **kw):
    kw.setdefault("blur_sigma", 0.0)
    kw.setdefault("noise_sigma", 0.0)
    return composite_full(photo, pbr, cov, sr, labels, rng=np.random.default_rng(seed), **kw)


# --------------------------------------------------------------------------------------------------
# Published
# --------------------------------------------------------------------------------------------------

def test_published_is_pbr_times_ao_inside_the_mask_and_the_photo_outside():
    photo = _photo()
    pbr, cov, labels, _ = _frame()
    ao = np.full((H, W), 0.8, np.float32)
    out = composite_published(photo, pbr, ao, labels > 0, coverage=cov)
    m = labels > 0
    assert np.array_equal(out[~m], photo[~m])
    want = color.encode_u8(np.array([0.5, 0.2, 0.1], np.float32) * 0.8)
    assert (out[m] == want).all()   # un-premultiplied: edge pixels are not darker than the interior


def test_published_with_an_empty_mask_is_the_photo():
    photo = _photo()
    pbr, cov, labels, _ = _frame()
    out = composite_published(photo, pbr, np.ones((H, W), np.float32), np.zeros((H, W), bool), coverage=cov)
    assert np.array_equal(out, photo)


# --------------------------------------------------------------------------------------------------
# Full
# --------------------------------------------------------------------------------------------------

def test_full_changes_only_the_objects_their_edge_band_and_their_shadows():
    photo = _photo()
    pbr, cov, labels, sr = _frame()
    res = _full(photo, pbr, cov, sr, labels)
    changed = (res.image != photo).any(axis=-1)
    from scipy.ndimage import binary_dilation

    allowed = binary_dilation(labels > 0, np.ones((3, 3), bool)) | (sr != 1)
    assert not (changed & ~allowed).any()
    interior = (cov == 1)
    assert (res.image[interior] == color.encode_u8(np.array([0.5, 0.2, 0.1], np.float32))).all()


def test_full_soft_edges_blend_by_coverage_in_linear_light():
    photo = np.full((H, W, 3), 200, np.uint8)
    pbr, cov, labels, _ = _frame(colour=(0.0, 0.0, 0.0))
    res = _full(photo, pbr, cov, np.ones((H, W), np.float32), labels)
    edge = (cov > 0.2) & (cov < 0.8)
    assert edge.any()
    want = color.encode_u8(color.decode_u8(photo)[edge] * (1 - cov[edge])[:, None])
    assert np.abs(res.image[edge].astype(int) - want.astype(int)).max() <= 1
    hard = _full(photo, pbr, cov, np.ones((H, W), np.float32), labels, soft_edges=False)
    assert set(np.unique(hard.image[..., 0])) <= {0, 200}
    assert np.array_equal(hard.image[..., 0] == 0, labels > 0)   # hard mask = the label mask


def test_white_object_beside_a_white_wall_has_the_walls_pixel_value():
    photo = np.full((H, W, 3), 230, np.uint8)
    lin = float(color.decode_u8(np.array([230], np.uint8))[0])
    pbr, cov, labels, _ = _frame(colour=(lin, lin, lin))
    res = _full(photo, pbr, cov, np.ones((H, W), np.float32), labels)
    assert (res.image == 230).all()
    # radiance_scale 2 in the tracer: the gain 1/2 brings it back
    res2 = _full(photo, pbr * 2, cov, np.ones((H, W), np.float32), labels, gain=0.5)
    assert (res2.image == 230).all()


def test_shadows_darken_the_room_by_the_ratio_in_linear_light():
    photo = _photo()
    pbr, cov, labels, sr = _frame()
    res = _full(photo, pbr, cov, sr, labels)
    ring = (sr < 1) & (cov == 0)
    want = color.encode_u8(color.decode_u8(photo)[ring] * 0.6)
    assert np.abs(res.image[ring].astype(int) - want.astype(int)).max() <= 1
    off = _full(photo, pbr, cov, sr, labels, shadows=False)
    assert np.array_equal(off.image[ring], photo[ring])


def _aa_texture(seed: int, h: int = H, w: int = W) -> np.ndarray:
    """(h, w) float64 gray levels: anti-aliased disks at random sub-pixel places (edges at every phase)."""
    rng = np.random.default_rng(seed)
    img = np.full((h, w), 120.0)
    for _ in range(14):
        cov, _ = _disk(rng.uniform(0, w), rng.uniform(0, h), rng.uniform(4, 14), h, w)
        img = img * (1 - cov) + rng.uniform(30, 230) * cov
    return img


def test_measured_blur_and_noise_follow_the_photo():
    rng = np.random.default_rng(3)
    lin = color.srgb_to_linear(np.round(_aa_texture(1)).astype(np.uint8)[..., None].repeat(3, -1))   # sharp room
    obj = color.srgb_to_linear(np.round(_aa_texture(2)).astype(np.uint8)[..., None].repeat(3, -1))
    _, cov, labels, _ = _frame(r=14.0)
    pbr = obj * cov[..., None]   # a textured object, as sharp as the tracer makes it
    sr = np.ones((H, W), np.float32)
    photo = color.encode_u8(cl.gaussian_blur(lin, 1.5))
    noisy = np.clip(np.round(photo + 4.0 * rng.standard_normal(photo.shape)), 0, 255).astype(np.uint8)
    res = composite_full(noisy, pbr, cov, sr, labels, rng=np.random.default_rng(0))
    assert 1.0 <= res.blur_sigma <= 2.0
    assert res.photo_noise == pytest.approx(4.0, rel=0.3)
    assert res.noise_added > 2.0
    sharp_res = composite_full(color.encode_u8(lin), pbr, cov, sr, labels, rng=np.random.default_rng(0))
    assert sharp_res.blur_sigma <= 0.6 and sharp_res.noise_added < 1.5


def test_full_is_deterministic_per_seed_and_the_seed_moves_only_object_pixels():
    photo = _photo()
    pbr, cov, labels, sr = _frame()
    a = _full(photo, pbr, cov, sr, labels, seed=5, noise_sigma=3.0)
    b = _full(photo, pbr, cov, sr, labels, seed=5, noise_sigma=3.0)
    c = _full(photo, pbr, cov, sr, labels, seed=6, noise_sigma=3.0)
    assert np.array_equal(a.image, b.image)
    diff = (a.image != c.image).any(axis=-1)
    assert diff.any() and not (diff & (cov == 0)).any()


# --------------------------------------------------------------------------------------------------
# Stability
# --------------------------------------------------------------------------------------------------

def _sane(res_img, photo):
    assert res_img.dtype == np.uint8 and res_img.shape == photo.shape


@pytest.mark.parametrize("mode", ["published", "full"])
def test_object_at_the_image_border(mode):
    photo = _photo()
    pbr, cov, labels, sr = _frame(cx=2.0, cy=57.0, r=10.0)
    if mode == "published":
        out = composite_published(photo, pbr, np.ones((H, W), np.float32), labels > 0, coverage=cov)
    else:
        out = composite_full(photo, pbr, cov, sr, labels, rng=np.random.default_rng(0)).image
    _sane(out, photo)
    assert (out[labels > 0] != photo[labels > 0]).any()


def test_fully_occluded_object_leaves_the_photo_and_masks_alone():
    photo = _photo()
    z = np.zeros((H, W), np.float32)
    res = composite_full(photo, np.zeros((H, W, 3), np.float32), z, np.ones((H, W), np.float32),
                         np.zeros((H, W), np.uint16), rng=np.random.default_rng(0))
    assert np.array_equal(res.image, photo) and res.noise_added == 0.0
    # the tracer covered pixels the raster hid (real-depth occlusion): they stay hidden
    pbr, cov, _, _ = _frame()
    res2 = composite_full(photo, pbr, cov, np.ones((H, W), np.float32), np.zeros((H, W), np.uint16),
                          rng=np.random.default_rng(0))
    assert np.array_equal(res2.image, photo)


def test_object_filling_the_frame():
    photo = _photo()
    cov = np.ones((H, W), np.float32)
    pbr = np.full((H, W, 3), 0.3, np.float32)
    res = composite_full(photo, pbr, cov, np.ones((H, W), np.float32), np.ones((H, W), np.uint16),
                         rng=np.random.default_rng(0))
    assert np.isfinite(res.photo_noise) and res.photo_noise >= 0
    assert (res.image == color.encode_u8(np.float32(0.3))).mean() > 0.5


@pytest.mark.parametrize("level", [0, 3, 252, 255])
def test_very_dark_and_saturated_photos(level):
    photo = np.full((H, W, 3), level, np.uint8)
    pbr, cov, labels, sr = _frame()
    res = composite_full(photo, pbr, cov, sr, labels, rng=np.random.default_rng(0))
    _sane(res.image, photo)
    obj = color.encode_u8(np.array([0.5, 0.2, 0.1], np.float32))
    assert np.abs(res.image[cov == 1].astype(int) - obj.astype(int)).max() <= 3
    if level >= 252:
        assert (res.image[sr < 1] < level).all()   # a shadow shows on a clipped white wall too


def test_nan_and_inf_in_the_passes_do_not_reach_the_image():
    photo = _photo()
    pbr, cov, labels, sr = _frame()
    pbr[30, 40] = np.nan
    pbr[31, 40] = np.inf
    cov = cov.copy()
    cov[29, 40] = np.nan
    sr = sr.copy()
    sr[5, 5] = np.nan
    sr[6, 6] = -np.inf
    res = composite_full(photo, pbr, cov, sr, labels, rng=np.random.default_rng(0))
    out = composite_published(photo, pbr, np.full((H, W), np.nan, np.float32), labels > 0, coverage=cov)
    _sane(res.image, photo)
    _sane(out, photo)


def test_shape_mismatch_is_an_error_naming_the_pass():
    photo = _photo()
    pbr, cov, labels, sr = _frame()
    with pytest.raises(ValueError, match="shadow_ratio"):
        composite_full(photo, pbr, cov, sr[:-1], labels, rng=np.random.default_rng(0))


def test_unpremultiply_fills_uncovered_mask_pixels_from_neighbours():
    pbr, cov, labels, _ = _frame()
    cov2 = cov.copy()
    cov2[30, 40] = 0.0
    pbr2 = pbr.copy()
    pbr2[30, 40] = 0.0
    col = unpremultiply(pbr2, cov2, np.zeros((H, W, 3), np.float32))
    assert np.allclose(col[30, 40], [0.5, 0.2, 0.1], atol=1e-5)
    assert np.allclose(col[0, 0], 0.0)


# --------------------------------------------------------------------------------------------------
# Stage
# --------------------------------------------------------------------------------------------------

def _make_run(run: Path, *, with_trace: bool = True, exposure: float | None = None) -> None:
    """Ingested scan (one frame, photo on disk, no depth), one raster frame and its trace passes."""
    from pipeline import annotate
    from pipeline.runfolder import save_scan
    from pipeline.io import atomic_save_npz, atomic_write_image, atomic_write_json
    from pipeline.types import Scan

    scene_dir = run / "ingest" / "room"
    photo = _photo(2 * H, 2 * W)   # the photo is at twice the raster resolution (raster.image_scale 0.5)
    atomic_write_image(scene_dir / "color0.png", photo)
    K = np.array([[60.0, 0, 39.5], [0, 60.0, 29.5], [0, 0, 1]])
    scan = Scan(name="room", root=str(scene_dir), format="7scenes", frame_ids=np.arange(1),
                color_paths=(str(scene_dir / "color0.png"),), depth_paths=("",), width=2 * W, height=2 * H,
                K=K[None], T_c2w=np.eye(4)[None], depth_width=2 * W, depth_height=2 * H, depth_K=K[None],
                depth_scale=0.001, depth_registered=True, up_w=np.array([0, 0, 1.0]),
                mesh_path=str(scene_dir / "room.ply"))
    save_scan(scene_dir, scan)
    pbr, cov, labels, sr = _frame()
    stem = run / "raster" / "room" / "drop0000" / "f000000"
    depth = np.where(labels > 0, 1.5, 0).astype(np.float32)
    atomic_save_npz(stem.with_suffix(".npz"), labels=labels, depth=depth,
                    amodal=annotate.pack_masks((labels > 0)[None]), visib=annotate.pack_masks((labels > 0)[None]),
                    written_depth=depth)
    atomic_write_json(stem.with_suffix(".json"), {"status": "ok", "scene": "room", "drop": 0, "frame": 0,
                                                  "width": W, "height": H, "K": K.tolist(),
                                                  "T_c2w": np.eye(4).tolist(), "instances": []})
    atomic_write_json(stem.parent / "f000001.json", {"status": "rejected", "reason": "too small"})
    if with_trace:
        extra = {} if exposure is None else {"exposure": np.float32(exposure)}
        atomic_save_npz(run / "trace/room/drop0000/f000000.npz", pbr=pbr, ao=np.ones((H, W), np.float32),
                        coverage=cov, shadow_ratio=sr, **extra)


def _ctx(run: Path, **composite):
    from pipeline.config import build_config
    from pipeline.stages import StageContext

    return StageContext(run_dir=run, cfg=build_config({"composite": composite}), stage="composite")


@pytest.mark.parametrize("mode", ["published", "full"])
def test_stage_writes_where_export_reads_deterministically(tmp_path, mode):
    from pipeline.composite import STAGE
    from pipeline.io import load_npz

    run = tmp_path / "run"
    _make_run(run)
    ctx = _ctx(run, mode=mode)
    items = STAGE.plan(ctx)
    assert [it.key for it in items] == ["room/drop0000/f000000"]
    before = (run / "raster/room/drop0000/f000000.json").read_bytes()
    res = STAGE.run_item(ctx, items[0])
    assert res["mode"] == mode
    png = FrameKey("room", 0, 0).path(run, COMPOSITE_TPATH)
    import cv2

    img = cv2.imread(str(png), cv2.IMREAD_COLOR)
    assert img.shape == (H, W, 3)
    d = load_npz(FrameKey("room", 0, 0).path(run, COMPOSITE_DEPTH_TPATH))["depth"]
    _, _, labels, _ = _frame()
    assert d.shape == (H, W) and (d[labels > 0] == 1.5).all() and (d[labels == 0] == 0).all()
    first = png.read_bytes()
    STAGE.run_item(ctx, items[0])
    assert png.read_bytes() == first
    assert (run / "raster/room/drop0000/f000000.json").read_bytes() == before   # annotations untouched


def test_stage_without_trace_output_names_the_fix(tmp_path):
    from pipeline.composite import STAGE
    from pipeline.errors import InputError

    run = tmp_path / "run"
    _make_run(run, with_trace=False)
    ctx = _ctx(run)
    with pytest.raises(InputError, match="trace"):
        STAGE.run_item(ctx, STAGE.plan(ctx)[0])


def test_stage_plans_nothing_without_raster(tmp_path):
    from pipeline.composite import STAGE

    assert STAGE.plan(_ctx(tmp_path)) == []


def test_config_rejects_unknown_mode():
    from pipeline.config import build_config
    from pipeline.errors import ConfigError

    with pytest.raises(ConfigError, match="mode"):
        build_config({"composite": {"mode": "magic"}})


def test_stage_on_the_trace_stages_real_output(tmp_path):
    """Trace stage -> composite stage on a tiny box room with a ball: the agreed names and shapes hold."""
    import dataclasses

    from pipeline.composite import STAGE
    from pipeline.config import build_config
    from pipeline.runfolder import load_scan, save_scan
    from pipeline.io import atomic_write_image
    from pipeline.stages import StageContext
    from pipeline.trace.stage import STAGE as TRACE
    from tests.pipeline.test_trace_stage import _make_run as make_trace_run

    run = tmp_path / "run"
    make_trace_run(run)
    scan = load_scan(run, "room")
    photo = _photo(scan.height, scan.width)
    atomic_write_image(run / "ingest/room/color0.png", photo)
    save_scan(run / "ingest/room", dataclasses.replace(scan, color_paths=(str(run / "ingest/room/color0.png"),)))
    cfg = build_config({"trace": {"spp": 4, "shadow_samples": 8}})
    tctx = StageContext(run_dir=run, cfg=cfg, stage="trace")
    TRACE.run_item(tctx, TRACE.plan(tctx)[0])
    ctx = StageContext(run_dir=run, cfg=cfg, stage="composite")
    res = STAGE.run_item(ctx, STAGE.plan(ctx)[0])
    import cv2

    img = cv2.imread(str(FrameKey("room", 0, 0).path(run, COMPOSITE_TPATH)), cv2.IMREAD_COLOR)[..., ::-1]
    labels = np.load(run / "raster/room/drop0000/f000000.npz")["labels"]
    assert img.shape == photo.shape and res["mode"] == "full"
    assert (img[labels > 0] != photo[labels > 0]).any(axis=-1).mean() > 0.9   # the ball is in the image
    far = np.ones(labels.shape, bool)
    far[max(0, np.nonzero(labels)[0].min() - 8):, :] = False   # rows well above the ball and its shadow
    assert np.array_equal(img[far], photo[far])


def test_blurred_contact_shadow_has_no_bright_rim_at_the_object():
    photo = np.full((H, W, 3), 200, np.uint8)
    dark = float(color.decode_u8(np.array([200], np.uint8))[0]) * 0.6   # the object is as dark as the shadow
    pbr, cov, labels, sr = _frame(colour=(dark, dark, dark))
    res = _full(photo, pbr, cov, sr, labels, blur_sigma=1.5)
    yy, xx = np.mgrid[0:H, 0:W]
    dist = np.hypot(xx - 40.0, yy - 30.0) - 12.0          # distance outside the disk's edge, pixels
    near = (dist > 0.5) & (dist < 3.0) & (np.hypot(xx - 40.0, yy - 34.0) < 13.5)   # well inside the ring
    shadowed = int(color.encode_u8(np.float32(dark)))
    assert near.any() and (np.abs(res.image[near].astype(int) - shadowed) <= 2).all()


@pytest.mark.parametrize("exposure", [0.5, float("nan")])
def test_stage_scales_the_objects_by_the_traced_exposure_in_full_mode_only(tmp_path, exposure):
    """The trace stage's per-frame exposure multiplies the objects' radiance (full mode, match_exposure);
    a bad value (NaN) counts as 1, as does a trace output without it."""
    import cv2

    from pipeline.composite import STAGE

    def run_one(name, **kw):
        run = tmp_path / name
        _make_run(run, exposure=kw.pop("exposure", None))
        ctx = _ctx(run, blur_sigma=0.0, noise_sigma=0.0, **kw)
        res = STAGE.run_item(ctx, STAGE.plan(ctx)[0])
        img = cv2.imread(str(FrameKey("room", 0, 0).path(run, COMPOSITE_TPATH)), cv2.IMREAD_COLOR).astype(float)
        return res, img

    _, _, labels, _ = _frame()
    inner = labels > 0
    res_none, none = run_one("none")
    res_e, with_e = run_one("e", exposure=exposure)
    _, off = run_one("off", exposure=exposure, match_exposure=False)
    _, pub = run_one("pub", exposure=exposure, mode="published")
    _, pub_none = run_one("pub_none", mode="published")
    assert np.array_equal(off, none) and np.array_equal(pub, pub_none)
    if np.isnan(exposure):
        assert res_e["exposure"] == 1.0 and np.array_equal(with_e, none)
    else:
        assert res_e["exposure"] == 0.5 and with_e[inner].mean() < 0.85 * none[inner].mean()


def test_contact_line_one_pixel_wide_keeps_its_strength_at_partly_covered_edge_pixels():
    # The dark line where an object meets the table is about a pixel wide and lies right at the object's
    # edge, where the pixels are partly covered. Their uncovered share shows the traced ratio there
    # (outside the label mask), or the nearest traced ratio (inside it, where the tracer wrote none),
    # not the mean of a wider window that reaches the unshadowed room (against Mitsuba, the light suite's
    # contact lines came out 25-35 gray levels too bright that way).
    photo = np.full((H, W, 3), 180, np.uint8)
    pbr, cov, labels, _ = _frame(colour=(0.3, 0.3, 0.3))
    yy, xx = np.mgrid[0:H, 0:W]
    ring = (labels == 0) & (np.hypot(xx - 40.0, yy - 30.0) < 13.5)   # the first unlabelled pixels around the disk
    sr = np.where(ring, np.float32(0.1), np.float32(1.0))
    res = _full(photo, pbr, cov, sr, labels)
    bg = float(color.decode_u8(np.array([180], np.uint8))[0])

    def expected(ratio):
        return color.encode_u8((0.3 * cov + (1 - cov) * bg * ratio).astype(np.float32))

    out_edge = ring & (cov > 0.05)               # partly covered, unlabelled: the traced ratio itself
    in_edge = (labels > 0) & (cov < 0.95)        # partly covered, labelled: filled from the ring beside them
    assert out_edge.sum() > 10 and in_edge.sum() > 10
    assert (np.abs(res.image[out_edge][:, 0].astype(int) - expected(0.1)[out_edge]) <= 1).all()
    assert (np.abs(res.image[in_edge][:, 0].astype(int) - expected(0.1)[in_edge]) <= 2).all()
