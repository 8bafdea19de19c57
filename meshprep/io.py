"""Reading and writing meshes, reports and arrays.

Meshes are read and written with PyMeshLab, which keeps vertex colours, UVs (per vertex and per
wedge) and texture images. Every output is written atomically (temporary file in the target's
folder, then ``os.replace``), so a killed run never leaves a truncated file. JSON and NPZ outputs are
deterministic (sorted keys; NPZ without zip timestamps).
"""

from __future__ import annotations

import io as _io
import json
import logging
import os
import shutil
import tempfile
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from meshprep.errors import InputError

TMP_MARK = ".tmp-"  # temporary files of the atomic writers: <name>.tmp-<pid>

if TYPE_CHECKING:  # pragma: no cover
    import pymeshlab

log = logging.getLogger(__name__)

# Extensions PyMeshLab reads (and writes) that this package accepts.
READ_EXTENSIONS = (".ply", ".obj", ".off", ".stl", ".gltf", ".glb", ".3ds", ".wrl", ".dae")
WRITE_EXTENSIONS = (".ply", ".obj", ".off", ".stl")


def check_readable(path: str | Path) -> Path:
    """Return ``path`` as a Path if it is an existing, non-empty file of a supported mesh format.

    Raises
    ------
    InputError
        Naming the file and the fix (missing file, folder, empty file, unknown extension).
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file; check the path")
    if not p.is_file():
        raise InputError(f"{p}: is a folder, not a mesh file; give a {'/'.join(READ_EXTENSIONS)} file")
    if p.suffix.lower() not in READ_EXTENSIONS:
        raise InputError(f"{p}: unsupported extension {p.suffix!r}; convert it to one of "
                         f"{', '.join(READ_EXTENSIONS)} (or rename it if the extension is wrong)")
    if p.stat().st_size == 0:
        raise InputError(f"{p}: file is empty (0 bytes); re-export the mesh")
    return p


def check_writable(path: str | Path, allowed: tuple[str, ...] = WRITE_EXTENSIONS) -> Path:
    """Return ``path`` as a Path if its extension is one we write; raise InputError otherwise."""
    p = Path(path)
    if p.suffix.lower() not in allowed:
        raise InputError(f"{p}: cannot write {p.suffix!r} files; use one of {', '.join(allowed)}")
    if p.exists() and p.is_dir():
        raise InputError(f"{p}: is a folder; give a file name for the output")
    return p


def faces_with_missing_vertices(path: str | Path, limit: int = 5) -> dict:
    """Faces of an OBJ file that point at a vertex the file does not have (PyMeshLab drops them).

    ``f 1 2 9`` in a file with three vertices is read as no face at all, silently; this finds them so
    the caller can say what was dropped. Indices are 1-based or negative (relative to the vertices read
    so far), as the OBJ format defines; ``v/vt/vn`` triplets use their first number. Other formats
    (PLY, OFF, STL, glTF) index vertices in binary or by construction and are not checked.

    Returns
    -------
    dict: ``count`` (faces dropped) and ``examples`` (up to ``limit`` strings
    ``"line L: f 1 2 9 (vertex 9 of 3)"``). ``count`` is 0 for files that are not OBJ.
    """
    p = Path(path)
    out: dict = {"count": 0, "examples": []}
    if p.suffix.lower() != ".obj":
        return out
    n_v = 0
    with open(p, "r", encoding="utf-8", errors="replace") as fh:
        for line_no, line in enumerate(fh, 1):
            if line.startswith("v "):
                n_v += 1
            elif line.startswith("f "):
                bad = []
                for tok in line.split()[1:]:
                    head = tok.split("/", 1)[0]
                    try:
                        i = int(head)
                    except ValueError:
                        bad.append(tok)
                        continue
                    j = i if i > 0 else n_v + 1 + i
                    if not 1 <= j <= n_v:
                        bad.append(tok)
                if bad:
                    out["count"] += 1
                    if len(out["examples"]) < limit:
                        out["examples"].append(f"line {line_no}: {line.strip()} (vertex "
                                               f"{', '.join(bad)} of {n_v})")
    return out


def load_meshset(path: str | Path) -> "pymeshlab.MeshSet":
    """Load a mesh file into a PyMeshLab MeshSet holding exactly one (current) mesh.

    Files with several meshes (glTF scenes) are merged into one. Colours, UVs and textures are kept.

    Raises
    ------
    InputError
        When the file is missing, empty, of an unknown format, truncated or otherwise unreadable.
    """
    import pymeshlab

    p = check_readable(path)
    ms = pymeshlab.MeshSet()
    try:
        ms.load_new_mesh(str(p))
    except pymeshlab.PyMeshLabException as e:
        detail = " ".join(str(e).split())
        raise InputError(f"{p}: could not read the mesh ({detail}); the file is truncated or corrupt, "
                         f"re-export it") from None
    if ms.mesh_number() > 1:
        ms.generate_by_merging_visible_meshes()
        keep = ms.current_mesh_id()
        for mid in [m for m in range(ms.mesh_number() + 8) if ms.mesh_id_exists(m) and m != keep]:
            ms.set_current_mesh(mid)
            ms.delete_current_mesh()
        ms.set_current_mesh(keep)
    dropped = faces_with_missing_vertices(p)
    if dropped["count"]:
        log.warning("%s: dropped %d face%s that point%s at a missing vertex (%s%s); check the exporter",
                    p, dropped["count"], "" if dropped["count"] == 1 else "s",
                    "s" if dropped["count"] == 1 else "", "; ".join(dropped["examples"]),
                    ", ..." if dropped["count"] > len(dropped["examples"]) else "")
    names = list(ms.current_mesh().textures()) if ms.current_mesh().texture_number() else []
    if "dummy.png" in names:
        # PyMeshLab could not decode a texture image (its wheels read PNG but not JPEG); UVs are
        # kept, the image is written as a blank "dummy.png". Convert the texture to PNG to keep it.
        log.warning("%s: a texture image could not be read (PyMeshLab reads PNG, not JPEG); UVs are "
                    "kept but the texture is written as a blank dummy.png; convert it to PNG", p)
    return ms


def meshset_from_arrays(vertices: np.ndarray, faces: np.ndarray,
                        vertex_colors: np.ndarray | None = None) -> "pymeshlab.MeshSet":
    """Build a one-mesh MeshSet from arrays.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    vertex_colors : (V, 3) or (V, 4) uint8, optional
    """
    import pymeshlab

    v = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.ascontiguousarray(faces, dtype=np.int32).reshape(-1, 3)
    kw: dict[str, Any] = {}
    if vertex_colors is not None:
        c = np.asarray(vertex_colors, dtype=np.float64) / 255.0
        if c.shape[1] == 3:
            c = np.hstack([c, np.ones((len(c), 1))])
        kw["v_color_matrix"] = np.ascontiguousarray(c)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f, **kw))
    return ms


def arrays_of(ms: "pymeshlab.MeshSet") -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V,3) float64, faces (F,3) int32) of the current mesh of ``ms`` (copies)."""
    m = ms.current_mesh()
    return (np.array(m.vertex_matrix(), dtype=np.float64).reshape(-1, 3),
            np.array(m.face_matrix(), dtype=np.int32).reshape(-1, 3))


def load_arrays(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a mesh file and return (vertices (V,3) float64, faces (F,3) int32)."""
    return arrays_of(load_meshset(path))


def save_meshset(ms: "pymeshlab.MeshSet", path: str | Path) -> Path:
    """Write the current mesh of ``ms`` atomically, keeping colours, UVs and textures.

    The files (mesh, and for OBJ its .mtl and texture images) are written into a temporary folder
    beside the target and renamed into place one by one.
    """
    p = check_writable(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    m = ms.current_mesh()
    kw: dict[str, Any] = {}
    if p.suffix.lower() == ".ply":
        kw["binary"] = True
    if p.suffix.lower() in (".ply", ".obj", ".off"):
        kw["save_vertex_color"] = bool(m.has_vertex_color())
    tmpdir = Path(tempfile.mkdtemp(prefix=f".{p.name}.tmp-", dir=p.parent))
    try:
        ms.save_current_mesh(str(tmpdir / p.name), **kw)
        for produced in sorted(tmpdir.iterdir()):
            os.replace(produced, p.parent / produced.name)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
    return p


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"cannot write {type(o).__name__} as JSON")


def dumps_json(obj: Any, *, indent: int | None = 2) -> str:
    """Deterministic JSON text (sorted keys, arrays as lists, NaN refused)."""
    return json.dumps(obj, indent=indent, sort_keys=True, default=_json_default, allow_nan=False) + "\n"


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write bytes to ``path`` atomically (temporary file in the same folder, then rename)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f"{p.name}{TMP_MARK}{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, p)
    return p


def write_json(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as deterministic JSON, atomically."""
    return atomic_write_bytes(path, dumps_json(obj).encode("utf-8"))


# zlib level of NPZ members: 1, not the default 6. The arrays are mostly float images, which level 6
# shrinks only 4 % more (24 raster/trace/composite files of 7-Scenes: 14.1 vs 13.5 MB of 163 MB) at
# about twice the CPU; every stage writes them, the trace stage ~0.08 s per frame at level 6.
NPZ_LEVEL = 1


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """NPZ file contents with fixed zip timestamps and sorted names: equal arrays give equal bytes."""
    buf = _io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            arr = _io.BytesIO()
            np.lib.format.write_array(arr, np.asanyarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, arr.getvalue(), compresslevel=NPZ_LEVEL)
    return buf.getvalue()


def save_npz(path: str | Path, arrays: dict[str, np.ndarray]) -> Path:
    """Save arrays as an NPZ file (:func:`npz_bytes`), atomically."""
    return atomic_write_bytes(path, npz_bytes(arrays))


def load_npz(path: str | Path) -> dict[str, np.ndarray]:
    """Every array of an NPZ file, as a dict (the file is closed on return)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such file; check the path")
    try:
        with np.load(p, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise InputError(f"{p}: not a readable NPZ file ({e}); regenerate it") from None


def load_cameras(path: str | Path) -> np.ndarray:
    """Camera positions from a file, for orienting scans and signing room distances.

    Accepted: ``.npy`` with (N,3) positions or (N,4,4) camera-to-world poses; text (``.txt``) with N
    rows of 3 numbers (positions) or 16 numbers (row-major 4x4 camera-to-world poses), or a single
    4x4 pose.

    Returns
    -------
    (N, 3) float64 camera centres, in the mesh's units.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such camera file; check --cameras")
    try:
        arr = np.load(p, allow_pickle=False) if p.suffix.lower() == ".npy" else np.loadtxt(p, ndmin=2)
    except (OSError, ValueError) as e:
        raise InputError(f"{p}: could not read camera positions ({e}); give a .npy or .txt file") from None
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[1:] == (4, 4):
        pos = arr[:, :3, 3]
    elif arr.ndim == 2 and arr.shape == (4, 4):
        pos = arr[None, :3, 3]
    elif arr.ndim == 2 and arr.shape[1] == 16:
        pos = arr.reshape(-1, 4, 4)[:, :3, 3]
    elif arr.ndim == 2 and arr.shape[1] == 3:
        pos = arr
    else:
        raise InputError(f"{p}: camera array has shape {arr.shape}; expected (N,3) positions or "
                         f"(N,4,4) / (N,16) camera-to-world poses")
    pos = pos[np.isfinite(pos).all(axis=1)]
    if len(pos) == 0:
        raise InputError(f"{p}: no finite camera positions; check the file")
    return pos
