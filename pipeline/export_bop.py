"""BOP dataset writer, in the layout bop_toolkit reads (``docs/bop_datasets_format.md``).

::

    DATASET/camera.json                      cx, cy, fx, fy, width, height, depth_scale
    DATASET/models/obj_{obj_id:06d}.ply      binary PLY, millimetres (x y z nx ny nz [red green blue]
                                             [texture_u texture_v]); textures as obj_{obj_id:06d}.png
    DATASET/models/models_info.json          {obj_id: diameter, min_x.., size_x.., symmetries_* (mm)}
    DATASET/train_pbr/{scene_id:06d}/        chunks of ``export.chunk_size`` images
        rgb/{im_id:06d}.jpg|png
        depth/{im_id:06d}.png                uint16; depth in mm = value * depth_scale
        mask/{im_id:06d}_{gt_id:06d}.png     amodal silhouette (object alone), 0/255
        mask_visib/{im_id:06d}_{gt_id:06d}.png   visible part, 0/255
        scene_camera.json                    {im_id: cam_K, cam_R_w2c, cam_t_w2c (mm), depth_scale}
        scene_gt.json                        {im_id: [{obj_id, cam_R_m2c, cam_t_m2c (mm)}]}
        scene_gt_info.json                   {im_id: [{bbox_obj, bbox_visib, px_count_all, px_count_valid,
                                                       px_count_visib, visib_fract}]}

The names come from :mod:`pipeline.bop_layout`. Millimetres exist only here: every input is in metres (:mod:`pipeline.types`). JSON files list their
integer keys in numeric order, one entry per line, as bop_toolkit's ``save_json`` does.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.bop_layout import (DEPTH_TPATH, MASK_TPATH, MASK_VISIB_TPATH, MODEL_TEXTURE_TPATH, MODEL_TPATH,
                                 MODELS_DIR, MODELS_INFO_PATH, RGB_TPATH, SCENE_CAMERA_PATH, SCENE_GT_INFO_PATH,
                                 SCENE_GT_PATH)
from pipeline.io import atomic_write_bytes, atomic_write_image
from pipeline.types import ObjectModel

M_TO_MM = 1000.0


def _r(x: float, nd: int = 6) -> float:
    """Round for JSON text (stable, short); -0.0 becomes 0.0."""
    v = round(float(x), nd)
    return 0.0 if v == 0 else v


def bop_json_text(content: dict) -> str:
    """JSON text of ``{int key: value}`` with keys in numeric order, one per line (bop_toolkit style)."""
    lines = [f'  "{k}": {json.dumps(content[k], sort_keys=True)}' for k in sorted(content)]
    return "{\n" + ",\n".join(lines) + ("\n" if lines else "") + "}\n"


def write_bop_json(path: str | Path, content: dict) -> Path:
    return atomic_write_bytes(path, bop_json_text(content).encode("utf-8"))


# ---------------------------------------------------------------------------------------------------
# Models
# ---------------------------------------------------------------------------------------------------

def models_info_mm(obj: ObjectModel) -> dict:
    """BOP ``models_info`` entry in millimetres, from ``obj.info`` (metres) or computed from the vertices."""
    v = np.asarray(obj.vertices, dtype=np.float64)
    info = dict(obj.info or {})
    lo, hi = v.min(axis=0), v.max(axis=0)
    out = {}
    for i, ax in enumerate("xyz"):
        out[f"min_{ax}"] = float(info.get(f"min_{ax}", lo[i]))
        out[f"size_{ax}"] = float(info.get(f"size_{ax}", hi[i] - lo[i]))
    diameter = info.get("diameter")
    if not diameter:
        diameter = _diameter(v)
    out["diameter"] = float(diameter)
    res = {k: _r(val * M_TO_MM) for k, val in out.items()}
    res.update(symmetries_mm(info))
    return res


def symmetries_mm(info: dict) -> dict:
    """BOP symmetry keys of ``obj.info`` (translations in metres) with translations in millimetres.

    ``symmetries_discrete``: row-major 4x4 matrices, the last column's first three values are the
    translation; ``symmetries_continuous``: ``axis`` (unit-free) and ``offset`` (a point on the axis).
    """
    out = {}
    if "symmetries_discrete" in info:
        mats = []
        for m in info["symmetries_discrete"]:
            M = np.asarray(m, dtype=np.float64).reshape(4, 4).copy()
            M[:3, 3] *= M_TO_MM
            mats.append([_r(x, 9) for x in M[:3].reshape(-1)] + [_r(x, 9) for x in M[3]])
        out["symmetries_discrete"] = mats
    if "symmetries_continuous" in info:
        out["symmetries_continuous"] = [{"axis": [_r(x, 9) for x in s["axis"]],
                                         "offset": [_r(x * M_TO_MM) for x in s["offset"]]}
                                        for s in info["symmetries_continuous"]]
    return out


def _diameter(v: np.ndarray) -> float:
    """Largest distance between two vertices (on the convex hull, exact)."""
    if len(v) < 2:
        return 0.0
    pts = v
    if len(v) > 4:
        from scipy.spatial import ConvexHull
        from scipy.spatial.distance import pdist

        try:
            pts = v[ConvexHull(v).vertices]
        except Exception:  # noqa: BLE001 - flat/degenerate models: fall back to all points
            pts = v
        return float(pdist(pts).max())
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    return float(d.max())


def ply_bytes_mm(obj: ObjectModel, texture_file: str | None = None) -> bytes:
    """Binary little-endian PLY of a model in millimetres, with the property names bop_toolkit reads.

    Vertex properties: ``float x y z nx ny nz``, then ``uchar red green blue`` when the model has vertex
    colours, then ``float texture_u texture_v`` when it has UVs (and ``comment TextureFile``).
    """
    v = np.asarray(obj.vertices, dtype=np.float64) * M_TO_MM
    n = len(v)
    cols = [("x", "f4"), ("y", "f4"), ("z", "f4"), ("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
    has_color = obj.vertex_colors is not None
    has_uv = obj.uv is not None
    if has_color:
        cols += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if has_uv:
        cols += [("texture_u", "f4"), ("texture_v", "f4")]
    rec = np.zeros(n, dtype=np.dtype([(c, "<" + t) for c, t in cols]))
    for i, c in enumerate("xyz"):
        rec[c] = v[:, i]
    normals = np.asarray(obj.normals, dtype=np.float32)
    for i, c in enumerate(("nx", "ny", "nz")):
        rec[c] = normals[:, i]
    if has_color:
        for i, c in enumerate(("red", "green", "blue")):
            rec[c] = obj.vertex_colors[:, i]
    if has_uv:
        rec["texture_u"] = obj.uv[:, 0]
        rec["texture_v"] = obj.uv[:, 1]
    ply_type = {"f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", "comment scansynth export, units: mm"]
    if has_uv and texture_file:
        header.append(f"comment TextureFile {texture_file}")
    header.append(f"element vertex {n}")
    header += [f"property {ply_type[t]} {c}" for c, t in cols]
    faces = np.asarray(obj.faces, dtype=np.int64)
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    frec = np.zeros(len(faces), dtype=np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
    frec["n"] = 3
    frec["i"] = faces
    return ("\n".join(header) + "\n").encode("ascii") + rec.tobytes() + frec.tobytes()


def write_models(root: str | Path, objects: list[ObjectModel]) -> Path:
    """``models/obj_XXXXXX.ply`` (+ texture PNG) and ``models/models_info.json`` under ``root``."""
    root = Path(root)
    info = {}
    for obj in sorted(objects, key=lambda o: o.obj_id):
        tex = None
        if obj.texture is not None and obj.uv is not None:
            tex_path = root / MODEL_TEXTURE_TPATH.format(obj_id=obj.obj_id)
            tex = tex_path.name   # the PLY header names its texture file, beside it
            atomic_write_image(tex_path, np.asarray(obj.texture, dtype=np.uint8))
        atomic_write_bytes(root / MODEL_TPATH.format(obj_id=obj.obj_id), ply_bytes_mm(obj, tex))
        info[int(obj.obj_id)] = models_info_mm(obj)
    write_bop_json(root / MODELS_INFO_PATH, info)
    return root / MODELS_DIR


# ---------------------------------------------------------------------------------------------------
# Per image
# ---------------------------------------------------------------------------------------------------

def camera_json(K: np.ndarray, width: int, height: int, depth_scale: float) -> dict:
    """``camera.json`` content (the per-image ``cam_K`` in ``scene_camera.json`` is authoritative)."""
    return {"cx": _r(K[0, 2]), "cy": _r(K[1, 2]), "fx": _r(K[0, 0]), "fy": _r(K[1, 1]),
            "width": int(width), "height": int(height), "depth_scale": float(depth_scale)}


def scene_camera_entry(K: np.ndarray, T_c2w: np.ndarray, depth_scale: float) -> dict:
    """One ``scene_camera.json`` entry: ``cam_K`` (px), ``cam_R_w2c``, ``cam_t_w2c`` (mm), ``depth_scale``."""
    T_w2c = np.linalg.inv(np.asarray(T_c2w, dtype=np.float64))
    return {"cam_K": [_r(x) for x in np.asarray(K, dtype=np.float64).reshape(9)],
            "cam_R_w2c": [_r(x, 9) for x in T_w2c[:3, :3].reshape(9)],
            "cam_t_w2c": [_r(x * M_TO_MM) for x in T_w2c[:3, 3]],
            "depth_scale": float(depth_scale)}


def scene_gt_entries(instances: list[dict]) -> list[dict]:
    """``scene_gt.json`` entries of an image from raster annotations (metres -> mm)."""
    return [{"obj_id": int(a["obj_id"]),
             "cam_R_m2c": [_r(x, 9) for x in np.asarray(a["R_m2c"], dtype=np.float64).reshape(9)],
             "cam_t_m2c": [_r(x * M_TO_MM) for x in np.asarray(a["t_m2c"], dtype=np.float64).reshape(3)]}
            for a in instances]


def bop_box(box) -> list[int]:
    """A raster box ``[x, y, w, h]`` (w, h = pixel extent, COCO style) as bop_toolkit writes boxes.

    bop_toolkit's ``misc.calc_2d_bbox`` (used by ``calc_gt_info.py``) gives ``w = x_max - x_min``, one
    less than the pixel extent; ``[-1, -1, -1, -1]`` (nothing visible) stays as it is.
    """
    x, y, w, h = (int(v) for v in box)
    if w < 0:
        return [x, y, w, h]
    return [x, y, w - 1, h - 1]


def scene_gt_info_entries(instances: list[dict]) -> list[dict]:
    """``scene_gt_info.json`` entries of an image from raster annotations (boxes as :func:`bop_box`)."""
    return [{"bbox_obj": bop_box(a["bbox_obj"]), "bbox_visib": bop_box(a["bbox_visib"]),
             "px_count_all": int(a["px_count_all"]), "px_count_valid": int(a["px_count_valid"]),
             "px_count_visib": int(a["px_count_visib"]), "visib_fract": _r(a["visib_fract"])}
            for a in instances]


def depth_png(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """(H, W) uint16 depth image: ``round(depth_mm / depth_scale)``; 0 where invalid or out of range."""
    v = np.round(np.asarray(depth_m, dtype=np.float64) * M_TO_MM / depth_scale)
    ok = (v > 0) & (v <= np.iinfo(np.uint16).max)
    return np.where(ok, v, 0).astype(np.uint16)


def image_paths(scene_dir: str | Path, im_id: int, n_inst: int, ext: str) -> dict:
    """Paths of one image's files in a BOP scene folder."""
    d = Path(scene_dir)
    return {"rgb": d / RGB_TPATH.format(im_id=im_id, ext=ext), "depth": d / DEPTH_TPATH.format(im_id=im_id),
            "mask": [d / MASK_TPATH.format(im_id=im_id, gt_id=g) for g in range(n_inst)],
            "mask_visib": [d / MASK_VISIB_TPATH.format(im_id=im_id, gt_id=g) for g in range(n_inst)]}


def write_image_files(scene_dir: str | Path, im_id: int, *, rgb: np.ndarray, depth_m: np.ndarray,
                      amodal: np.ndarray, visib: np.ndarray, ext: str, depth_scale: float,
                      jpeg_quality: int = 95) -> dict:
    """Write rgb, depth, mask and mask_visib files of one image (each atomically); return their paths.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    depth_m : (H, W) float32, metres, 0 = invalid
    amodal : (N, H, W) bool
    visib : (N, H, W) bool, visible masks (``mask_visib``)
    ext : "jpg" | "png"
    """
    p = image_paths(scene_dir, im_id, len(amodal), ext)
    atomic_write_image(p["rgb"], np.asarray(rgb, dtype=np.uint8), jpeg_quality=jpeg_quality)
    atomic_write_image(p["depth"], depth_png(depth_m, depth_scale))
    for g in range(len(amodal)):
        atomic_write_image(p["mask"][g], amodal[g].astype(np.uint8) * 255)
        atomic_write_image(p["mask_visib"][g], visib[g].astype(np.uint8) * 255)
    return p


def write_scene_files(scene_dir: str | Path, scene_camera: dict, scene_gt: dict, scene_gt_info: dict) -> None:
    """``scene_camera.json``, ``scene_gt.json``, ``scene_gt_info.json`` of one BOP scene folder."""
    d = Path(scene_dir)
    write_bop_json(d / SCENE_CAMERA_PATH, scene_camera)
    write_bop_json(d / SCENE_GT_PATH, scene_gt)
    write_bop_json(d / SCENE_GT_INFO_PATH, scene_gt_info)


# ---------------------------------------------------------------------------------------------------
# Reading back (for checks; mirrors bop_toolkit's inout.load_ply for the subset written here)
# ---------------------------------------------------------------------------------------------------

def read_ply_mm(path: str | Path) -> dict:
    """Read a PLY written by :func:`ply_bytes_mm`: ``{"pts" (V,3) mm, "faces" (T,3), "normals", ...}``."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    props, nv, nf = [], 0, 0
    section = None
    for line in header:
        w = line.split()
        if w[:2] == ["element", "vertex"]:
            nv, section = int(w[2]), "v"
        elif w[:2] == ["element", "face"]:
            nf, section = int(w[2]), "f"
        elif w[:1] == ["property"] and section == "v":
            props.append((w[2], {"float": "<f4", "uchar": "u1", "double": "<f8", "int": "<i4"}[w[1]]))
    vdt = np.dtype(props)
    rec = np.frombuffer(data, dtype=vdt, count=nv, offset=end)
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    frec = np.frombuffer(data, dtype=fdt, count=nf, offset=end + nv * vdt.itemsize)
    out = {"pts": np.stack([rec[c] for c in "xyz"], axis=1).astype(np.float64),
           "faces": frec["i"].astype(np.int64)}
    names = set(rec.dtype.names)
    if {"nx", "ny", "nz"} <= names:
        out["normals"] = np.stack([rec[c] for c in ("nx", "ny", "nz")], axis=1)
    if {"red", "green", "blue"} <= names:
        out["colors"] = np.stack([rec[c] for c in ("red", "green", "blue")], axis=1)
    if not np.all(frec["n"] == 3):
        raise ValueError(f"{path}: non-triangle faces")
    return out
