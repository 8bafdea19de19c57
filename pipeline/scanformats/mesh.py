"""Room meshes: loading a scan's own mesh, checks, and the pipeline's room PLY (write and read).

The room mesh the pipeline passes on is a binary little-endian PLY in metres, world frame, with
float32 vertex positions, uint8 RGB vertex colours and int32 triangle indices; written byte-for-byte
deterministically by :func:`ply_bytes`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import InputError
from pipeline.camera import Camera
from pipeline.tolerances import MESH_SEEN_DEPTH_M, MESH_SEEN_MIN_SHARE


def ply_bytes(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None) -> bytes:
    """Binary PLY of a triangle mesh.

    Parameters
    ----------
    vertices : (V, 3) float, metres (stored as float32).
    faces : (T, 3) int, vertex indices.
    colors : (V, 3) uint8 RGB, or None.
    """
    V = np.asarray(vertices, dtype="<f4").reshape(-1, 3)
    F = np.asarray(faces, dtype="<i4").reshape(-1, 3)
    head = ["ply", "format binary_little_endian 1.0", "comment scansynth room mesh, metres, world frame",
            f"element vertex {len(V)}", "property float x", "property float y", "property float z"]
    vdt = [("p", "<f4", 3)]
    if colors is not None:
        head += ["property uchar red", "property uchar green", "property uchar blue"]
        vdt.append(("c", "u1", 3))
    head += [f"element face {len(F)}", "property list uchar int vertex_indices", "end_header"]
    vrec = np.empty(len(V), dtype=vdt)
    vrec["p"] = V
    if colors is not None:
        vrec["c"] = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
    frec = np.empty(len(F), dtype=[("n", "u1"), ("i", "<i4", 3)])
    frec["n"] = 3
    frec["i"] = F
    return ("\n".join(head) + "\n").encode("ascii") + vrec.tobytes() + frec.tobytes()


def read_room_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a PLY written by :func:`ply_bytes` (other PLYs go through trimesh).

    Returns
    -------
    vertices (V, 3) float64 metres, faces (T, 3) int32, vertex colours (V, 3) uint8 or None.
    """
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    header = data[:end].decode("ascii", errors="replace").splitlines() if end > 0 else []
    if "comment scansynth room mesh, metres, world frame" not in header:
        return load_mesh_file(path)
    nv = int(next(h for h in header if h.startswith("element vertex")).split()[-1])
    nf = int(next(h for h in header if h.startswith("element face")).split()[-1])
    has_c = "property uchar red" in header
    vdt = [("p", "<f4", 3)] + ([("c", "u1", 3)] if has_c else [])
    off = end + len(b"end_header\n")
    vrec = np.frombuffer(data, dtype=vdt, count=nv, offset=off)
    off += vrec.nbytes
    frec = np.frombuffer(data, dtype=[("n", "u1"), ("i", "<i4", 3)], count=nf, offset=off)
    return (vrec["p"].astype(np.float64), frec["i"].astype(np.int32),
            vrec["c"].copy() if has_c else None)


def load_mesh_file(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Load a scan's mesh file (PLY with vertex colours, OBJ with texture, ...) as a triangle mesh.

    Texture colours are sampled at the vertices (scan meshes are dense enough for vertex colours).

    Returns
    -------
    vertices (V, 3) float64 (file units), faces (T, 3) int32, vertex colours (V, 3) uint8 or None.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: mesh file is missing; fix the path (scan.mesh) or remove it to reconstruct")
    try:
        m = trimesh.load(str(path), process=False, force="mesh")
    except Exception as e:  # noqa: BLE001 - trimesh raises many types for bad files
        raise InputError(f"{path}: mesh cannot be read ({type(e).__name__}: {e}); re-export it as PLY or OBJ") from None
    faces = np.asarray(getattr(m, "faces", np.zeros((0, 3))), dtype=np.int64)
    verts = np.asarray(getattr(m, "vertices", np.zeros((0, 3))), dtype=np.float64)
    if len(verts) == 0 or faces.ndim != 2 or faces.shape[0] == 0 or faces.shape[1] != 3:
        raise InputError(f"{path}: mesh has {len(verts)} vertices and no triangle faces (a point cloud or an "
                         f"empty file?); give a triangle mesh, or remove it to reconstruct from depth")
    if not np.all(np.isfinite(verts)):
        raise InputError(f"{path}: mesh has non-finite vertex coordinates; repair or re-export it")
    colors = None
    vis = getattr(m, "visual", None)
    if vis is not None and vis.kind == "texture":
        try:
            colors = np.asarray(vis.to_color().vertex_colors)[:, :3].astype(np.uint8)
        except Exception:  # noqa: BLE001 - a texture that cannot be sampled leaves the mesh uncoloured
            colors = None
    elif vis is not None and vis.kind == "vertex":
        colors = np.asarray(vis.vertex_colors)[:, :3].astype(np.uint8)
    elif vis is not None and vis.kind == "face":
        fc = np.asarray(vis.face_colors)[:, :3].astype(np.float64)
        acc = np.zeros((len(verts), 3))
        cnt = np.zeros(len(verts))
        for k in range(3):
            np.add.at(acc, faces[:, k], fc)
            np.add.at(cnt, faces[:, k], 1)
        colors = np.round(acc / np.maximum(cnt, 1)[:, None]).astype(np.uint8)
    return verts, faces.astype(np.int32), colors


def check_mesh_seen_by_cameras(vertices: np.ndarray, cameras: list[Camera], path: str | Path) -> None:
    """InputError when no camera sees the mesh: fewer than :data:`MESH_SEEN_MIN_SHARE` of (a sample of) its
    vertices project into some camera's image at a plausible distance (:data:`MESH_SEEN_DEPTH_M`).

    A mesh need not surround its cameras (a table captured from one side, a single frame's depth), but it
    must be in front of them: one that is not is in other units or another frame than the poses.
    """
    V = np.asarray(vertices, np.float64)
    V = V[:: max(1, len(V) // 20000)]
    near, far = MESH_SEEN_DEPTH_M
    best = 0.0
    for cam in cameras[:: max(1, len(cameras) // 50)]:
        uv, z = cam.project(V)
        seen = (z > near) & (z < far) & (uv[:, 0] > -0.5) & (uv[:, 0] < cam.width - 0.5) & \
            (uv[:, 1] > -0.5) & (uv[:, 1] < cam.height - 0.5)
        best = max(best, float(seen.mean()) if len(V) else 0.0)
        if best >= MESH_SEEN_MIN_SHARE:
            return
    ext = float(np.max(V.max(0) - V.min(0))) if len(V) else 0.0
    hint = " It spans {:.0f} units: millimetres? ".format(ext) if ext > 100 else ""
    raise InputError(f"{path}: no camera sees the mesh (at most {best:.1%} of its vertices project into an image "
                     f"{near}-{far:g} m in front of one of the {len(cameras)} cameras; its bounding box is "
                     f"{np.round(V.min(0), 3).tolist()} .. {np.round(V.max(0), 3).tolist()}, e.g. camera at "
                     f"{np.round(cameras[0].center, 3).tolist()}), so it is in other units or another frame than "
                     f"the poses.{hint} Convert the mesh to metres in the scan's world frame, or remove it to "
                     f"reconstruct from depth")


def canonical_order(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Reorder vertices and faces into a canonical order (same mesh, same bytes, whatever the thread order).

    Unreferenced vertices are dropped; each face is rotated so its smallest index comes first (winding
    kept).
    """
    used = np.unique(faces)
    v = vertices[used]
    order = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
    remap = np.empty(len(vertices), dtype=np.int64)
    remap[used[order]] = np.arange(len(used))
    f = remap[faces]
    k = np.argmin(f, axis=1)
    rows = np.arange(len(f))
    f = np.stack([f[rows, k], f[rows, (k + 1) % 3], f[rows, (k + 2) % 3]], axis=1)
    forder = np.lexsort((f[:, 2], f[:, 1], f[:, 0]))
    c = colors[used][order] if colors is not None else None
    return v[order], f[forder].astype(np.int32), c
