"""Our engine against MuJoCo on scenes both can represent: a plane, boxes, spheres, convex hulls.

Final rest poses must agree within PHYS_MUJOCO_POS_TOL / PHYS_MUJOCO_ANGLE_TOL_DEG. MuJoCo is a test and
benchmark dependency only.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.physics import Body, Options, box_body, build_model, make_state, sphere_body, step
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


def _compare(bodies, R, t, boxes, opt=None):
    m = build_model(bodies, planes=FLOOR, opt=opt or Options())
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


def _sink_mujoco(model, state, v0, seconds=1.0):
    """Deepest sink (m, lowest com height minus the rest-free height) and final com height of body 0
    in MuJoCo at 2 ms, started with vertical velocity ``-v0``."""
    import mujoco

    from pipeline.physics.mjref import mjcf

    mm = mujoco.MjModel.from_xml_string(mjcf(model, state, timestep=0.002))
    d = mujoco.MjData(mm)
    d.qvel[2] = -v0
    zs = []
    for _ in range(int(seconds / 0.002)):
        mujoco.mj_step(mm, d)
        zs.append(d.qpos[2])
    return min(zs), zs[-1]


@pytest.mark.parametrize("v0", [1.0, 2.0])
def test_soft_impact_sinks_and_springs_back_like_mujoco(v0):
    """Options.soft_impact follows MuJoCo's continuous soft contact through an impact (the ball sinks
    ~v0 tc / e and springs back; implicit reference acceleration at dt 0.02 sinks 65-80 % as deep as
    MuJoCo at 2 ms); the default stops the ball at the surface. Both rest at MuJoCo's height."""
    r = 0.03
    lows, finals = {}, {}
    for soft in (False, True):
        m = build_model([sphere_body(r, 0.2)], planes=FLOOR, opt=Options(soft_impact=soft))
        s = make_state(m, np.eye(3)[None], [[0, 0, r + 0.001]], vel=[[0, 0, -v0]])
        zs = []
        for _ in range(50):
            s = step(m, s)
            zs.append(s.pos[0, 2])
        lows[soft], finals[soft] = min(zs), zs[-1]
    low_mj, final_mj = _sink_mujoco(m, make_state(m, np.eye(3)[None], [[0, 0, r + 0.001]]), v0)
    sink_mj = r - low_mj
    assert sink_mj > 0.01 * v0                                   # MuJoCo's soft impact: ~15 mm per m/s
    assert 0.6 * sink_mj <= r - lows[True] <= 1.1 * sink_mj
    assert r - lows[False] <= 1e-3
    for soft in (False, True):
        assert abs(finals[soft] - final_mj) <= 2e-4


def test_dropped_boxes_and_prisms_match_mujoco_with_soft_impact():
    """Bodies dropped 8 cm, tilted: the rest pose depends on the impact, which soft_impact follows."""
    h = np.array([0.04, 0.03, 0.025])
    R = Rotation.from_euler("xyz", [[3, -4, 30], [-2, 3, 34], [4, 1, 28]], degrees=True).as_matrix()
    _compare([box_body(h, 0.3), _prism(7, r=0.045, h=0.02, mass=0.25), box_body(h[::-1], 0.4)], R,
             [[0, 0, 0.08], [0.25, 0, 0.08], [0.5, 0, 0.08]], boxes={0: h, 2: h[::-1]},
             opt=Options(soft_impact=True))
