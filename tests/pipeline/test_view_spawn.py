"""Spawn cells from the kept frames' depth: analytic floor and wall views."""

from __future__ import annotations

import numpy as np

from pipeline.view_spawn import ViewMap, focus_bounds, frame_support_points, sample_focus

K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])


def _look(R_c2w: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_c2w, t
    return T


def _plane_depth(T_c2w: np.ndarray, n: np.ndarray, d: float, H: int = 120, W: int = 160) -> np.ndarray:
    """Depth (z along the camera axis) of the plane n.x = d seen by the camera."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    rays_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    R, o = T_c2w[:3, :3], T_c2w[:3, 3]
    s = (d - n @ o) / (rays_c @ R.T @ n)
    return np.where(s > 0, s, 0).astype(np.float32)


def test_floor_seen_from_above_is_up_facing_at_its_height():
    # camera 1.5 m above the floor z = 0 (world z up), looking straight down (camera z -> world -z)
    R = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
    T = _look(R, np.array([0.3, -0.2, 1.5]))
    depth = _plane_depth(T, np.array([0, 0, 1.0]), 0.0)
    pts, nrm = frame_support_points(depth, K, T, stride=4, margin=0.15, max_depth=4.0)
    assert len(pts) > 100
    np.testing.assert_allclose(pts[:, 2], 0.0, atol=1e-9)
    np.testing.assert_allclose(nrm, np.tile([0, 0, 1.0], (len(nrm), 1)), atol=1e-9)
    # central window: 70 % of 160 px at 1.5 m / 100 px focal = 1.68 m wide around the camera's foot
    assert np.all(np.abs(pts[:, 0] - 0.3) <= 0.5 * 0.7 * 160 * 1.5 / 100 + 1e-9)


def test_wall_is_not_support_and_far_points_are_ignored():
    # camera looking horizontally (camera z -> world +x) at a wall x = 2
    R = np.array([[0, 0, 1.0], [-1, 0, 0], [0, -1, 0]])
    T = _look(R, np.array([0, 0, 1.2]))
    depth = _plane_depth(T, np.array([1.0, 0, 0]), 2.0)
    pts, nrm = frame_support_points(depth, K, T, stride=4, margin=0.15, max_depth=4.0)
    assert len(pts) > 100
    np.testing.assert_allclose(nrm @ [0, 0, 1.0], 0.0, atol=1e-9)     # no upward-facing point
    np.testing.assert_allclose(nrm, np.tile([-1.0, 0, 0], (len(nrm), 1)), atol=1e-9)  # faces the camera
    pts, _ = frame_support_points(depth, K, T, stride=4, margin=0.15, max_depth=1.9)
    assert len(pts) == 0


def test_sample_focus_follows_votes_and_bounds_are_centred():
    vm = ViewMap(np.eye(3), 0.2, np.array([[0.1, 0.1], [1.1, 0.1]]), np.array([0.0, 3.0]), 3,
                 np.array([0.0, 0.7]))
    rng = np.random.default_rng(0)
    assert all(sample_focus(vm, rng) == 1 for _ in range(20))
    assert sample_focus(ViewMap(np.eye(3), 0.2, np.zeros((0, 2)), np.zeros(0), 0, np.zeros(0)), rng) is None
    (lo, hi), z = focus_bounds(np.array([1.0, -2.0]), 0.3, np.array([-5.0, -5, -1]), np.array([5.0, 5, 2]),
                               (0.5, 0.65), lowest=0.0)
    np.testing.assert_allclose(lo, [0.7, -2.3, -1])
    np.testing.assert_allclose(hi, [1.3, -1.7, 2])
    assert z == (0.5, 0.65)          # a room's slab (0.5..0.95 m) is above the surface: left as it is


def test_slab_is_raised_above_the_surface_seen_on_a_low_capture():
    """A table cropped out of a scan: the heights span 0.45 m, the slab of that range (0.22..0.29 m) lies
    under the top of the clutter seen in the cell (0.35 m); it moves up, keeping its thickness."""
    room_lo, room_hi = np.array([-1.0, -1, 0.0]), np.array([1.0, 1, 0.45])
    (lo, hi), (f0, f1) = focus_bounds(np.zeros(2), 0.3, room_lo, room_hi, (0.5, 0.65), lowest=0.5)
    z0, z1 = lo[2] + f0 * (hi[2] - lo[2]), lo[2] + f1 * (hi[2] - lo[2])
    np.testing.assert_allclose([z0, z1], [0.5, 0.5 + 0.15 * 0.45])
    assert lo[2] == 0.0              # the spawn check still looks for the surface down to the floor


def test_view_map_records_the_highest_surface_of_a_cell(tmp_path):
    """A floor at 0 and a box top at 0.4 m, seen from above: the cells over the box report its top."""
    import cv2

    from pipeline.scanformats.detect import read_scan
    from pipeline.view_spawn import view_map

    R = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])
    T = _look(R, np.array([0.0, 0.0, 1.5]))
    depth = _plane_depth(T, np.array([0, 0, 1.0]), 0.0)
    box = _plane_depth(T, np.array([0, 0, 1.0]), 0.4)
    v, u = np.mgrid[0:120, 0:160]
    inside = (np.abs(u - 80) < 30) & (np.abs(v - 60) < 30)
    depth = np.where(inside, box, depth)
    root = tmp_path / "scan"                # one frame in the 7-Scenes layout
    root.mkdir()
    np.savetxt(root / "camera-intrinsics.txt", K)
    np.savetxt(root / "frame-000000.pose.txt", T)
    cv2.imwrite(str(root / "frame-000000.depth.png"), np.round(depth * 1000).astype(np.uint16))
    cv2.imwrite(str(root / "frame-000000.color.png"), np.full((120, 160, 3), 128, np.uint8))
    scan = read_scan(root)
    vm = view_map(scan, [0], np.eye(3), cell=0.2, stride=2)
    centre = np.argmin(np.linalg.norm(vm.centers - [0.1, 0.1], axis=1))
    corner = np.argmax(np.linalg.norm(vm.centers, axis=1))
    assert abs(vm.top[centre] - 0.4) < 0.01 and abs(vm.top[corner]) < 0.01, (vm.top, vm.centers)
    # a mesh holding only the box (its floor cropped away): the floor the depth sees does not vote
    box_only = view_map(scan, [0], np.eye(3), cell=0.2, stride=2,
                        surface_distance=lambda p: np.where(p[:, 2] > 0.2, 0.0, 1.0))
    assert 0 < len(box_only.score) < len(vm.score) and np.all(np.abs(box_only.top - 0.4) < 0.01)
