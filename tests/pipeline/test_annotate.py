"""Annotation helpers on tiny hand-made arrays: invariants, BOP conventions, dtypes."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline import annotate
from pipeline.camera import Camera


def test_poses_m2c_composes_rigid_transforms():
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    R_c2w = Rotation.random(random_state=1).as_matrix()
    T_c2w = annotate.rigid(R_c2w, [1.0, 2.0, 3.0])
    R_m2w = Rotation.random(3, random_state=2).as_matrix()
    t_m2w = rng.normal(size=(3, 3))
    R, t = Camera(K=np.eye(3), T_c2w=T_c2w, width=1, height=1).poses_m2c(R_m2w, t_m2w)
    p_m = rng.normal(size=3)
    for i in range(3):
        p_w = R_m2w[i] @ p_m + t_m2w[i]
        p_c = np.linalg.inv(T_c2w) @ np.append(p_w, 1.0)
        assert np.allclose(R[i] @ p_m + t[i], p_c[:3])


def test_projected_window_contains_projection_and_is_clipped():
    K = np.array([[100.0, 0, 49.5], [0, 100.0, 39.5], [0, 0, 1]])
    cube = np.array([[x, y, z] for x in (-0.1, 0.1) for y in (-0.1, 0.1) for z in (-0.1, 0.1)])
    w = annotate.projected_window(K, np.eye(3), np.array([0, 0, 2.0]), cube, 100, 80, 0.01)
    # u = 49.5 +- 100 * 0.1 / 1.9 = 44.24 .. 54.76 -> pixel centres 45 .. 54 (+1 px margin)
    assert w == (44, 34, 56, 46)
    assert annotate.window_area_in_image(w, 100, 80) == 12 * 12
    # far to the right: clipped to the canvas [-W, 2W)
    w = annotate.projected_window(K, np.eye(3), np.array([50.0, 0, 2.0]), cube, 100, 80, 0.01)
    assert w is None
    # behind the camera
    assert annotate.projected_window(K, np.eye(3), np.array([0, 0, -2.0]), cube, 100, 80, 0.01) is None
    # crossing the near plane: unbounded projection -> whole canvas
    assert annotate.projected_window(K, np.eye(3), np.array([0, 0, 0.05]), cube, 100, 80, 0.01) == \
        annotate.canvas(100, 80)


def test_split_window():
    assert annotate.split_window((10, 10, 20, 20), 100, 80) == ((10, 10, 20, 20), [])
    assert annotate.split_window((-5, 10, 20, 20), 100, 80) == ((0, 10, 20, 20), [(-5, 10, 0, 20)])
    inside, out = annotate.split_window(annotate.canvas(100, 80), 100, 80)
    assert inside == (0, 0, 100, 80)
    area = sum((r[2] - r[0]) * (r[3] - r[1]) for r in out)
    assert area == 300 * 240 - 100 * 80  # disjoint cover of the canvas minus the image
    assert annotate.split_window((120, -30, 150, -10), 100, 80) == (None, [(120, -30, 150, -10)])
    assert annotate.split_window(None, 100, 80) == (None, [])


def test_compose_front_crops_equals_full_composition():
    rng = np.random.default_rng(4)
    full = np.zeros((4, 20, 30), np.float32)
    crops = []
    for i in range(4):
        x0, y0 = rng.integers(0, 20), rng.integers(0, 12)
        d = (rng.random((8, 10)) * (rng.random((8, 10)) > 0.3)).astype(np.float32)
        d[0, 0] = 0.5  # exact ties between instances
        full[i, y0:y0 + 8, x0:x0 + 10] = d
        crops.append((d, int(x0), int(y0)))
    crops.append(None)
    full = np.concatenate([full, np.zeros((1, 20, 30), np.float32)])
    a = annotate.compose_front(full)
    b = annotate.compose_front_crops(crops, 30, 20)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_compose_front_nearest_wins_and_ties_go_to_lower_index():
    d = np.zeros((3, 2, 3), np.float32)
    d[0, 0, :] = 2.0
    d[1, 0, 1:] = 1.0
    d[2, 0, 2] = 1.0  # tie with instance 1
    d[2, 1, 0] = 5.0
    depth, front = annotate.compose_front(d)
    assert front.dtype == np.uint16
    assert front.tolist() == [[1, 2, 2], [3, 0, 0]]
    assert depth.tolist() == [[2.0, 1.0, 1.0], [5.0, 0.0, 0.0]]
    depth, front = annotate.compose_front(np.zeros((0, 2, 2), np.float32))
    assert front.shape == (2, 2) and not front.any()


def test_visible_labels_room_and_real_depth():
    depth = np.full((1, 5), 2.0, np.float32)
    front = np.ones((1, 5), np.uint16)
    room = np.array([[0.0, 1.0, 3.0, 3.0, 3.0]], np.float32)
    real = np.array([[0.0, 0.0, 1.0, 1.98, 0.0]], np.float32)
    v = annotate.visible_labels(depth, front, room, real, tol_abs=0.02, tol_rel=0.01)
    # 0: nothing behind -> visible; 1: behind room; 2: behind real depth; 3: real within tolerance; 4: real invalid
    assert v.labels.tolist() == [[1, 0, 0, 1, 1]]
    assert v.occluded_by_room.tolist() == [[False, True, False, False, False]]
    assert v.occluded_by_real.tolist() == [[False, False, True, False, False]]
    v = annotate.visible_labels(depth, front, room, None, tol_abs=0.02, tol_rel=0.01)
    assert v.labels.tolist() == [[1, 0, 1, 1, 1]]


def test_bbox_and_union():
    m = np.zeros((6, 8), bool)
    assert annotate.bbox_xywh(m) is None
    m[2:4, 3:7] = True
    assert annotate.bbox_xywh(m) == (3, 2, 4, 2)
    assert annotate.bbox_xywh(m, -8, 10) == (-5, 12, 4, 2)
    assert annotate.union_box((0, 0, 2, 2), (5, 5, 1, 1)) == (0, 0, 6, 6)
    assert annotate.union_box(None, (5, 5, 1, 1)) == (5, 5, 1, 1)


@pytest.mark.parametrize("w", [1, 7, 8, 13])
def test_pack_unpack_roundtrip(w):
    m = np.random.default_rng(w).random((3, 5, w)) > 0.5
    p = annotate.pack_masks(m)
    assert p.dtype == np.uint8 and p.shape == (3, 5, (w + 7) // 8)
    assert np.array_equal(annotate.unpack_masks(p, w), m)


def _masks(labels: np.ndarray, n: int) -> np.ndarray:
    return np.stack([labels == i + 1 for i in range(n)])


def test_instance_annotations_follow_bop_definitions():
    h, w = 10, 10
    amodal = np.zeros((2, h, w), bool)
    amodal[0, 2:6, 2:6] = True   # 16 px, 4 more outside the image
    amodal[1, 0:2, 0:2] = True   # fully hidden
    labels = np.zeros((h, w), np.uint16)
    labels[2:6, 2:4] = 1         # 8 visible px of instance 0
    valid = np.ones((h, w), bool)
    valid[5, :] = False
    anns = annotate.instance_annotations(
        obj_ids=np.array([7, 9]), R_m2c=np.repeat(np.eye(3)[None], 2, 0), t_m2c=np.zeros((2, 3)),
        amodal=amodal, px_outside=np.array([4, 0]), box_outside=[(-2, 2, 2, 2), None], visib=_masks(labels, 2),
        valid_depth=valid, visib_threshold=0.3)
    a, b = anns
    assert a["obj_id"] == 7 and a["px_count_all"] == 20 and a["px_count_visib"] == 8
    assert a["px_count_valid"] == 12
    assert a["visib_fract"] == pytest.approx(0.4) and a["visible"] is True
    assert a["bbox_obj"] == [-2, 2, 8, 4] and a["bbox_visib"] == [2, 2, 2, 4]
    assert b["px_count_visib"] == 0 and b["visib_fract"] == 0.0 and b["visible"] is False
    assert b["bbox_obj"] == [-1, -1, -1, -1] and b["bbox_visib"] == [-1, -1, -1, -1]
    anns = annotate.instance_annotations(
        obj_ids=np.array([7]), R_m2c=np.eye(3)[None], t_m2c=np.zeros((1, 3)), amodal=amodal[:1],
        px_outside=np.array([4]), box_outside=[None], visib=_masks(labels, 1), valid_depth=valid,
        visib_threshold=0.5)
    assert anns[0]["visible"] is False


def test_compose_depth():
    labels = np.array([[0, 1]], np.uint16)
    depth = np.array([[0.0, 1.5]], np.float32)
    bg = np.array([[2.0, 3.0]], np.float32)
    assert annotate.compose_depth(labels, depth, bg).tolist() == [[2.0, 1.5]]
    assert annotate.compose_depth(labels, depth, None).tolist() == [[0.0, 1.5]]


def test_written_depth_fills_from_the_room_only_where_the_room_hides_an_object():
    labels = np.array([[1, 0, 0, 0]], np.uint16)
    obj = np.array([[1.0, 2.0, 0.0, 0.0]], np.float32)           # px 1: an object the room hides
    real = np.array([[0.0, 0.0, 0.0, 3.0]], np.float32)          # the sensor saw only px 3
    room = np.array([[2.5, 1.5, 2.2, 2.9]], np.float32)
    hidden = np.array([[False, True, False, False]])
    d = annotate.written_depth(labels, obj, real, room, hidden, fill_room=False)
    assert d.tolist() == [[1.0, 1.5, 0.0, 3.0]]
    d = annotate.written_depth(labels, obj, real, room, hidden, fill_room=True)
    assert d.tolist() == [[1.0, 1.5, pytest.approx(2.2), 3.0]]


def test_quantize_depth_is_what_the_png_stores():
    """At depth_scale 0.1 mm (BOP's train_pbr) uint16 ends at 6.5535 m: beyond, the PNG stores 0."""
    from pipeline.export_bop import depth_png

    d = np.array([[0.0, 0.00004, 1.23444, 6.5535, 6.5536, 7.0]], np.float32)
    q = annotate.quantize_depth(d, 0.1)
    assert q[0].tolist() == pytest.approx([0.0, 0.0, 1.2344, 6.5535, 0.0, 0.0], abs=1e-6)
    assert np.array_equal(np.round(q * 10000).astype(np.uint16), depth_png(d, 0.1))
    assert annotate.quantize_depth(d, 1.0)[0].tolist() == pytest.approx([0, 0, 1.234, 6.554, 6.554, 7.0], abs=1e-6)


def test_bop_visib_masks_follow_bop19():
    """Visible within delta behind the written depth, or where the depth is missing; distances, not z."""
    K = np.array([[100.0, 0, 0.5], [0, 100.0, 0.5], [0, 0, 1]])
    obj = np.full((2, 2), 1.0, np.float32)
    written = np.array([[1.0, 0.99], [0.98, 0.0]], np.float32)    # 0, 10 mm, 20 mm in front; missing
    m = annotate.bop_visib_masks([(obj, 0, 0)], (2, 2), 1, written, K, 0.015)
    assert m[0].tolist() == [[True, True], [False, True]]
    m = annotate.bop_visib_masks([None], (2, 2), 1, written, K, 0.015)
    assert not m.any()

