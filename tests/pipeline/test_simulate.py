"""The simulate stage: placement files round trip; drops are deterministic and reported honestly."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from pipeline.config import SimulateConfig
from pipeline.errors import InputError, UserError
from pipeline.physics.io import room_from_arrays
from pipeline.runfolder import PLACEMENT_TPATH, load_placement, path, read_placement, save_placement
from pipeline.simulate import simulate
from pipeline.types import Placement


def _room_arrays(size=1.6, spacing=0.04) -> dict:
    """A room proxy's arrays: floor and four walls as a distance grid."""
    ax = np.arange(0, size + 1e-9, spacing)
    X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    udf = np.minimum.reduce([Z, X, size - X, Y, size - Y]).astype(np.float32)
    return {"origin": np.zeros(3), "spacing": spacing, "udf": udf}


def _room(size=1.6, spacing=0.04):
    return room_from_arrays(_room_arrays(size, spacing))


def _box_proxy(h, mass):
    h = np.asarray(h, float)
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * h
    e = 2 * h
    inertia = mass / 12 * np.diag([e[1] ** 2 + e[2] ** 2, e[0] ** 2 + e[2] ** 2, e[0] ** 2 + e[1] ** 2])
    return {"hull_vertices": corners + 0.01, "mass": mass, "com": np.full(3, 0.01), "inertia": inertia}


PROXIES = {1: _box_proxy([0.03, 0.02, 0.01], 0.1), 5: _box_proxy([0.04, 0.04, 0.04], 0.3),
           9: _box_proxy([0.05, 0.02, 0.03], 0.2)}


def test_placement_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    p = Placement(scene="kitchen", drop=3, obj_ids=np.array([1, 5, 5], np.int32),
                  R_m2w=Rotation.random(3, random_state=1).as_matrix(), t_m2w=rng.normal(size=(3, 3)),
                  at_rest=np.array([True, False, True]), max_penetration=0.000123456789,
                  verdict="rejected:never-settled")
    out = path(tmp_path, PLACEMENT_TPATH, scene="kitchen", drop=3)
    save_placement(out, p, extra={"seconds": 1.5})
    q = load_placement(tmp_path, "kitchen", 3)
    for f in dataclasses.fields(Placement):
        a, b = getattr(p, f.name), getattr(q, f.name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b), f.name
        else:
            assert a == b, f.name
    assert out.name == "drop0003.json"
    assert json.loads(out.read_text())["sim_seconds"] == 1.5


def test_missing_or_broken_placement_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="simulate"):
        load_placement(tmp_path, "kitchen", 0)
    bad = tmp_path / "bad.json"
    bad.write_text('{"scene": "x"}')
    with pytest.raises(InputError, match="not a placement"):
        read_placement(bad)


def test_simulate_drop_is_deterministic_and_accepted():
    cfg = SimulateConfig(objects_per_drop=4, p_velocity=0.5)
    runs = [simulate(cfg, scene="s", drop=0, room=_room(), up=np.array([0, 0, 1.0]), proxies=PROXIES,
                     rng=np.random.default_rng(7)) for _ in range(2)]
    (a, facts), (b, _) = runs
    assert a.verdict == "accepted" and a.at_rest.all()
    assert a.max_penetration <= 2e-3
    assert set(a.obj_ids.tolist()) <= set(PROXIES)
    assert np.array_equal(a.t_m2w, b.t_m2w) and np.array_equal(a.R_m2w, b.R_m2w)
    assert np.all(a.t_m2w[:, 2] < 0.2)        # on the floor (or each other), not floating
    assert 0 < facts["seconds"] < cfg.max_time


def test_distinct_objects_beyond_the_library_is_an_input_error():
    cfg = SimulateConfig(objects_per_drop=5, repeat_objects=False)
    with pytest.raises(InputError, match="repeat_objects"):
        simulate(cfg, scene="s", drop=0, room=_room(), up=np.array([0, 0, 1.0]), proxies=PROXIES,
                 rng=np.random.default_rng(0))


def test_distinct_objects_are_distinct():
    cfg = SimulateConfig(objects_per_drop=3, repeat_objects=False, max_time=0.1)
    p, _ = simulate(cfg, scene="s", drop=0, room=_room(), up=np.array([0, 0, 1.0]), proxies=PROXIES,
                    rng=np.random.default_rng(0))
    assert sorted(p.obj_ids.tolist()) == [1, 5, 9]
    assert p.verdict == "rejected:never-settled"   # 0.1 s is too short to land: counted, not kept


def test_room_info_given_or_computed_gives_the_same_drop():
    from pipeline.physics.drop import room_info

    cfg = SimulateConfig(objects_per_drop=3, p_velocity=0.5)
    room, up = _room(), np.array([0, 0, 1.0])
    a, _ = simulate(cfg, scene="s", drop=0, room=room, up=up, proxies=PROXIES, rng=np.random.default_rng(3))
    b, _ = simulate(cfg, scene="s", drop=0, room=room, up=up, proxies=PROXIES, rng=np.random.default_rng(3),
                    info=room_info(room, up))
    assert np.array_equal(a.t_m2w, b.t_m2w) and np.array_equal(a.R_m2w, b.R_m2w) and a.verdict == b.verdict


def test_room_cache_reloads_a_rewritten_proxy(tmp_path):
    import os

    from pipeline.io import atomic_save_npz
    from pipeline.runfolder import file_stamp
    from pipeline.simulate import _cached_room

    path = tmp_path / "room_proxy.npz"
    atomic_save_npz(path, **_room_arrays())
    up = (0.0, 0.0, 1.0)
    r1, i1 = _cached_room(file_stamp(path), up)
    assert _cached_room(file_stamp(path), up)[0] is r1           # same file: built once per process
    atomic_save_npz(path, **_room_arrays(size=1.2))
    os.utime(path, ns=(1, 1))                                 # a different stamp even within one mtime tick
    r2, i2 = _cached_room(file_stamp(path), up)
    assert r2 is not r1 and r2.udf.shape != r1.udf.shape
    # the info is rebuilt from the new file: its surface spans the smaller room (compared in the world
    # frame: the horizontal axes room_frame picks for a square room are arbitrary, so bounds in the room
    # frame of a 1.2 m square may exceed those of the 1.6 m one)
    assert np.ptp(i2.surface, axis=0).max() < np.ptp(i1.surface, axis=0).max()


def _retried(cfg, seed, room=None):
    from pipeline.simulate import simulate_with_retries

    return simulate_with_retries(cfg, lambda k: np.random.default_rng([seed, k]), scene="s", drop=0,
                                 room=_room() if room is None else room, up=np.array([0, 0, 1.0]), proxies=PROXIES)


def test_a_never_settled_drop_is_retried_with_a_new_draw_and_accepted():
    # 1 s is long enough for some draws of three thrown boxes to come to rest, not for others.
    cfg = SimulateConfig(objects_per_drop=3, p_velocity=1.0, max_time=1.0, retries=2)
    p, facts = _retried(cfg, 2)
    assert [a["verdict"] for a in facts["attempts"]] == ["rejected:never-settled", "accepted"]
    assert p.verdict == "accepted" and facts["attempt"] == 1 and p.at_rest.all()
    # the placement is the second draw's own, and the same generators give the same bytes
    q, _ = simulate(cfg, scene="s", drop=0, room=_room(), up=np.array([0, 0, 1.0]), proxies=PROXIES,
                    rng=np.random.default_rng([2, 1]))
    assert np.array_equal(p.t_m2w, q.t_m2w) and np.array_equal(p.R_m2w, q.R_m2w)
    again, facts2 = _retried(cfg, 2)
    assert facts2 == facts and np.array_equal(again.t_m2w, p.t_m2w) and np.array_equal(again.obj_ids, p.obj_ids)
    # without retries the drop is lost
    lost, facts0 = _retried(dataclasses.replace(cfg, retries=0), 2)
    assert lost.verdict == "rejected:never-settled" and facts0["attempt"] == 0 and len(facts0["attempts"]) == 1


def test_retries_stop_at_the_limit_and_spare_spawn_failures():
    cfg = SimulateConfig(objects_per_drop=3, p_velocity=1.0, max_time=0.4, retries=2)
    p, facts = _retried(cfg, 0)
    assert [a["verdict"] for a in facts["attempts"]] == ["rejected:never-settled"] * 3
    assert p.verdict == "rejected:never-settled" and facts["attempt"] == 2
    # forty objects do not fit a 0.4 m room: another draw would not either
    p, facts = _retried(SimulateConfig(objects_per_drop=40, retries=2), 0, room=_room(0.4))
    assert p.verdict == "rejected:spawn" and len(facts["attempts"]) == 1
