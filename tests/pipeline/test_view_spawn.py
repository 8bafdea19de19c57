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
    vm = ViewMap(np.eye(3), 0.2, np.array([[0.1, 0.1], [1.1, 0.1]]), np.array([0.0, 3.0]), 3)
    rng = np.random.default_rng(0)
    assert all(np.allclose(sample_focus(vm, rng), [1.1, 0.1]) for _ in range(20))
    assert sample_focus(ViewMap(np.eye(3), 0.2, np.zeros((0, 2)), np.zeros(0), 0), rng) is None
    lo, hi = focus_bounds(np.array([1.0, -2.0]), 0.3, np.array([-5.0, -5, -1]), np.array([5.0, 5, 2]))
    np.testing.assert_allclose(lo, [0.7, -2.3, -1])
    np.testing.assert_allclose(hi, [1.3, -1.7, 2])
