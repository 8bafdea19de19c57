"""Object libraries: real LM-O / YCB / fuze models, BOP models_info, units, materials, bad files."""

from __future__ import annotations

import json
from itertools import combinations

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.objects import (builtin_shapes, load_library, load_object_file, load_saved_library,
                              max_pairwise_distance, models_info, save_library)
from pipeline.scanformats.common import IngestWarning

INFO_KEYS = ("diameter", "min_x", "min_y", "min_z", "size_x", "size_y", "size_z")


def cube_mesh(size: float = 1.0):
    import trimesh

    return trimesh.creation.box(extents=(size, size, size))


def write_colored_ply(path, m, color=(200, 30, 30)):
    import trimesh

    trimesh.Trimesh(m.vertices, m.faces, vertex_colors=np.tile(color, (len(m.vertices), 1)),
                    process=False).export(path)


# ---------------------------------------------------------------------------------------------------
# models_info
# ---------------------------------------------------------------------------------------------------

def test_max_pairwise_distance_matches_brute_force():
    P = np.random.default_rng(0).normal(size=(300, 3))
    brute = max(np.linalg.norm(a - b) for a, b in combinations(P, 2))
    assert max_pairwise_distance(P) == pytest.approx(brute, abs=1e-12)


def test_max_pairwise_distance_degenerate_inputs():
    assert max_pairwise_distance(np.zeros((1, 3))) == 0.0
    flat = np.array([[0, 0, 0], [3, 0, 0], [0, 4, 0], [1, 1, 0.0]])
    assert max_pairwise_distance(flat) == pytest.approx(5.0)


def test_models_info_of_a_box():
    info = models_info(cube_mesh(2.0).vertices)
    assert info["diameter"] == pytest.approx(2 * np.sqrt(3))
    assert info["min_x"] == pytest.approx(-1.0) and info["size_z"] == pytest.approx(2.0)


# ---------------------------------------------------------------------------------------------------
# Real models
# ---------------------------------------------------------------------------------------------------

@pytest.mark.shared_data
def test_lmo_models_load_with_colours_and_reproduce_models_info(shared_data):
    d = shared_data / "objects" / "lmo" / "models"
    ref = json.loads((d / "models_info.json").read_text())
    models = load_library([str(d)])
    assert [m.obj_id for m in models] == sorted(int(k) for k in ref)
    for m in models:
        assert m.vertex_colors is not None and m.vertex_colors.shape == m.vertices.shape
        assert m.vertex_colors.std() > 5  # real colours, not a constant
        r = ref[str(m.obj_id)]
        for k in INFO_KEYS:  # models_info.json is in mm, ours in metres: within 0.1 mm
            assert abs(m.info[k] * 1000.0 - r[k]) < 0.1, (m.obj_id, k)
        assert 0.05 < m.info["diameter"] < 0.3  # metres


@pytest.mark.shared_data
def test_lmo_dataset_folder_finds_its_models(shared_data):
    from pipeline.objects import _bop_dir

    assert _bop_dir(shared_data / "objects" / "lmo") == shared_data / "objects" / "lmo" / "models"


@pytest.mark.shared_data
def test_ycb_gltf_and_fuze_obj_load_with_textures(shared_data):
    models = load_library([str(shared_data / "objects" / "ycb-textured"),
                           str(shared_data / "objects" / "fuze" / "fuze.obj")])
    assert [m.obj_id for m in models] == list(range(1, 8))
    assert models[-1].name == "fuze"
    for m in models:
        assert m.texture is not None and m.texture.dtype == np.uint8 and m.texture.shape[2] == 3
        assert m.texture.std() > 10
        assert m.uv is not None and m.uv.shape == (len(m.vertices), 2)
        assert 0.05 < m.info["diameter"] < 0.35  # metres already: no scaling
        assert np.allclose(np.linalg.norm(m.normals, axis=1), 1.0, atol=1e-3)
    # glTF carries its PBR factors
    assert models[0].roughness == 1.0 and models[0].metallic == 0.0


# ---------------------------------------------------------------------------------------------------
# Formats written here
# ---------------------------------------------------------------------------------------------------

def test_bop_folder_in_mm_becomes_metres_with_ids_and_symmetries(tmp_path):
    m = cube_mesh(50.0)  # 5 cm cube in mm
    write_colored_ply(tmp_path / "obj_000007.ply", m)
    write_colored_ply(tmp_path / "obj_000002.ply", cube_mesh(80.0))
    sym = [{"axis": [0, 0, 1], "offset": [0, 0, 10.0]}]
    (tmp_path / "models_info.json").write_text(json.dumps({
        "7": {"diameter": 86.6025, "min_x": -25, "min_y": -25, "min_z": -25, "size_x": 50, "size_y": 50,
              "size_z": 50, "symmetries_continuous": sym}}))
    models = load_library([str(tmp_path)])
    assert [m.obj_id for m in models] == [2, 7]
    assert models[1].info["size_x"] == pytest.approx(0.05)
    assert models[1].info["symmetries_continuous"][0]["offset"] == [0, 0, pytest.approx(0.01)]
    np.testing.assert_array_equal(models[1].vertex_colors[0], [200, 30, 30])


def test_obj_with_mtl_texture(tmp_path):
    import cv2

    (tmp_path / "m.obj").write_text(
        "mtllib m.mtl\nusemtl a\nv 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\n"
        "vt 0 0\nvt 1 0\nvt 0 1\nvt 1 1\n"
        "f 1/1 3/3 2/2\nf 1/1 2/2 4/4\nf 1/1 4/4 3/3\nf 2/2 3/3 4/4\n")
    (tmp_path / "m.mtl").write_text("newmtl a\nKd 1 1 1\nmap_Kd tex.png\n")
    tex = np.zeros((8, 8, 3), np.uint8)
    tex[..., 2] = 255  # blue (RGB)
    cv2.imwrite(str(tmp_path / "tex.png"), tex[..., ::-1])
    m = load_library([str(tmp_path / "m.obj")])[0]
    assert m.texture is not None and np.all(m.texture[..., 2] == 255) and np.all(m.texture[..., 0] == 0)
    assert m.uv.shape == (len(m.vertices), 2) and len(m.faces) == 4


def test_glb_round_trip(tmp_path):
    import trimesh

    c = cube_mesh(0.1)
    trimesh.Trimesh(c.vertices, c.faces, vertex_colors=np.tile((10, 200, 10, 255), (8, 1)),
                    process=False).export(tmp_path / "c.glb")
    m = load_library([str(tmp_path / "c.glb")])[0]
    assert m.info["diameter"] == pytest.approx(0.1 * np.sqrt(3), rel=1e-6)
    assert m.vertex_colors is not None and np.all(m.vertex_colors[:, 1] == 200)


def _gltf_files(folder, mesh):
    """Export ``mesh`` as a .gltf with separate .bin buffers into ``folder``; returns the .gltf path and the
    buffers' names."""
    folder.mkdir(parents=True, exist_ok=True)
    files = mesh.export(file_type="gltf")
    for name, data in files.items():
        (folder / name).write_bytes(data)
    return folder / "model.gltf", [n for n in files if n.endswith(".bin")]


def test_gltf_whose_bin_is_a_symlink_to_another_folder_loads(tmp_path):
    """A folder of models made of symlinks (the user's choice of files) loads like the files themselves."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    gltf, bins = _gltf_files(tmp_path / "store", sphere)
    lib = tmp_path / "lib"
    lib.mkdir()
    (lib / "ball.gltf").write_bytes(gltf.read_bytes())
    for name in bins:
        (lib / name).symlink_to(tmp_path / "store" / name)
    m = load_object_file(lib / "ball.gltf", obj_id=1, scale=1.0, unit_note="metres (glTF)")
    assert len(m.vertices) == len(sphere.vertices) == 42 and len(m.faces) == len(sphere.faces)
    # the .gltf itself a symlink: its buffers are found beside its target
    (tmp_path / "links").mkdir()
    (tmp_path / "links" / "ball.gltf").symlink_to(gltf)
    assert len(load_library([str(tmp_path / "links")])[0].vertices) == 42


def test_gltf_with_a_missing_bin_names_the_file(tmp_path):
    import trimesh

    gltf, bins = _gltf_files(tmp_path / "store", trimesh.creation.icosphere(subdivisions=1, radius=0.05))
    (tmp_path / "lib").mkdir()
    (tmp_path / "lib" / "ball.gltf").write_bytes(gltf.read_bytes())
    with pytest.raises(InputError, match=rf"ball\.gltf: the model refers to '{bins[0]}', which is not in "
                                         rf".*lib; copy the file"):
        load_library([str(tmp_path / "lib" / "ball.gltf")])


def test_gltf_reference_outside_its_folder_is_refused_with_the_reason(tmp_path):
    import trimesh

    gltf, bins = _gltf_files(tmp_path / "store", trimesh.creation.icosphere(subdivisions=1, radius=0.05))
    doc = json.loads(gltf.read_text())
    for b in doc["buffers"]:
        b["uri"] = "../store/" + b["uri"]
    (tmp_path / "lib").mkdir()
    (tmp_path / "lib" / "ball.gltf").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"refers to '\.\./store/.*\.bin', outside its folder .*lib; .* a symlink "
                                         r"to it"):
        load_library([str(tmp_path / "lib" / "ball.gltf")])


def test_ids_across_sources(tmp_path):
    (tmp_path / "bop").mkdir()
    write_colored_ply(tmp_path / "bop" / "obj_000004.ply", cube_mesh(50.0))
    write_colored_ply(tmp_path / "a.ply", cube_mesh(0.05))
    models = load_library([str(tmp_path / "a.ply"), str(tmp_path / "bop"), "builtin:shapes"])
    assert [(m.obj_id, m.name) for m in models][:3] == [(4, "obj_000004"), (5, "box"), (6, "cylinder")]
    assert models[-1].name == "a" and models[-1].obj_id == 10


def test_scale_from_config_overrides_the_format(tmp_path):
    write_colored_ply(tmp_path / "a.ply", cube_mesh(100.0))  # a 10 cm cube written in mm
    m = load_library([str(tmp_path / "a.ply")], scale=0.001)[0]
    assert m.info["size_x"] == pytest.approx(0.1)


def test_implausible_size_warns_with_the_assumed_unit(tmp_path):
    write_colored_ply(tmp_path / "a.ply", cube_mesh(100.0))  # mm written, metres assumed
    with pytest.warns(IngestWarning, match=r"173.2 m across with metres .* set objects.scale"):
        load_library([str(tmp_path / "a.ply")])


def test_builtin_shapes():
    models = builtin_shapes()
    assert [m.obj_id for m in models] == [1, 2, 3, 4, 5]
    assert [m.name for m in models] == ["box", "cylinder", "torus", "capsule", "cone"]
    for m in models:
        assert m.vertex_colors is not None and m.faces.dtype == np.int32
        assert 0.05 < m.info["diameter"] < 0.2
        np.testing.assert_allclose(m.vertices.min(0) + m.vertices.max(0), 0, atol=1e-12)
    assert models[0].info["diameter"] == pytest.approx(np.sqrt(0.12**2 + 0.08**2 + 0.05**2))


def test_save_and_load_library_round_trip_and_bytes(tmp_path):
    import trimesh

    c = cube_mesh(0.1)
    trimesh.Trimesh(c.vertices, c.faces, process=False).export(tmp_path / "plain.ply")
    models = builtin_shapes() + [load_object_file(tmp_path / "plain.ply", obj_id=9, scale=1.0, unit_note="m")]
    save_library(tmp_path / "a", models)
    save_library(tmp_path / "b", models)
    for f in sorted((tmp_path / "a").iterdir()):
        assert f.read_bytes() == (tmp_path / "b" / f.name).read_bytes()
    back = load_saved_library(tmp_path / "a")
    for m, b in zip(models, back):
        assert (m.obj_id, m.name, m.base_color, m.info) == (b.obj_id, b.name, b.base_color, b.info)
        np.testing.assert_array_equal(m.vertices, b.vertices)
        np.testing.assert_array_equal(m.faces, b.faces)
    assert back[-1].vertex_colors is None or back[-1].vertex_colors.shape == (8, 3)


# ---------------------------------------------------------------------------------------------------
# Bad object files
# ---------------------------------------------------------------------------------------------------

def test_object_without_faces(tmp_path):
    p = tmp_path / "pts.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                 "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(InputError, match=r"pts\.ply: object file has 3 vertices and no faces"):
        load_library([str(p)])


def test_object_unreadable(tmp_path):
    p = tmp_path / "junk.glb"
    p.write_bytes(b"\x00\x01garbage")
    with pytest.raises(InputError, match=r"junk\.glb: object model cannot be read"):
        load_library([str(p)])


def test_object_unknown_extension(tmp_path):
    p = tmp_path / "m.stl5"
    p.write_text("x")
    with pytest.raises(InputError, match=r"unknown object file type '\.stl5'"):
        load_library([str(p)])


def test_folder_without_models(tmp_path):
    (tmp_path / "readme.txt").write_text("x")
    with pytest.raises(InputError, match="holds no object model"):
        load_library([str(tmp_path)])


def test_unknown_builtin_library():
    with pytest.raises(InputError, match="unknown built-in library 'builtin:cars'"):
        load_library(["builtin:cars"])


def test_colliding_bop_ids(tmp_path):
    for d in ("a", "b"):
        (tmp_path / d).mkdir()
        write_colored_ply(tmp_path / d / "obj_000001.ply", cube_mesh(50.0))
    with pytest.raises(InputError, match="object id 1 is also"):
        load_library([str(tmp_path / "a"), str(tmp_path / "b")])
