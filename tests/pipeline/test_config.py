"""Configs: defaults, TOML round trip, overrides, and one clear error per kind of mistake."""

from __future__ import annotations

import dataclasses

import pytest

from pipeline.config import (Config, ConfigError, build_config, dump_config, load_config, parse_override,
                             reference_markdown)


def test_defaults_are_valid_and_frozen():
    cfg = build_config({})
    assert cfg == Config()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.run.seed = 3  # type: ignore[misc]


def test_dump_and_load_round_trip(tmp_path):
    cfg = load_config(None, ["run.seed=11", "simulate.drops=3", "composite.mode=published"])
    p = tmp_path / "c.toml"
    p.write_text(dump_config(cfg))
    assert load_config(p) == cfg


def test_override_parses_toml_values():
    assert parse_override("run.seed=5") == ("run", "seed", 5)
    assert parse_override("export.formats=['bop']") == ("export", "formats", ["bop"])
    assert parse_override("composite.mode=full") == ("composite", "mode", "full")


@pytest.mark.parametrize("raw, words", [
    ({"run": {"sed": 1}}, ["run.sed", "valid keys", "seed"]),
    ({"nope": {}}, ["[nope]", "valid tables"]),
    ({"run": {"seed": "x"}}, ["run.seed", "'x'", "integer"]),
    ({"run": {"seed": 1.5}}, ["run.seed", "integer"]),
    ({"run": {"seed": True}}, ["run.seed", "integer"]),
    ({"simulate": {"drops": -1}}, ["simulate.drops", "-1", ">= 0"]),
    ({"simulate": {"timestep": 0}}, ["simulate.timestep", "> 0"]),
    ({"raster": {"visib_threshold": 1.5}}, ["raster.visib_threshold", "<= 1"]),
    ({"composite": {"mode": "fancy"}}, ["composite.mode", "'fancy'", "'published'", "'full'"]),
    ({"export": {"formats": ["bop", "voc"]}}, ["export.formats", "'voc'", "'coco'"]),
    ({"scan": {"paths": ["/definitely/not/here"]}}, ["scan.paths", "/definitely/not/here", "does not exist"]),
    ({"run": 3}, ["[run]", "table"]),
])
def test_bad_values_name_key_value_and_fix(raw, words):
    with pytest.raises(ConfigError) as e:
        build_config(raw)
    for w in words:
        assert w in str(e.value)


def test_relative_paths_resolve_against_the_config_folder(tmp_path):
    (tmp_path / "scans" / "a").mkdir(parents=True)
    p = tmp_path / "c.toml"
    p.write_text('[scan]\npaths = ["scans/a"]\n')
    assert load_config(p).scan.paths == (str((tmp_path / "scans" / "a").resolve()),)


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[run\nseed = 1\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ConfigError, match="UTF-8"):
        load_config(binary)


def test_errors_say_whether_the_file_or_set_gave_the_bad_key(tmp_path):
    p = tmp_path / "mine.toml"
    p.write_text('[run]\nsed = 1\n[trace]\nspp = 8\n')
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert str(e.value).startswith(f"{p}: unknown key run.sed")
    p.write_text('[trace]\nspp = 8\n')
    for text, words in [("run.seed=abc", ["--set 'run.seed=abc'", "run.seed = 'abc'", "integer"]),
                        ("trace.nope=1", ["--set 'trace.nope=1'", "unknown key trace.nope", "valid keys"]),
                        ("foo.bar=1", ["--set 'foo.bar=1'", "unknown table [foo]"])]:
        with pytest.raises(ConfigError) as e:
            load_config(p, [text])
        assert all(w in str(e.value) for w in words), str(e.value)
        assert str(p) not in str(e.value)
    # a bad value in the file is the file's, even with a good --set beside it
    p.write_text('[trace]\nspp = -3\n')
    with pytest.raises(ConfigError) as e:
        load_config(p, ["run.seed=2"])
    assert str(e.value).startswith(f"{p}: trace.spp = -3")


def test_a_removed_key_says_what_became_of_it_and_to_delete_it(tmp_path):
    p = tmp_path / "old.toml"
    p.write_text('[trace]\nfit_albedo_shrink = 0.0\n')
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert str(e.value).startswith(f"{p}: trace.fit_albedo_shrink is no longer an option ("), str(e.value)
    assert str(e.value).endswith("delete it"), str(e.value)
    p.write_text('[trace]\nspp = 8\n')
    with pytest.raises(ConfigError, match="trace.fit_light_colour is no longer an option"):
        load_config(p, ["trace.fit_light_colour=shared"])
    from pipeline.config import REMOVED_KEYS, TraceConfig

    assert not {k.split(".")[1] for k in REMOVED_KEYS} & {f.name for f in dataclasses.fields(TraceConfig)}


def test_reference_lists_every_key():
    ref = reference_markdown()
    for f in dataclasses.fields(Config):
        assert f"[{f.name}]" in ref
        for g in dataclasses.fields(getattr(Config(), f.name)):
            assert f"`{g.name}`" in ref


def test_presets_set_defaults_and_explicit_keys_win(tmp_path):
    from pipeline.presets import PRESETS

    fast = build_config({"run": {"preset": "fast"}})
    assert fast.trace.spp == PRESETS["fast"]["trace"]["spp"]
    assert build_config({"run": {"preset": "fast"}, "trace": {"spp": 99}}).trace.spp == 99
    assert build_config({}).trace == Config().trace
    # Every preset names only real keys with valid values, and survives a dump/load round trip.
    for name in PRESETS:
        cfg = build_config({"run": {"preset": name}})
        p = tmp_path / f"{name}.toml"
        p.write_text(dump_config(cfg))
        assert load_config(p) == cfg
    with pytest.raises(ConfigError, match="run.preset"):
        build_config({"run": {"preset": "ultra"}})
