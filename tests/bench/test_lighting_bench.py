"""bench/lighting.py's figures over run seeds (``--seeds``): what it counts and what it keeps. The runs
themselves are checked on the tiny Mitsuba suite (test_lighting_suite.py); here the summary and the file."""

from __future__ import annotations

import json

import numpy as np
import pytest


def _room(psnr: float, brightness, band: float, photo_band: float, render: str = "r") -> dict:
    """A run_room result with only what the summary reads."""
    return {"render": render, "photo_band_psnr": photo_band,
            "variants": {"fit": {"psnr_objects": psnr, "brightness": brightness, "psnr_band": band, "fit_s": 12.34}}}


def test_seeds_summary_counts_the_rooms_within_the_target_per_seed():
    from bench.lighting import seeds_summary

    # seed order as given (the first ran every variant); 0.9 and 1.1 are inside the target, 0.8999 is not
    per_seed = {
        2: {"ceiling": _room(30.0, [1.0, 0.95, 0.9], 36.0, 30.0),
            "spot": _room(26.0, [1.0, 1.0, 0.8999], 31.0, 26.0),
            "dim": _room(34.0, [1.1, 1.0, 1.0], 40.0, 33.0)},
        0: {"ceiling": _room(31.0, [1.0, 1.0, 1.0], 36.5, 30.0),
            "spot": _room(28.0, [0.95, 0.95, 0.95], 31.5, 26.0),
            "dim": _room(35.0, [1.1001, 1.0, 1.0], 40.0, 33.0, render="other")},
    }
    got = seeds_summary(per_seed)
    assert got["seeds"] == [2, 0]
    assert got["within_10pct_rooms_per_seed"] == [2, 2]
    assert got["rooms"]["spot"]["within_10pct"] == [False, True]
    assert got["rooms"]["dim"]["within_10pct"] == [True, False]
    assert got["rooms"]["ceiling"]["psnr_objects"] == [30.0, 31.0]
    assert got["rooms"]["ceiling"]["mean"] == 30.5 and got["rooms"]["ceiling"]["spread"] == 1.0
    assert got["rooms"]["ceiling"]["band_over_photo_db"] == [6.0, 6.5]
    assert got["rooms"]["dim"]["render"] == "r"          # the first seed's render
    assert got["rooms"]["spot"]["fit_s"] == [12.3, 12.3]
    # the groups: tuned on (ceiling), held out (spot, dim), all; the worst room per seed
    assert got["groups"]["tuned_on"] == {"rooms": ["ceiling"], "mean_per_seed": [30.0, 31.0], "mean": 30.5,
                                         "min_per_seed": [30.0, 31.0]}
    assert got["groups"]["held_out"]["rooms"] == ["spot", "dim"]
    assert got["groups"]["held_out"]["mean_per_seed"] == [30.0, 31.5]
    assert got["groups"]["all"]["min_per_seed"] == [26.0, 28.0]
    assert got["groups"]["all"]["mean_per_seed"] == [30.0, 31.33]
    json.dumps(got)


def test_seeds_summary_leaves_out_a_room_missing_at_a_seed():
    from bench.lighting import seeds_summary

    per_seed = {0: {"ceiling": _room(31.0, [1, 1, 1], 36.0, 30.0), "spot": _room(28.0, [1, 1, 1], 31.0, 26.0)},
                1: {"ceiling": _room(30.0, [1, 1, 1], 36.0, 30.0)}}
    got = seeds_summary(per_seed)
    assert list(got["rooms"]) == ["ceiling"]
    assert got["within_10pct_rooms_per_seed"] == [1, 1]
    assert "held_out" not in got["groups"]


def test_a_tuning_room_outside_the_suite_is_its_own_group():
    """A room of bench.lightsuite.DEV_ROOMS (tuning only) is reported as the group "dev", never in "all", in
    the count of rooms within the target, or in summarise's "all"."""
    from bench.lighting import seeds_summary, summarise

    per_seed = {0: {"ceiling": _room(31.0, [1, 1, 1], 36.0, 30.0), "coloured_dev": _room(20.0, [1, 1, 1], 30.0, 25.0)},
                1: {"ceiling": _room(30.0, [1, 1, 1], 36.0, 30.0), "coloured_dev": _room(22.0, [2, 1, 1], 30.0, 25.0)}}
    got = seeds_summary(per_seed)
    assert got["within_10pct_rooms_per_seed"] == [1, 1]
    assert got["rooms"]["coloured_dev"]["within_10pct"] == [True, False]
    assert got["groups"]["dev"] == {"rooms": ["coloured_dev"], "mean_per_seed": [20.0, 22.0], "mean": 21.0,
                                    "min_per_seed": [20.0, 22.0]}
    assert got["groups"]["all"]["rooms"] == ["ceiling"] and got["groups"]["all"]["mean_per_seed"] == [31.0, 30.0]
    assert got["within_10pct_dev_rooms_per_seed"] == [1, 0]
    suite_only = {s: {"ceiling": v["ceiling"]} for s, v in per_seed.items()}
    assert "within_10pct_dev_rooms_per_seed" not in seeds_summary(suite_only)
    for r in per_seed[0].values():
        r["variants"]["fit"]["cpu_s_per_frame"] = 1.0
    s = summarise(per_seed[0], ("fit",))
    assert s["all"]["rooms"] == ["ceiling"] and s["dev"]["rooms"] == ["coloured_dev"]
    assert s["dev"]["fit"]["psnr_objects_mean"] == 20.0 and s["all"]["fit"]["psnr_objects_mean"] == 31.0


def test_seeds_file_holds_the_current_figures_only(tmp_path):
    """A run with --seeds rewrites lighting_seeds.json: its figures replace the old ones, and keys the run does not
    write (figures of other code or another render, diagnostics) are not kept."""
    from bench.lighting import write_seeds

    path = tmp_path / "lighting_seeds.json"
    old = {"what": "old", "rooms": {"ceiling": {"psnr_objects": [1.0]}, "spot": {"psnr_objects": [2.0]}},
           "screens_diagnostics": {"x": [1, 2]}, "previous_render": {"y": "z"}}
    path.write_text(json.dumps(old, indent=1))
    block = {"what": "new", "rooms": {"spot": {"psnr_objects": [29.0, 28.5]}}, "seeds": [0, 1]}
    write_seeds(path, block)
    assert json.loads(path.read_text()) == block
    fresh = tmp_path / "fresh.json"
    write_seeds(fresh, {"what": "w"})
    assert json.loads(fresh.read_text()) == {"what": "w"}


@pytest.mark.parametrize("args, says", [
    (["--seeds", "0,x"], "integers"),
    (["--seeds", "0,0"], "distinct"),
    (["--seeds", "-1"], "non-negative"),
    (["--seeds", "0,1", "--variants", "scan"], "add fit to --variants"),
])
def test_bad_seeds_are_refused_before_anything_runs(args, says, tmp_path, capsys):
    """A usage error names the option and the fix, before the suite is built (tens of minutes) or any room runs."""
    from bench.lighting import main

    with pytest.raises(SystemExit) as e:
        main(["--suite", str(tmp_path / "no-suite"), "--work", str(tmp_path / "w"), "--out", str(tmp_path / "o"),
              *args])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "--seeds" in err and says in err
    assert not (tmp_path / "no-suite").exists() and not (tmp_path / "w").exists()


@pytest.mark.parametrize("rooms, out, says", [("ceiling, kitchen", [], "unknown room(s) kitchen;"),
                                              ("coloured_dev", [], "give --out"),
                                              ("window,coloured_dev", ["--out", ""], "give --out")])
def test_bad_rooms_are_refused_before_anything_runs(rooms, out, says, tmp_path, capsys):
    """An unknown room is named with the rooms to choose from (spaces after the commas are not part of a name); a
    tuning-only room without --out would write the headline results (bench/results/lighting.json) with it:
    refused, with the fix."""
    from bench.lighting import main

    with pytest.raises(SystemExit) as e:
        main(["--suite", str(tmp_path / "no-suite"), "--work", str(tmp_path / "w"), "--rooms", rooms, *out])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "--rooms" in err and says in err
    assert not (tmp_path / "no-suite").exists() and not (tmp_path / "w").exists()


def test_the_tuning_room_is_not_a_held_out_room_again():
    """coloured_dev (tuning only) has strongly coloured walls like the held-out coloured room, but other hues on
    every coloured wall and lamps over 1 m from its lamps, and is not one of the suite's six."""
    from bench.lightsuite import DEV_ROOMS, ROOMS, room_spec

    assert DEV_ROOMS == ("coloured_dev",) and not set(DEV_ROOMS) & set(ROOMS)
    dev, held = room_spec("coloured_dev"), room_spec("coloured_walls")
    walls = {s.name: s.base for s in dev.surfaces if s.name.startswith("wall_")}
    held_walls = {s.name: s.base for s in held.surfaces if s.name.startswith("wall_")}
    coloured = [k for k, b in walls.items() if max(b) > 3 * min(b)]
    assert len(coloured) == 3 and all(walls[k] != held_walls[k] for k in coloured)
    assert min(float(np.linalg.norm(a.centre - b.centre)) for a in dev.emitters for b in held.emitters) > 1.0
    with pytest.raises(ValueError, match="coloured_dev"):
        room_spec("kitchen")
