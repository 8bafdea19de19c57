"""Analytic tests of the physics engine (pipeline/physics): each sub-step, then whole scenes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.errors import InputError
from pipeline.physics import Body, Options, box_body, build_model, make_state, model_poses, sphere_body, step
from pipeline.physics.ccd import advance
from pipeline.physics.io import room_from_arrays
from pipeline.physics.collide import collide, room_distance
from pipeline.physics.drop import DropSettings, run, simulate_drop
from pipeline.physics.integrate import inertia_world, mat_to_quat, quat_to_mat
from pipeline.physics.solve import project_cone, solve_contacts
from pipeline.physics.step import external, penetration
from pipeline.tolerances import PHYS_REST_HEIGHT_TOL

G = 9.81
FLOOR = np.array([[0.0, 0.0, 1.0, 0.0]])
NO_SLEEP = Options(sleep_time=1e9)


@pytest.fixture(autouse=True)
def _one_blas_thread():
    # the tests step directly; drop.run does this itself (threaded BLAS on small matrices is slow)
    from pipeline.threads import one_blas_thread

    with one_blas_thread():
        yield


def _run(model, state, seconds):
    for _ in range(int(round(seconds / model.opt.timestep))):
        state = step(model, state)
    return state


def _sheet_room(half=0.5, spacing=0.02):
    """A zero-thickness horizontal sheet at z = 0 as an unsigned distance grid (open, one-sided)."""
    ax = np.arange(-half, half + 1e-9, spacing)
    _, _, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    return room_from_arrays({"origin": np.full(3, -half), "spacing": spacing, "udf": np.abs(Z).astype(np.float32)})


def _box_room(size=(2.0, 2.0, 2.0), spacing=0.04, hole=None):
    """Floor and four walls (no ceiling) as a distance grid; ``hole`` = (x0, x1, y0, y1) cut in the floor."""
    xs, ys, zs = (np.arange(0, s + 1e-9, spacing) for s in size)
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    if hole is None:
        floor = Z
    else:
        x0, x1, y0, y1 = hole
        dx = np.maximum(np.maximum(x0 - X, X - x1), 0)
        dy = np.maximum(np.maximum(y0 - Y, Y - y1), 0)
        inside = (dx == 0) & (dy == 0)
        edge = np.minimum.reduce([np.abs(X - x0), np.abs(X - x1), np.abs(Y - y0), np.abs(Y - y1)])
        floor = np.where(inside, np.sqrt(edge ** 2 + Z ** 2), Z)
    udf = np.minimum.reduce([floor, X, size[0] - X, Y, size[1] - Y])
    return room_from_arrays({"origin": np.zeros(3), "spacing": spacing, "udf": udf.astype(np.float32)})


def _energy(model, state):
    R = quat_to_mat(state.quat)
    L = np.einsum("bij,bj->bi", inertia_world(R, model.body_inertia), state.angvel)
    ke = 0.5 * np.sum(model.body_mass * np.sum(state.vel ** 2, 1)) + 0.5 * np.sum(state.angvel * L)
    pe = -np.sum(model.body_mass * (state.pos @ np.asarray(model.opt.gravity)))
    return ke + pe


# --- model and types -------------------------------------------------------------------------------

def test_build_model_rejects_bad_bodies():
    good = box_body([0.1, 0.1, 0.1], 1.0)
    with pytest.raises(InputError, match="mass"):
        build_model([dataclasses.replace(good, mass=-1.0)])
    with pytest.raises(InputError, match="positive definite"):
        build_model([dataclasses.replace(good, inertia=-np.eye(3))])
    with pytest.raises(InputError, match="triangle"):
        build_model([dataclasses.replace(good, inertia=np.diag([1.0, 1.0, 5.0]))])
    flat = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    with pytest.raises(InputError, match="no volume"):
        build_model([dataclasses.replace(good, vertices=flat)])
    with pytest.raises(InputError, match="non-finite"):
        build_model([dataclasses.replace(good, com=np.array([np.nan, 0, 0]))])
    with pytest.raises(InputError, match="udf"):
        build_model([good], room=room_from_arrays({"origin": np.zeros(3), "spacing": 0.1, "udf": np.zeros((4, 4))}))


def test_model_is_frozen_and_poses_round_trip():
    body = Body(vertices=np.random.default_rng(0).normal(size=(30, 3)) * 0.1, mass=2.0,
                com=np.array([0.01, -0.02, 0.03]), inertia=np.diag([0.01, 0.02, 0.025]) + 0.001)
    m = build_model([body])
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.room_spacing = 1.0
    R = Rotation.from_euler("xyz", [[10, 20, 30]], degrees=True).as_matrix()
    t = np.array([[0.1, 0.2, 0.3]])
    s = make_state(m, R, t)
    R2, t2 = model_poses(m, s)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(t2, t, atol=1e-12)
    # body frame origin is the com
    np.testing.assert_allclose(s.pos[0], R[0] @ body.com + t[0], atol=1e-12)


def test_quaternion_matrix_round_trip():
    R = Rotation.random(50, random_state=1).as_matrix()
    np.testing.assert_allclose(quat_to_mat(mat_to_quat(R)), R, atol=1e-12)


# --- integration -----------------------------------------------------------------------------------

def test_free_flight_conserves_momentum_and_energy():
    m = build_model([box_body([0.1, 0.05, 0.02], 2.0)], opt=Options(gravity=(0.0, 0.0, 0.0)))
    s = make_state(m, np.eye(3)[None], [[0, 0, 0]], vel=[[1.0, 2.0, 3.0]], angvel=[[3.0, 0.2, 5.0]])
    L0 = inertia_world(quat_to_mat(s.quat), m.body_inertia)[0] @ s.angvel[0]
    E0 = _energy(m, s)
    for _ in range(200):
        s = step(m, s)
        L = inertia_world(quat_to_mat(s.quat), m.body_inertia)[0] @ s.angvel[0]
        np.testing.assert_allclose(L, L0, rtol=1e-12, atol=1e-15)
        assert abs(_energy(m, s) - E0) < 1e-4 * E0
    np.testing.assert_allclose(s.vel[0], [1, 2, 3], rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.pos[0], np.array([1, 2, 3]) * 200 * 0.02, rtol=1e-12)


def test_free_fall_is_semi_implicit_euler():
    m = build_model([sphere_body(0.1, 1.0)])
    s = make_state(m, np.eye(3)[None], [[0, 0, 10.0]])
    n, dt = 50, m.opt.timestep
    s = _run(m, s, n * dt)
    # semi-implicit Euler: z_n = z0 - g dt^2 n (n + 1) / 2, within g t dt / 2 of 1/2 g t^2
    assert s.pos[0, 2] == pytest.approx(10 - G * dt * dt * n * (n + 1) / 2, abs=1e-9)
    assert abs(s.pos[0, 2] - (10 - 0.5 * G * (n * dt) ** 2)) <= 0.5 * G * n * dt * dt + 1e-9
    np.testing.assert_allclose(s.vel[0], [0, 0, -G * n * dt], atol=1e-9)


# --- collision -------------------------------------------------------------------------------------

def test_collide_box_on_plane_gives_four_face_contacts():
    m = build_model([box_body([0.1, 0.1, 0.05], 1.0)], planes=FLOOR)
    s = make_state(m, np.eye(3)[None], [[0, 0, 0.05]])
    c = collide(m, s)
    assert 4 <= c.count <= m.opt.contacts_per_pair
    np.testing.assert_allclose(c.dist, 0, atol=1e-12)
    np.testing.assert_allclose(c.normal, np.tile([0, 0, 1.0], (c.count, 1)))
    assert set(c.body_b) == {-1}
    # contact reduction keeps the support polygon: all four corners are among the points
    corners = {(sx, sy) for sx in (-0.1, 0.1) for sy in (-0.1, 0.1)}
    assert corners <= {tuple(np.round(p[:2], 9)) for p in c.pos}


def test_collide_stacked_boxes_use_the_shared_face_normal():
    m = build_model([box_body([0.05] * 3, 1.0)] * 2)
    s = make_state(m, np.repeat(np.eye(3)[None], 2, 0), [[0, 0, 0.05], [0.01, 0, 0.15]])
    c = collide(m, s)
    touching = np.abs(c.dist) < 1e-9
    assert touching.sum() >= 4
    # the touching points push along z, from b to a; the others are speculative (further than 0)
    np.testing.assert_allclose(np.abs(c.normal[touching, 2]), 1.0)
    up = np.where(s.pos[c.body_a, 2] > s.pos[c.body_b, 2], 1, -1)
    assert np.all(np.sign(c.normal[touching, 2]) == up[touching])
    assert np.all(c.dist[~touching] > 0.005)


def test_collide_far_bodies_make_no_contacts():
    m = build_model([box_body([0.05] * 3, 1.0)] * 2, planes=FLOOR)
    s = make_state(m, np.repeat(np.eye(3)[None], 2, 0), [[0, 0, 1.0], [1.0, 0, 1.0]])
    assert collide(m, s).count == 0


def test_room_distance_and_normal_on_both_sides_of_a_thin_sheet():
    m = build_model([sphere_body(0.01, 1.0)], room=_sheet_room())
    pts = np.array([[0.013, 0.0, 0.1], [0.0, 0.02, -0.07], [2.0, 0, 0]])
    d, g = room_distance(m, pts)
    assert d[0] == pytest.approx(0.1, abs=1e-6)
    assert d[1] == pytest.approx(0.07, abs=1e-6)
    assert d[2] == np.inf
    np.testing.assert_allclose(g[0], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(g[1], [0, 0, -1], atol=1e-6)


# --- solver ----------------------------------------------------------------------------------------

def test_project_cone():
    p = np.array([[-1.0, 0.5, 0], [1.0, 3.0, 4.0], [1.0, 0.1, 0.1]])
    q = project_cone(p, np.array([0.5, 0.5, 0.5]))
    np.testing.assert_allclose(q[0], 0)
    np.testing.assert_allclose(q[1], [1.0, 0.3, 0.4])
    np.testing.assert_allclose(q[2], p[2])


def test_solve_resting_box_carries_its_weight():
    m = build_model([box_body([0.1, 0.1, 0.05], 2.0)], planes=FLOOR, opt=NO_SLEEP)
    s = make_state(m, np.eye(3)[None], [[0, 0, 0.05]])
    s = _run(m, s, 1.0)                      # settle into the soft contact
    c = collide(m, s)
    res = solve_contacts(m, s, external(m, s), c)
    assert res.impulse[:, 0].sum() == pytest.approx(2.0 * G * m.opt.timestep, rel=1e-3)
    assert np.all(np.linalg.norm(res.impulse[:, 1:], axis=1) <= c.friction * res.impulse[:, 0] + 1e-12)
    assert np.linalg.norm(res.vel) < 1e-3     # m/s, far below the sleep threshold


def test_direct_solve_at_rest_matches_the_iterations():
    # a resting stack: the active-set solve from the warm start is exact (no iteration) and gives the
    # velocities the projected-gradient iterations converge to from zero
    from pipeline.physics.step import warm_start

    m = build_model([box_body([0.05] * 3, 1.0)] * 3, planes=FLOOR, opt=NO_SLEEP)
    s = make_state(m, np.repeat(np.eye(3)[None], 3, 0), [[0, 0, 0.05], [0, 0, 0.15], [0, 0, 0.25]])
    s = _run(m, s, 1.0)
    free = external(m, s)
    c = collide(m, s)
    direct = solve_contacts(m, s, free, c, warm_start(s, c))
    assert direct.iterations == 0
    slow = dataclasses.replace(m, opt=dataclasses.replace(m.opt, iterations=5000, tolerance=1e-9))
    it = solve_contacts(slow, s, free, c, None)
    assert it.iterations > 10
    np.testing.assert_allclose(direct.vel, it.vel, atol=1e-6)
    np.testing.assert_allclose(direct.angvel, it.angvel, atol=1e-5)
    assert np.all(direct.impulse[:, 0] >= 0)
    assert np.all(np.linalg.norm(direct.impulse[:, 1:], axis=1) <= c.friction * direct.impulse[:, 0] + 1e-12)


# --- whole scenes (the analytic list) ------------------------------------------------------

def test_box_dropped_on_plane_rests_face_down_at_its_height():
    h = np.array([0.08, 0.05, 0.03])
    m = build_model([box_body(h, 1.0)], planes=FLOOR)
    R = Rotation.from_euler("xyz", [[25, -15, 40]], degrees=True).as_matrix()
    s = make_state(m, R, [[0, 0, 0.4]])
    r = run(m, s, DropSettings(max_time=10))
    assert r.verdict == "accepted" and r.at_rest.all()
    # face down: one model axis is vertical, and the com sits at that half extent
    axis = int(np.argmax(np.abs(r.R_m2w[0][2])))
    assert abs(r.R_m2w[0][2, axis]) > np.cos(np.radians(0.5))
    assert r.t_m2w[0, 2] == pytest.approx(h[axis], abs=PHYS_REST_HEIGHT_TOL)


def test_stack_of_three_boxes_stays_up_for_ten_seconds():
    m = build_model([box_body([0.05] * 3, 1.0)] * 3, planes=FLOOR, opt=NO_SLEEP)
    s = make_state(m, np.repeat(np.eye(3)[None], 3, 0), [[0, 0, 0.05], [0, 0, 0.15], [0, 0, 0.25]])
    s = _run(m, s, 0.5)
    p_settled = s.pos.copy()
    # soft contacts sink a little under load (MuJoCo does the same): <= 2 mm for the top box
    assert np.all(np.abs(p_settled[:, 2] - [0.05, 0.15, 0.25]) < 2e-3)
    s = _run(m, s, 9.5)
    assert np.max(np.linalg.norm(s.pos - p_settled, axis=1)) <= 1e-3


def _incline(mu, seconds=2.0):
    th = np.radians(30)
    n = np.array([-np.sin(th), 0, np.cos(th)])
    down = np.array([-np.cos(th), 0, -np.sin(th)])
    R = Rotation.from_euler("y", -30, degrees=True).as_matrix()
    m = build_model([box_body([0.05] * 3, 1.0, friction=mu)], planes=[[*n, 0.0]], opt=NO_SLEEP)
    s = make_state(m, R[None], [n * 0.05])
    speeds, pos = [], []
    for _ in range(int(seconds / m.opt.timestep)):
        s = step(m, s)
        speeds.append(s.vel[0] @ down)
        pos.append(s.pos[0] @ down)
    return np.array(speeds), np.array(pos), th


def test_block_on_30_degree_incline_slides_with_coulomb_acceleration():
    v, _, th = _incline(0.2)
    dt = 0.02
    acc = (v[-1] - v[20]) / ((len(v) - 1 - 20) * dt)
    expected = G * (np.sin(th) - 0.2 * np.cos(th))
    assert acc == pytest.approx(expected, rel=0.02)


def test_block_on_30_degree_incline_sticks_when_mu_exceeds_tan30():
    _, x, _ = _incline(0.7)
    assert abs(x[-1] - x[0]) < 2e-3


@pytest.mark.parametrize("shape", ["ball", "spinning box"])
def test_fast_body_does_not_pass_a_zero_thickness_sheet(shape):
    body = sphere_body(0.03, 0.1) if shape == "ball" else box_body([0.03] * 3, 0.1)
    m = build_model([body], room=_sheet_room(half=1.5, spacing=0.03))
    assert m.opt.timestep == 0.02
    s = make_state(m, Rotation.from_euler("xyz", [[10, 20, 30]], degrees=True).as_matrix(), [[0, 0, 0.3]],
                   vel=[[0, 0, -20.0]], angvel=[[0, 0, 0]] if shape == "ball" else [[15.0, 5.0, 0]])
    lowest = np.inf
    for _ in range(100):
        s = step(m, s)
        lowest = min(lowest, s.pos[0, 2])
    assert lowest > 0.0
    assert s.asleep[0]
    assert s.pos[0, 2] > 0.02


def test_fast_ball_does_not_pass_a_plane():
    m = build_model([sphere_body(0.03, 0.1)], planes=FLOOR)
    s = make_state(m, np.eye(3)[None], [[0, 0, 0.3]], vel=[[0, 0, -20.0]])
    for _ in range(50):
        s = step(m, s)
        assert s.pos[0, 2] > 0.03 - 2e-3


def _advance(m, pos0, q0, pos1, q1, vel, angvel):
    """ccd.advance of one awake body moving from (pos0, q0) to (pos1, q1): (pos, quat, vel, angvel, clipped)."""
    start = make_state(m, np.eye(3)[None], pos0).replace(pos=pos0, quat=q0)
    out = advance(m, start, start.replace(pos=pos1, quat=q1, vel=vel, angvel=angvel))
    return out.state.pos, out.state.quat, out.state.vel, out.state.angvel, out.clipped


def test_ccd_stops_a_sweep_through_the_sheet():
    m = build_model([box_body([0.02] * 3, 0.1)], room=_sheet_room())
    q = np.array([[1.0, 0, 0, 0]])
    pos0, pos1 = np.array([[0, 0, 0.2]]), np.array([[0, 0, -0.2]])
    p, _, v, _, hit = _advance(m, pos0, q, pos1, q, np.array([[0, 0, -20.0]]), np.zeros((1, 3)))
    assert hit[0]
    assert 0.02 < p[0, 2] < 0.2
    assert v[0, 2] == 0.0


def test_energy_never_grows_in_a_resting_pile():
    # a pile built close to its rest pose (stacked boxes turned against each other, a sphere against the
    # bottom box): it settles the same way every time instead of tumbling chaotically into a pile or
    # not, which made this test depend on rounding (BLAS threads) rather than on the physics
    bodies = [box_body([0.05, 0.04, 0.03], 1.0), box_body([0.04] * 3, 0.7), sphere_body(0.03, 0.3),
              box_body([0.06, 0.02, 0.02], 0.5), box_body([0.03] * 3, 0.4)]
    m = build_model(bodies, planes=FLOOR, opt=NO_SLEEP)
    R = Rotation.from_euler("z", [[0], [30], [0], [70], [20]], degrees=True).as_matrix()
    t = np.array([[0, 0, 0.0301], [0.005, 0, 0.1003], [0.081, 0, 0.0302], [0, 0.003, 0.1605],
                  [0.005, 0, 0.2107]])
    s = _run(m, make_state(m, R, t), 2.0)
    assert s.pos[4, 2] > 0.2              # four boxes high: a pile, not a row
    e = [_energy(m, s)]
    for _ in range(150):
        s = step(m, s)
        e.append(_energy(m, s))
    assert s.pos[4, 2] > 0.2
    # J; soft contacts store ~4e-3 J in their springs here (1/2 force x penetration), so allow 1e-4 J
    # of exchange, no gain. A solve stopped before it converges pumps energy in (1e-3 J and more over
    # this window with the old 60-iteration cap), as did contacts with wrong lever arms (a box on an edge)
    assert np.max(np.array(e) - e[0]) <= 1e-4


def test_box_standing_on_an_edge_gets_contacts_along_that_edge_only():
    # a cube balanced on one edge on a wide box: the contact points lie on that edge (not spread over
    # the box's top face at the edge's depth, which gives wrong torques and pumps energy)
    m = build_model([box_body([0.1, 0.1, 0.03], 1.0), box_body([0.03] * 3, 0.5)], planes=FLOOR)
    R1 = Rotation.from_euler("y", 45, degrees=True).as_matrix()
    z1 = 0.06 + 0.03 * np.sqrt(2) - 0.0005                      # the edge 0.5 mm into the box
    s = make_state(m, np.stack([np.eye(3), R1]), [[0, 0, 0.03], [0.01, 0, z1]])
    c = collide(m, s)
    pair = (c.body_b >= 0) & (c.dist < 0)
    assert pair.any()
    np.testing.assert_allclose(c.dist[pair], -0.0005, atol=1e-6)
    np.testing.assert_allclose(c.pos[pair, 0], 0.01, atol=1e-6)   # on the edge's line x = 0.01
    np.testing.assert_allclose(c.pos[pair, 2], 0.06, atol=1e-3)


def test_bodies_at_rest_sleep_and_are_not_integrated_then_wake_on_contact():
    m = build_model([box_body([0.05] * 3, 1.0), sphere_body(0.03, 0.5)], planes=FLOOR)
    s = make_state(m, np.repeat(np.eye(3)[None], 2, 0), [[0, 0, 0.05], [0, 0, 10.0]])
    for _ in range(60):
        s = step(m, s)
    assert s.asleep[0] and not s.asleep[1]
    frozen = s.pos[0].copy(), s.quat[0].copy()
    s = step(m, s)
    assert np.array_equal(s.pos[0], frozen[0]) and np.array_equal(s.quat[0], frozen[1])
    woke = False
    for _ in range(100):
        s = step(m, s)
        woke |= not s.asleep[0]
    assert woke                           # the falling ball woke the box
    assert s.pos[1, 2] > 0.1 - 0.003      # and rests on it, not in it


# --- drops -----------------------------------------------------------------------------------------

def _pile_bodies(n, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        if rng.random() < 0.3:
            out.append(sphere_body(rng.uniform(0.02, 0.05), rng.uniform(0.1, 0.5)))
        else:
            out.append(box_body(rng.uniform(0.02, 0.06, 3), rng.uniform(0.1, 0.8)))
    return out


def test_drop_into_room_settles_inside_and_is_deterministic():
    room = _box_room()
    st = DropSettings(p_velocity=0.5)
    a = simulate_drop(_pile_bodies(6), room=room, up=np.array([0, 0, 1.0]), settings=st,
                      rng=np.random.default_rng(5))
    b = simulate_drop(_pile_bodies(6), room=room, up=np.array([0, 0, 1.0]), settings=st,
                      rng=np.random.default_rng(5))
    assert a.verdict == "accepted", a.verdict
    assert a.at_rest.all()
    assert a.max_penetration <= 2e-3
    assert np.all((a.t_m2w > 0) & (a.t_m2w < 2.0))
    assert np.all(a.t_m2w[:, 2] < 0.3)    # on the floor or on each other, not floating
    assert np.array_equal(a.t_m2w, b.t_m2w) and np.array_equal(a.R_m2w, b.R_m2w)


def test_drop_through_a_hole_is_rejected_as_left_room():
    room = _box_room(hole=(0.5, 1.5, 0.5, 1.5))
    m = build_model([box_body([0.05] * 3, 0.3)], room=room)
    s = make_state(m, np.eye(3)[None], [[1.0, 1.0, 1.0]])        # above the hole
    r = run(m, s, DropSettings(), R_w2g=np.eye(3), floor=0.0)
    assert r.verdict == "rejected:left-room"


def test_room_without_floor_gives_no_spawn_pose():
    room = _box_room(hole=(0.0, 2.0, 0.0, 2.0))   # no floor at all: nothing to land on anywhere
    r = simulate_drop(_pile_bodies(3), room=room, up=np.array([0, 0, 1.0]),
                      settings=DropSettings(floor_plane=False), rng=np.random.default_rng(1))
    assert r.verdict == "rejected:spawn"


def test_floor_plane_catches_bodies_over_holes_in_the_scanned_floor():
    room = _box_room(hole=(0.3, 1.7, 0.3, 1.7))   # most of the floor unscanned
    r = simulate_drop(_pile_bodies(3), room=room, up=np.array([0, 0, 1.0]), settings=DropSettings(),
                      rng=np.random.default_rng(1))
    assert r.verdict == "accepted"
    assert np.all(np.abs(r.t_m2w[:, 2]) < 0.15)     # resting at the floor's height


def test_drop_that_cannot_settle_in_time_is_rejected():
    r = simulate_drop(_pile_bodies(3), room=_box_room(), up=np.array([0, 0, 1.0]),
                      settings=DropSettings(max_time=0.2), rng=np.random.default_rng(1))
    assert r.verdict == "rejected:never-settled"
    assert not r.at_rest.all()


def test_drop_with_no_free_spawn_pose_is_rejected():
    big = [box_body([0.4] * 3, 1.0) for _ in range(20)]
    r = simulate_drop(big, room=_box_room(), up=np.array([0, 0, 1.0]),
                      settings=DropSettings(spawn_tries=20), rng=np.random.default_rng(1))
    assert r.verdict == "rejected:spawn"


def test_penetration_measure():
    m = build_model([box_body([0.05] * 3, 1.0)], planes=FLOOR)
    s = make_state(m, np.eye(3)[None], [[0, 0, 0.047]])
    assert penetration(m, s) == pytest.approx(0.003)


def test_jitter_in_place_falls_asleep_but_steady_motion_does_not():
    from pipeline.physics.sleep import update_sleep

    m = build_model([box_body([0.05] * 3, 1.0)] * 2)
    pos = np.zeros((2, 3))
    quat = np.tile([1.0, 0, 0, 0], (2, 1))
    s = make_state(m, np.repeat(np.eye(3)[None], 2, 0), pos).replace(pos=pos, quat=quat)
    for k in range(40):
        vel = np.array([[0.05 * (-1) ** k, 0, 0], [0.05, 0, 0]])   # kicked back and forth / sliding
        s = update_sleep(m, s.replace(vel=vel, angvel=np.zeros((2, 3)),
                                      pos=s.pos + np.array([[0.0, 0, 0], [0.05 * m.opt.timestep, 0, 0]])))
    assert s.asleep[0] and not s.asleep[1]


# --- exact room distances at contacts (room mesh) ----------------------------------------------------

def _tilted_sheet_room(deg=15.0, half=0.5, spacing=0.02, offset=0.007):
    """A zero-thickness sheet through (0, 0, offset) tilted ``deg`` about y, as an unsigned grid (whose
    trilinear values are off near the kink at the sheet) plus the sheet's two triangles."""
    a = np.radians(deg)
    n = np.array([-np.sin(a), 0.0, np.cos(a)])
    ax = np.arange(-half, half + 1e-9, spacing)
    P = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), axis=-1)
    udf = np.abs((P - [0, 0, offset]) @ n).astype(np.float32)
    u = np.array([np.cos(a), 0.0, np.sin(a)])
    v = np.array([0.0, 1.0, 0.0])
    c = np.array([0, 0, offset])
    s = 0.45
    verts = np.array([c - s * u - s * v, c + s * u - s * v, c + s * u + s * v, c - s * u + s * v])
    room = {"origin": np.full(3, -half), "spacing": spacing, "udf": udf,
            "mesh_vertices": verts, "mesh_faces": np.array([[0, 1, 2], [0, 2, 3]])}
    return room, n, c


@pytest.mark.slow   # the first open3d import takes ~5 s here
def test_room_mesh_gives_exact_distance_normal_and_sheet_side():
    from pipeline.physics.roommesh import RoomMesh

    room, n, c = _tilted_sheet_room()
    rm = RoomMesh(room["mesh_vertices"], room["mesh_faces"])
    u = np.array([np.cos(np.radians(15)), 0, np.sin(np.radians(15))])     # along the sheet
    p = c + np.array([[0.05], [-0.1]]) * u + [[0, 0.02, 0], [0, 0, 0]] + np.array([[0.0123], [-0.004]]) * n
    d, nrm = rm.closest(p)
    np.testing.assert_allclose(d, [0.0123, 0.004], atol=1e-6)
    np.testing.assert_allclose(nrm, [n, -n], atol=1e-5)
    # the second point crossed the sheet: its body's centre is above it
    d, nrm = rm.closest(p, centres=p + 0.05 * n)
    np.testing.assert_allclose(d, [0.0123, -0.004], atol=1e-6)
    np.testing.assert_allclose(nrm, [n, n], atol=1e-5)
    # the grid alone is off here by more than a millimetre somewhere along the sheet
    m = build_model([sphere_body(0.01, 1.0)], room=room_from_arrays({k: room[k] for k in ("origin", "spacing", "udf")}))
    t = np.linspace(-0.2, 0.2, 41)
    q = c + t[:, None] * u + 0.01 * n
    g, _ = room_distance(m, q)
    assert np.max(np.abs(g - 0.01)) > 1e-3


def test_box_rests_on_a_tilted_scanned_sheet_without_sinking():
    room, n, c = _tilted_sheet_room()
    m = build_model([box_body([0.02] * 3, 0.2, friction=1.0)], room=room_from_arrays(room), room_thickness=0.01)
    R = np.array([[np.cos(np.radians(15)), 0, -np.sin(np.radians(15))], [0, 1, 0],
                  [np.sin(np.radians(15)), 0, np.cos(np.radians(15))]])
    s = make_state(m, R[None], (c + 0.04 * n)[None])
    s = _run(m, s, 1.5)
    # rests on the shell: centre half a side + the shell's half-thickness from the sheet
    assert (s.pos[0] - c) @ n == pytest.approx(0.03, abs=1e-3)
    assert penetration(m, s) <= 1e-3


def test_fast_spinning_box_does_not_cross_a_scanned_sheet_with_a_thin_shell():
    # a 5 mm shell is thinner than the grid's error near the sheet (the sheet lies between grid nodes):
    # exact distances at contacts and exact CCD keep it out
    from pipeline.physics.collide import world_vertices

    room, n, c = _tilted_sheet_room(deg=0.0)
    m = build_model([box_body([0.02] * 3, 0.2, friction=1.0)], room=room_from_arrays(room), room_thickness=0.005)
    R = Rotation.from_euler("xyz", [[10, 20, 30]], degrees=True).as_matrix()
    s = make_state(m, R, (c + 0.3 * n)[None], vel=(-20.0 * n)[None], angvel=[[30.0, 15.0, 0]])
    lowest = np.inf
    for _ in range(100):
        s = step(m, s)
        assert np.all(np.abs(s.pos[0, :2] - c[:2]) < 0.4)          # still over the sheet
        lowest = min(lowest, float(np.min((world_vertices(m, quat_to_mat(s.quat), s.pos)[0] - c) @ n)))
    assert lowest > 0.0                   # no hull point ever on the far side of the sheet
    assert s.asleep[0]
    assert penetration(m, s) <= 1e-3


def test_exact_ccd_stops_a_sweep_the_grid_misses_and_lets_a_body_leave():
    from pipeline.physics.collide import world_vertices

    room, n, c = _tilted_sheet_room(deg=0.0)        # sheet at z = 7 mm, between grid nodes
    grid = room_from_arrays({k: room[k] for k in ("origin", "spacing", "udf")})
    q = np.array([[1.0, 0, 0, 0]])
    pos0, pos1 = np.array([[0, 0, 0.2]]), np.array([[0, 0, -0.2]])
    args = (pos0, q, pos1, q, np.array([[0, 0, -20.0]]), np.zeros((1, 3)))
    exact = build_model([box_body([0.02] * 3, 0.1)], room=room_from_arrays(room), room_thickness=0.005)
    p, _, v, _, hit = _advance(exact, *args)
    assert hit[0] and v[0, 2] == 0.0
    low = float(np.min(world_vertices(exact, np.eye(3)[None], p)[0, :, 2])) - c[2]
    assert 0.0025 - 1e-6 <= low < 0.2            # stopped within the shell's outer half, above the sheet
    # the trilinear grid reads ~9 mm at the sheet itself here: a 5 mm shell is invisible to it
    coarse = build_model([box_body([0.02] * 3, 0.1)], room=grid, room_thickness=0.005)
    assert not _advance(coarse, *args)[4][0]
    # a body whose lowest points were pushed through the sheet (its centre above it) moving up, out of
    # the sheet, is not stopped
    up = (np.array([[0, 0, 0.022]]), q, np.array([[0, 0, 0.072]]), q, np.array([[0, 0, 2.5]]), np.zeros((1, 3)))
    assert not _advance(exact, *up)[4][0]


def _box_room_with_mesh(size=(1.0, 1.0, 1.0), spacing=0.04):
    """:func:`_box_room` with its surface as triangles (floor and four walls), for exact contacts."""
    base = _box_room(size, spacing)
    sx, sy, sz = size
    quads = [[(0, 0, 0), (sx, 0, 0), (sx, sy, 0), (0, sy, 0)],
             [(0, 0, 0), (0, sy, 0), (0, sy, sz), (0, 0, sz)], [(sx, 0, 0), (sx, sy, 0), (sx, sy, sz), (sx, 0, sz)],
             [(0, 0, 0), (sx, 0, 0), (sx, 0, sz), (0, 0, sz)], [(0, sy, 0), (sx, sy, 0), (sx, sy, sz), (0, sy, sz)]]
    V = np.array([p for q in quads for p in q], float)
    F = np.array([[4 * i, 4 * i + 1, 4 * i + 2] for i in range(5)] + [[4 * i, 4 * i + 2, 4 * i + 3] for i in range(5)])
    return room_from_arrays({"origin": base.origin, "spacing": base.spacing, "udf": base.udf,
                             "mesh_vertices": V, "mesh_faces": F})


def _round_body(r=0.03, h=0.04, n=96, mass=0.2) -> Body:
    """A cylinder with ``n`` rim points per end: its 48-vertex collision hull cuts inside the rims."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([r * np.cos(a), r * np.sin(a)], 1)
    pts = np.concatenate([np.c_[ring, np.full(n, -h / 2)], np.c_[ring, np.full(n, h / 2)]])
    I = mass * np.diag([(3 * r * r + h * h) / 12] * 2 + [r * r / 2])
    return Body(vertices=pts, mass=mass, com=np.zeros(3), inertia=I)


@pytest.mark.slow   # open3d
def test_dropped_objects_rest_on_the_scanned_surface_not_on_the_shell():
    """Issue 16: the gap between an object's own lowest point and the floor it rests on is at most a couple
    of millimetres (the thick shell only bridges the fall), and it does not sink in; with the settling
    turned off the same drop rests on the shell, ~1 cm up."""
    bodies = [_round_body() for _ in range(3)] + [box_body([0.03, 0.02, 0.015], 0.1)]
    low = {}
    for rest in (0.001, 0.01):
        st = DropSettings(room_thickness=0.01, rest_thickness=rest)
        r = simulate_drop(bodies, room=_box_room_with_mesh(), up=np.array([0, 0, 1.0]), settings=st,
                          rng=np.random.default_rng(3))
        assert r.verdict == "accepted", r.verdict
        low[rest] = np.array([float(np.min(np.asarray(b.vertices) @ R.T @ [0, 0, 1] + t[2]))
                              for b, R, t in zip(bodies, r.R_m2w, r.t_m2w)])
    on_floor = low[0.001] < 0.02          # not resting on another body
    assert on_floor.sum() >= 3
    assert np.all(low[0.001][on_floor] > -0.001) and np.all(low[0.001][on_floor] < 0.0025), low[0.001]
    assert np.all(low[0.01][low[0.01] < 0.03] > 0.005), low[0.01]
