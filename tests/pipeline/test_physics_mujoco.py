"""Our engine against MuJoCo on scenes both can represent: a plane, boxes, spheres, convex hulls.

Final rest poses must agree within PHYS_MUJOCO_POS_TOL / PHYS_MUJOCO_ANGLE_TOL_DEG. MuJoCo is a test and
benchmark dependency only.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.physics import Body, box_body, build_model, make_state, sphere_body
from pipeline.physics.drop import DropSettings, run
from pipeline.physics.integrate import quat_to_mat
from pipeline.tolerances import PHYS_MUJOCO_ANGLE_TOL_DEG, PHYS_MUJOCO_POS_TOL

pytest.importorskip("mujoco", reason="the MuJoCo comparison needs the 'mujoco' package "
                                     "(test/benchmark dependency: pip install mujoco)")

from pipeline.physics.mjref import simulate_mujoco  # noqa: E402

FLOOR = np.array([[0.0, 0.0, 1.0, 0.0]])


def _prism(n=6, r=0.04, h=0.03, mass=0.3):
    """A convex n-gonal prism (not a box): a convex hull body with its exact mass properties."""
    import trimesh

    mesh = trimesh.creation.cylinder(radius=r, height=2 * h, sections=n)
    mp = mesh.mass_properties
    dens = mass / mp["volume"]
    return Body(vertices=np.asarray(mesh.vertices), mass=mass, com=np.asarray(mp["center_mass"]),
                inertia=np.asarray(mp["inertia"]) * dens)


def _compare(bodies, R, t, boxes):
    m = build_model(bodies, planes=FLOOR)
    s = make_state(m, R, t)
    ours = run(m, s, DropSettings(max_time=10.0))
    assert ours.verdict == "accepted"
    p, q, _ = simulate_mujoco(m, s, 4.0, boxes=boxes)
    Rb = quat_to_mat(q)
    R_mj = Rb @ m.body_R_m2b
    t_mj = np.einsum("bij,bj->bi", Rb, m.body_t_m2b) + p
    dpos = np.linalg.norm(t_mj - ours.t_m2w, axis=1)
    dang = np.degrees([Rotation.from_matrix(a.T @ b).magnitude() for a, b in zip(R_mj, ours.R_m2w)])
    assert np.all(dpos <= PHYS_MUJOCO_POS_TOL), dpos
    assert np.all(dang <= PHYS_MUJOCO_ANGLE_TOL_DEG), dang


def test_boxes_and_a_sphere_rest_where_mujoco_puts_them():
    h = np.array([0.05, 0.03, 0.02])
    R = Rotation.from_euler("xyz", [[4, 3, 20], [2, -3, 70], [0, 0, 0]], degrees=True).as_matrix()
    _compare([box_body(h, 0.5), box_body(h, 0.5), sphere_body(0.03, 0.2)], R,
             [[0, 0, 0.05], [0.3, 0, 0.1], [0.6, 0, 0.1]], boxes={0: h, 1: h})


def test_stack_of_boxes_matches_mujoco():
    h = np.array([0.05, 0.05, 0.05])
    R = Rotation.from_euler("z", [[0], [10], [25]], degrees=True).as_matrix()
    _compare([box_body(h, 1.0)] * 3, R, [[0, 0, 0.051], [0, 0, 0.152], [0, 0, 0.253]],
             boxes={0: h, 1: h, 2: h})


def test_convex_hulls_match_mujoco():
    R = Rotation.from_euler("xyz", [[5, 0, 0], [0, -4, 30]], degrees=True).as_matrix()
    _compare([_prism(6), _prism(8, r=0.05, h=0.02)], R, [[0, 0, 0.06], [0.3, 0, 0.05]], boxes={})
