"""Object libraries: loading, unit normalisation, BOP ``models_info``, and the built-in demo shapes.

Sources (entries of ``objects.paths``):

- a BOP ``models/`` folder (``obj_XXXXXX.ply`` in millimetres with vertex colours or a texture, and
  ``models_info.json``), or a BOP dataset folder holding one (``lmo/`` with ``lmo/models/``): ids come
  from the file names;
- a single ``.ply``, ``.obj`` (+ ``.mtl`` + UV texture), ``.gltf``/``.glb`` file, or a folder of such
  files (sorted by name): ids are given in order after the largest BOP id;
- ``builtin:shapes``: a few procedural, vertex-coloured primitives with ids 1..N.

Units: ``objects.scale`` (metres per file unit) when set, else from the format (BOP: mm, glTF: m by its
specification, other files: m). An object whose size is implausible for the assumed unit gets an
:class:`~pipeline.scanformats.common.IngestWarning` naming the unit and the fix.

Each model keeps its render mesh with its material (texture + UVs, or vertex colours, or a base colour;
metallic and roughness from glTF, defaults otherwise) and ``info`` = BOP models_info in metres
(``diameter`` exactly: the largest distance between two vertices, computed on the convex hull).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np

from pipeline.errors import InputError
from pipeline.scanformats.common import warn
from pipeline.tolerances import OBJECT_DIAMETER_PLAUSIBLE_M
from pipeline.types import ObjectModel

log = logging.getLogger(__name__)

BUILTIN_SHAPES = "builtin:shapes"
MODEL_EXTS = (".ply", ".obj", ".gltf", ".glb")
BOP_RX = re.compile(r"obj_(\d{6})\.ply")


# ---------------------------------------------------------------------------------------------------
# models_info
# ---------------------------------------------------------------------------------------------------

def max_pairwise_distance(points: np.ndarray) -> float:
    """Largest distance between two of ``points`` (N, 3), exactly: the pair lies on the convex hull."""
    from scipy.spatial import ConvexHull, QhullError

    P = np.asarray(points, dtype=np.float64)
    if len(P) < 2:
        return 0.0
    try:
        H = P[ConvexHull(P).vertices]
    except (QhullError, ValueError):  # flat or degenerate: every point is a candidate
        H = np.unique(P, axis=0)
    best = 0.0
    for s in range(0, len(H), 1024):
        d = np.einsum("ijk,ijk->ij", H[s:s + 1024, None] - H[None], H[s:s + 1024, None] - H[None])
        best = max(best, float(d.max()))
    return float(np.sqrt(best))


def models_info(vertices: np.ndarray) -> dict:
    """BOP models_info of a model (same unit as ``vertices``): diameter, min_x/y/z, size_x/y/z."""
    V = np.asarray(vertices, dtype=np.float64)
    lo, hi = V.min(0), V.max(0)
    return {"diameter": max_pairwise_distance(V), "min_x": float(lo[0]), "min_y": float(lo[1]),
            "min_z": float(lo[2]), "size_x": float(hi[0] - lo[0]), "size_y": float(hi[1] - lo[1]),
            "size_z": float(hi[2] - lo[2])}


def _bop_symmetries(entry: dict, scale: float, where: str) -> dict:
    """Symmetry keys of a models_info.json entry with translations converted to metres.

    A missing key means no symmetry of that kind. A malformed one (not a list; a discrete symmetry that
    is not 16 numbers, a row-major 4x4 matrix; a continuous one without a 3-number ``axis`` and
    ``offset``) raises :class:`InputError` naming ``where`` (file and object) and the fix.
    """
    fix = ("BOP's format is \"symmetries_discrete\": [[16 numbers, a row-major 4x4 matrix], ...] and "
           "\"symmetries_continuous\": [{\"axis\": [x, y, z], \"offset\": [x, y, z]}, ...]; fix or remove it")

    def numbers(v, n: int) -> list[float] | None:
        if not isinstance(v, (list, tuple)) or len(v) != n:
            return None
        if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in v):
            return None
        return [float(x) for x in v]

    out = {}
    if "symmetries_discrete" in entry:
        sd = entry["symmetries_discrete"]
        if not isinstance(sd, list):
            raise InputError(f"{where}: symmetries_discrete is {sd!r}, not a list; {fix}")
        mats = []
        for m in sd:
            vals = numbers(m, 16)
            if vals is None:
                raise InputError(f"{where}: symmetries_discrete entry {m!r} is not 16 numbers; {fix}")
            M = np.asarray(vals, dtype=np.float64).reshape(4, 4)
            M[:3, 3] *= scale
            mats.append(M.reshape(-1).tolist())
        out["symmetries_discrete"] = mats
    if "symmetries_continuous" in entry:
        sc = entry["symmetries_continuous"]
        if not isinstance(sc, list):
            raise InputError(f"{where}: symmetries_continuous is {sc!r}, not a list; {fix}")
        conts = []
        for c in sc:
            axis = numbers(c.get("axis"), 3) if isinstance(c, dict) else None
            offset = numbers(c.get("offset"), 3) if isinstance(c, dict) else None
            if axis is None or offset is None:
                raise InputError(f"{where}: symmetries_continuous entry {c!r} needs \"axis\" and \"offset\", "
                                 f"3 numbers each; {fix}")
            conts.append({"axis": axis, "offset": [x * scale for x in offset]})
        out["symmetries_continuous"] = conts
    return out


# ---------------------------------------------------------------------------------------------------
# One file
# ---------------------------------------------------------------------------------------------------

class _ModelFolderResolver:
    """The files a model file refers to (a glTF's buffers and images, an OBJ's materials and textures),
    found in the model's folder; trimesh's resolver interface (``get``, ``[]``).

    A reference must name a file inside that folder: ``../`` or an absolute path is refused (a model
    made elsewhere must not make the pipeline read files beside it). The file found there may be a
    symlink to anywhere and is followed: whoever made the link chose the file (trimesh's own resolver
    refuses it because the link's target lies outside the folder). When the model file itself is a
    symlink, the folder of its target is searched next. References not found are kept in ``missing``
    and ``outside`` for the error message.
    """

    def __init__(self, path: Path):
        folder = Path(os.path.abspath(path)).parent
        self.roots = [folder]
        real = path.resolve().parent
        if real != folder.resolve():
            self.roots.append(real)
        self.missing: list[str] = []
        self.outside: list[str] = []

    def get(self, name: str) -> bytes:
        name = name.strip()
        for root in self.roots:
            # as written, without a leading "/", then the bare file name (trimesh's own candidates)
            for cand in dict.fromkeys((name, name.lstrip("/"), os.path.basename(name))):
                p = Path(os.path.normpath(root / cand))
                if p.is_relative_to(root) and p.is_file():
                    return p.read_bytes()
        if Path(os.path.normpath(self.roots[0] / name)).is_relative_to(self.roots[0]):
            self.missing.append(name)
        else:
            self.outside.append(name)
        raise FileNotFoundError(name)

    def __getitem__(self, name: str) -> bytes:
        return self.get(name)

    def error(self, path: Path) -> str | None:
        """The message for a model that failed to load because of its references, or None."""
        folder = self.roots[0]
        if self.outside:
            return (f"{path}: the model refers to {self.outside[0]!r}, outside its folder {folder}; a model's "
                    f"files must be in its folder (a model must not read other files): put the file, or a "
                    f"symlink to it, in {folder} and refer to it by its name there, or export the model as "
                    f"one .glb file")
        if self.missing:
            return (f"{path}: the model refers to {self.missing[0]!r}, which is not in {folder}; copy the "
                    f"file exported with the model there (a symlink to it is fine), or export the model as "
                    f"one .glb file")
        return None


def _load_trimesh(path: Path):
    import trimesh

    resolver = _ModelFolderResolver(path)
    try:
        loaded = trimesh.load(str(path), process=False, resolver=resolver)
    except Exception as e:  # noqa: BLE001 - trimesh raises many types for bad files
        msg = resolver.error(path)
        if msg is not None:
            raise InputError(msg) from None
        raise InputError(f"{path}: object model cannot be read ({type(e).__name__}: {e}); re-export it as "
                         f"PLY, OBJ or glTF") from None
    if isinstance(loaded, trimesh.Scene):
        if not loaded.geometry:
            raise InputError(f"{path}: object file holds no mesh (no faces); export the model with its "
                             f"triangles")
        meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if len(loaded.geometry) > 1 \
            else None
        if meshes is None:
            node = loaded.graph.nodes_geometry[0]
            T, gname = loaded.graph[node]
            m = loaded.geometry[gname].copy()
            m.apply_transform(T)
            return m
        if not meshes:
            raise InputError(f"{path}: object file holds no triangle mesh; export the model with its faces")
        if len(meshes) == 1:
            return meshes[0]
        # Several parts: one mesh; textures cannot be merged safely, so they become vertex colours.
        for g in meshes:
            if g.visual.kind == "texture":
                g.visual = g.visual.to_color()
        return trimesh.util.concatenate(meshes)
    return loaded


def _image_array(img) -> np.ndarray | None:
    if img is None:
        return None
    return np.ascontiguousarray(np.asarray(img.convert("RGB"), dtype=np.uint8))


def load_object_file(path: str | Path, *, obj_id: int, scale: float, unit_note: str,
                     name: str | None = None) -> ObjectModel:
    """Load one object model file and convert it to metres.

    Parameters
    ----------
    path : .ply, .obj, .gltf or .glb file.
    obj_id : library id (>= 1).
    scale : metres per file unit.
    unit_note : how the unit was chosen (for warnings), e.g. ``"millimetres (BOP)"``.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: object file is missing; fix objects.paths")
    m = _load_trimesh(path)
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        nv = len(getattr(m, "vertices", []))
        raise InputError(f"{path}: object file has {nv} vertices and no faces (a point cloud?); export the "
                         f"model as a triangle mesh")
    V = np.asarray(m.vertices, dtype=np.float64) * scale
    F = np.asarray(m.faces, dtype=np.int32)
    if not np.all(np.isfinite(V)):
        raise InputError(f"{path}: object has non-finite vertex coordinates; repair the model")
    N = np.asarray(m.vertex_normals, dtype=np.float64)
    n = np.linalg.norm(N, axis=1)
    if np.any(np.abs(n - 1.0) > 1e-3):  # zero or unnormalised normals in the file: recompute those
        calc = np.asarray(trimesh.Trimesh(V, F, process=False).vertex_normals, dtype=np.float64)
        bad = n < 0.5
        N = np.where(bad[:, None], calc, N / np.maximum(n, 1e-12)[:, None])
        N[np.linalg.norm(N, axis=1) < 0.5] = (0.0, 0.0, 1.0)  # vertices used by no face: any unit normal
    N = N.astype(np.float32)
    vc = uv = tex = None
    base = (0.8, 0.8, 0.8)
    metallic, roughness = 0.0, 0.5
    vis = m.visual
    if vis.kind == "texture":
        mat = vis.material
        img = getattr(mat, "baseColorTexture", None) or getattr(mat, "image", None)
        if isinstance(mat, trimesh.visual.material.PBRMaterial):
            if mat.metallicFactor is not None:
                metallic = float(mat.metallicFactor)
            if mat.roughnessFactor is not None:
                roughness = float(mat.roughnessFactor)
            f = mat.baseColorFactor
            if f is not None:
                base = tuple(float(x) / 255.0 for x in np.asarray(f)[:3])
        if img is not None and vis.uv is not None:
            tex = _image_array(img)
            uv = np.asarray(vis.uv, dtype=np.float32)
        else:
            vc = np.asarray(vis.to_color().vertex_colors)[:, :3].astype(np.uint8)
    elif vis.kind == "vertex":
        vc = np.asarray(vis.vertex_colors)[:, :3].astype(np.uint8)
    elif vis.kind == "face":
        vc = np.asarray(vis.face_colors_to_vertex_colors() if hasattr(vis, "face_colors_to_vertex_colors")
                        else vis.vertex_colors)[:, :3].astype(np.uint8)
    info = models_info(V)
    lo, hi = OBJECT_DIAMETER_PLAUSIBLE_M
    if not lo <= info["diameter"] <= hi:
        d_file = info["diameter"] / scale
        warn(f"{path}: object is {info['diameter']:.4g} m across with {unit_note} assumed ({d_file:.4g} file "
             f"units); objects are usually {lo}-{hi} m: if the file is in another unit set objects.scale "
             f"(metres per unit, e.g. 0.001 for millimetres)")
    return ObjectModel(obj_id=int(obj_id), name=name or path.stem, source_path=str(path.resolve()),
                       vertices=V, faces=F, normals=N, vertex_colors=vc, uv=uv, texture=tex,
                       base_color=base, metallic=metallic, roughness=roughness, info=info)


# ---------------------------------------------------------------------------------------------------
# Libraries
# ---------------------------------------------------------------------------------------------------

def _bop_dir(p: Path) -> Path | None:
    """The BOP models folder at or directly under ``p``, if any."""
    for d in (p, p / "models"):
        if d.is_dir() and ((d / "models_info.json").is_file() or any(BOP_RX.fullmatch(f.name) for f in d.iterdir())):
            return d
    return None


def _load_one(problems: list[str] | None, path: Path, **kw) -> ObjectModel | None:
    """:func:`load_object_file`; with a ``problems`` list, an unreadable file is recorded there and skipped."""
    try:
        return load_object_file(path, **kw)
    except InputError as e:
        if problems is None:
            raise
        log.error("object skipped: %s", e)
        problems.append(str(e))
        return None


def _load_bop(d: Path, scale_cfg: float, problems: list[str] | None = None) -> list[ObjectModel]:
    import json

    scale = scale_cfg if scale_cfg > 0 else 0.001
    note = f"{scale} m per unit (objects.scale)" if scale_cfg > 0 else "millimetres (BOP models)"
    files = sorted(f for f in d.iterdir() if BOP_RX.fullmatch(f.name))
    if not files:
        raise InputError(f"{d}: BOP models folder has no obj_XXXXXX.ply files; point objects.paths at the "
                         f"folder holding them")
    ref: dict = {}
    ip = d / "models_info.json"
    if ip.is_file():
        try:
            ref = json.loads(ip.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise InputError(f"{ip}: cannot be read as JSON ({e}); fix or delete it") from None
        if not isinstance(ref, dict):
            raise InputError(f"{ip}: is {type(ref).__name__}, not BOP's {{\"obj_id\": {{diameter, ...}}}} object; "
                             f"fix or delete it")
    out = []
    for f in files:
        oid = int(BOP_RX.fullmatch(f.name).group(1))
        m = _load_one(problems, f, obj_id=oid, scale=scale, unit_note=note)
        if m is None:
            continue
        entry = ref.get(str(oid), {})
        if not isinstance(entry, dict):
            raise InputError(f"{ip} (object {oid}): entry is {entry!r}, not an object with diameter, min_x, ...; "
                             f"fix or remove it")
        if entry:
            info = dict(m.info)
            info.update(_bop_symmetries(entry, scale, f"{ip} (object {oid})"))
            d_ref = float(entry.get("diameter", info["diameter"] / scale)) * scale
            if abs(d_ref - info["diameter"]) > 1e-4:
                warn(f"{f}: diameter {info['diameter'] / scale:.3f} computed from the vertices differs from "
                     f"models_info.json's {d_ref / scale:.3f}; the computed value is used")
            m = _replace(m, info=info)
        out.append(m)
    return out


def _replace(m: ObjectModel, **kw) -> ObjectModel:
    import dataclasses

    return dataclasses.replace(m, **kw)


def model_files(p: Path) -> list[Path]:
    """Model files a path names: the file itself, or the model files of a folder (sorted)."""
    if p.is_file():
        if p.suffix.lower() not in MODEL_EXTS:
            raise InputError(f"{p}: unknown object file type {p.suffix!r}; use one of {', '.join(MODEL_EXTS)}")
        return [p]
    files = sorted(f for f in p.iterdir() if f.is_file() and f.suffix.lower() in MODEL_EXTS)
    if not files:
        raise InputError(f"{p}: folder holds no object model ({', '.join(MODEL_EXTS)}) and is not a BOP "
                         f"models folder; fix objects.paths")
    return files


def load_library(paths: tuple[str, ...] | list[str], scale: float = 0.0,
                 problems: list[str] | None = None) -> list[ObjectModel]:
    """Every object of the sources ``paths`` (see the module docstring), ids unique, sorted by id.

    Parameters
    ----------
    paths : files, folders or ``"builtin:shapes"``.
    scale : metres per file unit; 0 = from the format.
    problems : when given, a model file that cannot be read is skipped and its error appended here
        (the ingest stage reports them and exits 1) instead of failing the whole library. Its id stays
        taken, so the other objects keep their ids once it is fixed. A path that does not exist, or a
        library where nothing loads, is still an error.
    """
    bop: list[ObjectModel] = []
    files: list[tuple[Path, str]] = []
    builtin: list[ObjectModel] = []
    for raw in paths:
        if raw == BUILTIN_SHAPES:
            builtin = builtin_shapes()
            continue
        if raw.startswith("builtin:"):
            raise InputError(f"objects.paths: unknown built-in library {raw!r}; valid: {BUILTIN_SHAPES!r}")
        p = Path(raw)
        if not p.exists():
            raise InputError(f"{p}: object path does not exist; fix objects.paths")
        d = _bop_dir(p) if p.is_dir() else None
        if d is not None:
            got = _load_bop(d, scale, problems)
            taken = {m.obj_id: m for m in bop}
            for m in got:
                if m.obj_id in taken:
                    raise InputError(f"{m.source_path}: object id {m.obj_id} is also {taken[m.obj_id].source_path}; "
                                     f"BOP libraries with the same ids cannot be mixed in one run")
            bop += got
        else:
            files += [(f, raw) for f in model_files(p)]
    out = list(bop)
    next_id = max([m.obj_id for m in out], default=0) + 1
    if builtin:
        builtin = [_replace(m, obj_id=next_id + k) for k, m in enumerate(builtin)] if out else builtin
        out += builtin
        next_id = max(m.obj_id for m in out) + 1
    for f, _ in files:
        ext = f.suffix.lower()
        if scale > 0:
            sc, note = scale, f"{scale} m per unit (objects.scale)"
        elif ext in (".gltf", ".glb"):
            sc, note = 1.0, "metres (glTF)"
        else:
            sc, note = 1.0, "metres (default for .ply/.obj; set objects.scale otherwise)"
        m = _load_one(problems, f, obj_id=next_id, scale=sc, unit_note=note)
        if m is not None:
            out.append(m)
        next_id += 1
    if not out:
        why = f" that can be read ({'; '.join(problems)})" if problems else ""
        raise InputError(f"objects.paths names no object{why}; give at least one model file or folder")
    return sorted(out, key=lambda m: m.obj_id)


def builtin_shapes() -> list[ObjectModel]:
    """Procedural vertex-coloured demo objects (ids 1..5): box, cylinder, torus, capsule, cone.

    Sizes 5-15 cm; colours carry a lighter band on the +x side so that rotations are visible.
    """
    import trimesh

    specs = [
        ("box", trimesh.creation.box(extents=(0.12, 0.08, 0.05)), (200, 40, 40)),
        ("cylinder", trimesh.creation.cylinder(radius=0.035, height=0.12, sections=48), (40, 80, 200)),
        ("torus", trimesh.creation.torus(major_radius=0.05, minor_radius=0.018, major_sections=48,
                                         minor_sections=24), (230, 190, 30)),
        ("capsule", trimesh.creation.capsule(height=0.08, radius=0.03, count=(24, 24)), (40, 170, 70)),
        ("cone", trimesh.creation.cone(radius=0.045, height=0.09, sections=48), (240, 120, 20)),
    ]
    out = []
    for k, (name, m, rgb) in enumerate(specs):
        V = np.asarray(m.vertices, dtype=np.float64)
        V = V - 0.5 * (V.min(0) + V.max(0))  # model frame at the bounding box centre
        F = np.asarray(m.faces, dtype=np.int32)
        import trimesh as _t

        mm = _t.Trimesh(V, F, process=False)
        band = (V[:, 0] > 0.25 * V[:, 0].max())[:, None]
        col = np.where(band, np.minimum(255, np.asarray(rgb) + 60), np.asarray(rgb)).astype(np.uint8)
        out.append(ObjectModel(obj_id=k + 1, name=name, source_path=BUILTIN_SHAPES, vertices=V, faces=F,
                               normals=np.asarray(mm.vertex_normals, dtype=np.float32), vertex_colors=col,
                               uv=None, texture=None, base_color=tuple(c / 255.0 for c in rgb),
                               metallic=0.0, roughness=0.5, info=models_info(V)))
    return out


# ---------------------------------------------------------------------------------------------------
# Saving and loading the normalised library
# ---------------------------------------------------------------------------------------------------

LIBRARY_JSON = "library.json"


def save_library(out_dir: str | Path, models: list[ObjectModel]) -> Path:
    """Write ``obj_XXXXXX.npz`` per model and ``library.json`` into ``out_dir`` (deterministic bytes)."""
    from pipeline.io import atomic_save_npz, atomic_write_json

    out_dir = Path(out_dir)
    entries = []
    for m in models:
        fname = f"obj_{m.obj_id:06d}.npz"
        arrays = {"vertices": m.vertices.astype(np.float64), "faces": m.faces.astype(np.int32),
                  "normals": m.normals.astype(np.float32)}
        if m.vertex_colors is not None:
            arrays["vertex_colors"] = m.vertex_colors.astype(np.uint8)
        if m.uv is not None:
            arrays["uv"] = m.uv.astype(np.float32)
        if m.texture is not None:
            arrays["texture"] = m.texture.astype(np.uint8)
        atomic_save_npz(out_dir / fname, **arrays)
        entries.append({"obj_id": m.obj_id, "name": m.name, "source_path": m.source_path, "file": fname,
                        "base_color": list(m.base_color), "metallic": m.metallic, "roughness": m.roughness,
                        "info": m.info, "num_vertices": int(len(m.vertices)), "num_faces": int(len(m.faces)),
                        "material": "texture" if m.texture is not None else
                        ("vertex_colors" if m.vertex_colors is not None else "base_color")})
    return atomic_write_json(out_dir / LIBRARY_JSON, {"units": "metres", "objects": entries})


def load_saved_library(out_dir: str | Path) -> list[ObjectModel]:
    """Read what :func:`save_library` wrote; models sorted by id."""
    from pipeline.io import load_npz, read_json

    out_dir = Path(out_dir)
    lib = out_dir / LIBRARY_JSON
    if not lib.is_file():
        raise InputError(f"{lib} is missing; run 'scansynth ingest' first")
    out = []
    for e in read_json(lib)["objects"]:
        a = load_npz(out_dir / e["file"])
        out.append(ObjectModel(obj_id=int(e["obj_id"]), name=e["name"], source_path=e["source_path"],
                               vertices=a["vertices"], faces=a["faces"], normals=a["normals"],
                               vertex_colors=a.get("vertex_colors"), uv=a.get("uv"), texture=a.get("texture"),
                               base_color=tuple(e["base_color"]), metallic=float(e["metallic"]),
                               roughness=float(e["roughness"]), info=dict(e["info"])))
    return sorted(out, key=lambda m: m.obj_id)
