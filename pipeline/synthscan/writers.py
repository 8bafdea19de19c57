"""Writers for the five real scan layouts, and the mesh files they carry.

Each layout is written the way its real producer writes it:

- ``7scenes`` (Microsoft 7-Scenes, as in ../shared/data/scans/7scenes-redkitchen):
  ``frames/frame-XXXXXX.color.png`` (8-bit RGB), ``frames/frame-XXXXXX.depth.png`` (uint16 mm,
  0 = invalid), ``frames/frame-XXXXXX.pose.txt`` (4x4 camera-to-world, metres),
  ``camera-intrinsics.txt`` (3x3 K), ``gravity-direction.txt`` (unit gravity vector, world frame,
  pointing down). No mesh: the world frame is the first camera's frame, as in KinectFusion output.
- ``3rscan``: ``sequence/frame-XXXXXX.color.jpg``, ``sequence/frame-XXXXXX.depth.pgm`` (16-bit binary
  PGM, mm), ``sequence/frame-XXXXXX.pose.txt``, ``sequence/_info.txt`` (``key = value`` lines, 4x4
  row-major intrinsics), ``mesh.refined.v2.obj`` + ``mesh.refined.mtl`` + ``mesh.refined_0.png``.
  Colour 960x540-like and depth 224x172-like with their own (anisotropic) intrinsics.
- ``scannet`` (SensReader ``reader.py`` export): ``color/N.jpg``, ``depth/N.png`` (uint16, depth shift
  1000), ``pose/N.txt`` (4x4 written with ``%f``; a tracking failure is written as all ``-inf``),
  ``intrinsic/intrinsic_color.txt``, ``intrinsic/intrinsic_depth.txt`` (4x4),
  ``intrinsic/extrinsic_color.txt``, ``intrinsic/extrinsic_depth.txt`` (identity),
  ``<scene>_vh_clean_2.ply`` (binary PLY with RGBA vertex colours). Colour larger than depth.
- ``transforms`` (nerfstudio ``transforms.json``): ``fl_x, fl_y, cx, cy, w, h``, ``camera_model``,
  ``frames[].file_path/depth_file_path/transform_matrix`` (camera-to-world with OpenGL camera axes:
  x right, y up, z backward), ``ply_file_path`` naming the room mesh (``mesh.ply``). Depth PNGs are
  uint16 mm (nerfstudio's default ``depth_unit_scale_factor`` 1e-3). ``cx, cy`` follow nerfstudio's
  pixel convention (pixel ``i`` is centred at ``i + 0.5``), so they are the OpenCV values + 0.5.
- ``bop`` (a BOP dataset's scene folder, as bop_toolkit writes it): ``rgb/NNNNNN.png``, ``depth/NNNNNN.png``
  (uint16, ``depth_scale`` 1.0: millimetres), ``scene_camera.json`` (per image: ``cam_K``, ``depth_scale``,
  ``cam_R_w2c``, ``cam_t_w2c`` in mm). No mesh.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.camera import CV_TO_GL
from pipeline.io import atomic_write_bytes, atomic_write_json, encode_image

LAYOUTS = ("7scenes", "3rscan", "scannet", "transforms", "bop")


@dataclass(frozen=True)
class FrameFiles:
    """Paths of one frame's files, relative to the scan folder."""

    color: str
    depth: str
    pose: str                 # "" when the layout keeps poses in one file (transforms.json)


def frame_files(layout: str, i: int) -> FrameFiles:
    """Relative file names of frame ``i`` (0-based) in ``layout``."""
    if layout == "7scenes":
        s = f"frames/frame-{i:06d}"
        return FrameFiles(f"{s}.color.png", f"{s}.depth.png", f"{s}.pose.txt")
    if layout == "3rscan":
        s = f"sequence/frame-{i:06d}"
        return FrameFiles(f"{s}.color.jpg", f"{s}.depth.pgm", f"{s}.pose.txt")
    if layout == "scannet":
        return FrameFiles(f"color/{i}.jpg", f"depth/{i}.png", f"pose/{i}.txt")
    if layout == "transforms":
        return FrameFiles(f"images/frame_{i + 1:05d}.png", f"depth/frame_{i + 1:05d}.png", "")
    if layout == "bop":
        return FrameFiles(f"rgb/{i:06d}.png", f"depth/{i:06d}.png", "")
    raise ValueError(f"unknown layout {layout!r}")


def frame_id(layout: str, i: int) -> int:
    """The number of frame ``i`` as a reader sees it: the file number, or the position in
    transforms.json's ``frames`` list (whose file names count from 1, as nerfstudio writes them)."""
    return i


def matrix_text(M: np.ndarray, fmt: str) -> bytes:
    """Rows of ``M`` as text lines, numbers separated by single spaces."""
    return "".join(" ".join(fmt % v for v in row) + "\n" for row in np.asarray(M, np.float64)).encode()


def pose_text(layout: str, T_c2w: np.ndarray, valid: bool = True) -> bytes:
    """A pose file's bytes. ScanNet's exporter writes ``%f`` (6 decimals) and ``-inf`` rows for lost tracking."""
    if layout == "scannet":
        M = T_c2w if valid else np.full((4, 4), -np.inf)
        return matrix_text(M, "%f")
    if layout == "7scenes":
        return matrix_text(T_c2w, "%.18e")
    return matrix_text(T_c2w, "%.17g")


def write_frame(out: Path, layout: str, i: int, color: np.ndarray, depth_mm: np.ndarray, T_c2w: np.ndarray,
                pose_valid: bool) -> list[str]:
    """Write frame ``i``'s colour, depth and pose files; returns their relative paths."""
    ff = frame_files(layout, i)
    atomic_write_image_bytes(out / ff.color, color, jpeg_quality=92)
    if layout == "3rscan":
        atomic_write_bytes(out / ff.depth, pgm16(depth_mm))
    else:
        atomic_write_image_bytes(out / ff.depth, depth_mm)
    written = [ff.color, ff.depth]
    if ff.pose:
        atomic_write_bytes(out / ff.pose, pose_text(layout, T_c2w, pose_valid))
        written.append(ff.pose)
    return written


def encode(path: str | Path, image: np.ndarray, jpeg_quality: int = 95) -> bytes:
    """Image bytes for ``path``'s extension; PNGs at zlib level 1 (several times faster than
    :func:`pipeline.io.encode_image`'s level 3 on noisy photos, files ~10% larger), else
    :func:`pipeline.io.encode_image`. No metadata: equal pixels, equal bytes."""
    if Path(path).suffix.lower() != ".png":
        return encode_image(path, image, jpeg_quality=jpeg_quality)
    import cv2

    img = image[..., ::-1] if image.ndim == 3 else image
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError(f"could not encode {image.dtype} image of shape {image.shape} as PNG")
    return buf.tobytes()


def atomic_write_image_bytes(path: Path, image: np.ndarray, jpeg_quality: int = 95) -> None:
    atomic_write_bytes(path, encode(path, image, jpeg_quality=jpeg_quality))


def pgm16(depth: np.ndarray) -> bytes:
    """16-bit binary PGM (P5, maxval 65535, big-endian samples), as 3RScan stores depth."""
    h, w = depth.shape
    return f"P5\n{w} {h}\n65535\n".encode() + depth.astype(">u2").tobytes()


# ---------------------------------------------------------------------------------------------------
# Meshes
# ---------------------------------------------------------------------------------------------------

def ply_bytes(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None, *,
              alpha: bool = False, vertex_ints: dict[str, np.ndarray] | None = None,
              comments: tuple[str, ...] = ()) -> bytes:
    """Binary little-endian PLY: float x, y, z; optional uchar red, green, blue (, alpha); optional int
    vertex properties; faces as ``list uchar int vertex_indices``."""
    n = len(vertices)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")] + ([("alpha", "u1")] if alpha else [])
    for name in (vertex_ints or {}):
        fields.append((name, "<i4"))
    v = np.empty(n, dtype=fields)
    v["x"], v["y"], v["z"] = vertices[:, 0], vertices[:, 1], vertices[:, 2]
    if colors is not None:
        v["red"], v["green"], v["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
        if alpha:
            v["alpha"] = 255
    for name, arr in (vertex_ints or {}).items():
        v[name] = arr
    f = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    f["n"] = 3
    f["i"] = faces
    types = {"<f4": "float", "u1": "uchar", "<i4": "int"}
    header = ["ply", "format binary_little_endian 1.0", *[f"comment {c}" for c in comments],
              f"element vertex {n}"]
    header += [f"property {types[t]} {name}" for name, t in fields]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    return ("\n".join(header) + "\n").encode("ascii") + v.tobytes() + f.tobytes()


def textured_obj(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, stem: str,
                 obj_name: str, cell: int = 2) -> tuple[bytes, bytes, np.ndarray]:
    """OBJ + MTL + texture atlas for a vertex-coloured mesh (each face gets its own flat-colour cell).

    Returns
    -------
    obj bytes, mtl bytes, (S, S, 3) uint8 texture; the MTL names ``{stem}_0.png`` and the OBJ
    ``{stem}.mtl``.
    """
    T = len(faces)
    per_row = max(1, int(np.ceil(np.sqrt(T))))
    size = per_row * cell
    face_col = colors[faces].astype(np.float32).mean(axis=1).round().astype(np.uint8)   # (T, 3)
    atlas = np.zeros((per_row * per_row, 3), np.uint8)
    atlas[:T] = face_col
    atlas = atlas.reshape(per_row, per_row, 3).repeat(cell, 0).repeat(cell, 1)
    k = np.arange(T)
    r, c = k // per_row, k % per_row
    u = (c * cell + cell / 2) / size
    v = 1.0 - (r * cell + cell / 2) / size        # OBJ/OpenGL: v up, row 0 is the top of the image
    lines = [f"mtllib {stem}.mtl\n", f"o {obj_name}\n"]
    lines.append(("v %.6f %.6f %.6f\n" * len(vertices)) % tuple(np.asarray(vertices, np.float64).ravel()))
    lines.append(("vt %.6f %.6f\n" * T) % tuple(np.stack([u, v], 1).ravel()))
    lines.append(f"usemtl {stem}_material\n")
    fi = faces.astype(np.int64) + 1
    ti = k + 1
    lines.append(("f %d/%d %d/%d %d/%d\n" * T) % tuple(
        np.stack([fi[:, 0], ti, fi[:, 1], ti, fi[:, 2], ti], 1).ravel()))
    obj = "".join(lines).encode()
    mtl = (f"newmtl {stem}_material\nKa 1.000000 1.000000 1.000000\nKd 1.000000 1.000000 1.000000\n"
           f"Ks 0.000000 0.000000 0.000000\nd 1.0\nillum 1\nmap_Kd {stem}_0.png\n").encode()
    return obj, mtl, atlas


# ---------------------------------------------------------------------------------------------------
# Per-layout static files (intrinsics, info, mesh)
# ---------------------------------------------------------------------------------------------------

def _k4(K: np.ndarray) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = K
    return M


def _flat(M: np.ndarray) -> str:
    return " ".join(repr(float(x)) if x != int(x) else str(int(x)) for x in np.asarray(M).ravel())


def write_static(out: Path, layout: str, *, scene: str, K: np.ndarray, width: int, height: int,
                 depth_K: np.ndarray, depth_width: int, depth_height: int, up_w: np.ndarray,
                 poses: np.ndarray, pose_valid: np.ndarray, mesh_vertices: np.ndarray,
                 mesh_faces: np.ndarray, mesh_colors: np.ndarray) -> list[str]:
    """Write the layout's files that are not per frame; returns their relative paths.

    ``mesh_*`` is the scanner's mesh in the layout's world frame (metres).
    """
    written: list[str] = []

    def put(rel: str, data: bytes) -> None:
        atomic_write_bytes(out / rel, data)
        written.append(rel)

    if layout == "7scenes":
        put("camera-intrinsics.txt", matrix_text(K, "%.18e"))
        put("gravity-direction.txt", matrix_text((-up_w).reshape(3, 1), "%.18e"))
    elif layout == "3rscan":
        info = [
            "m_versionNumber = 4",
            "m_sensorName = StructureSensor (synthetic)",
            f"m_colorWidth = {width}",
            f"m_colorHeight = {height}",
            f"m_depthWidth = {depth_width}",
            f"m_depthHeight = {depth_height}",
            "m_depthShift = 1000",
            f"m_calibrationColorIntrinsic = {_flat(_k4(K))}",
            f"m_calibrationColorExtrinsic = {_flat(np.eye(4))}",
            f"m_calibrationDepthIntrinsic = {_flat(_k4(depth_K))}",
            f"m_calibrationDepthExtrinsic = {_flat(np.eye(4))}",
            f"m_frames.size = {len(poses)}",
        ]
        put("sequence/_info.txt", ("\n".join(info) + "\n").encode())
        obj, mtl, atlas = textured_obj(mesh_vertices, mesh_faces, mesh_colors, "mesh.refined", scene)
        put("mesh.refined.v2.obj", obj)
        put("mesh.refined.mtl", mtl)
        put("mesh.refined_0.png", encode("mesh.refined_0.png", atlas))
    elif layout == "scannet":
        put("intrinsic/intrinsic_color.txt", matrix_text(_k4(K), "%f"))
        put("intrinsic/intrinsic_depth.txt", matrix_text(_k4(depth_K), "%f"))
        put("intrinsic/extrinsic_color.txt", matrix_text(np.eye(4), "%f"))
        put("intrinsic/extrinsic_depth.txt", matrix_text(np.eye(4), "%f"))
        put(f"{scene}_vh_clean_2.ply", ply_bytes(mesh_vertices, mesh_faces, mesh_colors, alpha=True))
    elif layout == "transforms":
        doc = {
            "camera_model": "OPENCV",
            "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
            "cx": float(K[0, 2]) + 0.5, "cy": float(K[1, 2]) + 0.5,     # nerfstudio pixel centres at i + 0.5
            "w": int(width), "h": int(height),
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
            "ply_file_path": "mesh.ply",
            "frames": [
                {"file_path": frame_files(layout, i).color,
                 "depth_file_path": frame_files(layout, i).depth,
                 "transform_matrix": (poses[i] @ CV_TO_GL).tolist()}
                for i in range(len(poses)) if pose_valid[i]
            ],
        }
        atomic_write_json(out / "transforms.json", doc)
        written.append("transforms.json")
        put("mesh.ply", ply_bytes(mesh_vertices, mesh_faces, mesh_colors))
    elif layout == "bop":
        cams = {}
        for i in range(len(poses)):
            T_w2c = np.linalg.inv(poses[i])
            cams[str(i)] = {"cam_K": np.asarray(K, float).ravel().tolist(), "depth_scale": 1.0}
            if pose_valid[i]:
                cams[str(i)].update(cam_R_w2c=T_w2c[:3, :3].ravel().tolist(),
                                    cam_t_w2c=(1000.0 * T_w2c[:3, 3]).tolist())
        atomic_write_json(out / "scene_camera.json", cams)
        written.append("scene_camera.json")
    else:
        raise ValueError(f"unknown layout {layout!r}")
    return written
