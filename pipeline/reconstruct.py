"""Room geometry from depth: Open3D TSDF fusion, and the up direction from the floor.

Open3D 0.19.0's ``ScalableTSDFVolume`` is used (checked on the real 7-Scenes frames; with 0.20.0 it
returned an empty mesh on the same data, see ../shared/data/README.md). The extracted mesh is put in a
canonical vertex/face order so the same inputs give the same bytes whatever Open3D's thread order.
"""

from __future__ import annotations

import logging

import numpy as np

from meshprep.metrics import open3d_module
from pipeline.errors import InputError
from pipeline.scanformats.common import read_color, read_depth
from pipeline.scanformats.mesh import canonical_order
from pipeline.types import Scan

log = logging.getLogger(__name__)


def fuse_tsdf(scan: Scan, *, voxel: float, trunc: float, depth_max: float,
              min_component_faces: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse every frame's depth (registered to colour) into a TSDF and extract a coloured mesh.

    Parameters
    ----------
    scan : the scan (``mesh_path`` is ignored).
    voxel : TSDF voxel size, metres.
    trunc : truncation distance, metres (several voxels).
    depth_max : depth beyond this is ignored, metres.
    min_component_faces : connected pieces with fewer triangles are dropped (0 = keep all).

    Returns
    -------
    vertices (V, 3) float64 metres world frame, faces (T, 3) int32, vertex colours (V, 3) uint8 sRGB.
    """
    o3d = open3d_module()
    vol = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=float(voxel), sdf_trunc=float(trunc),
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
    w, h = scan.width, scan.height
    for i in range(scan.num_frames):
        color = read_color(scan, i)
        depth = read_depth(scan, i)
        K = scan.K[i]
        intr = o3d.camera.PinholeCameraIntrinsic(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(color), o3d.geometry.Image(depth), depth_scale=1.0,
            depth_trunc=float(depth_max), convert_rgb_to_intensity=False)
        vol.integrate(rgbd, intr, np.linalg.inv(scan.T_c2w[i]))
    mesh = vol.extract_triangle_mesh()
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.triangles, dtype=np.int64)
    C = np.asarray(mesh.vertex_colors, dtype=np.float64)
    if len(F) == 0:
        raise InputError(f"{scan.root}: TSDF fusion of {scan.num_frames} frame(s) gave an empty mesh; check "
                         f"that the depth maps hold depth within ingest.depth_max = {depth_max} m and that "
                         f"poses are camera-to-world in metres")
    C8 = np.clip(np.round(C * 255.0), 0, 255).astype(np.uint8)
    if min_component_faces > 0:
        F = drop_small_components(F, len(V), min_component_faces)
    V, F, C8 = canonical_order(V, F, C8)
    log.info("%s: TSDF %.3f m -> %d vertices, %d triangles", scan.name, voxel, len(V), len(F))
    return V, F, C8


def drop_small_components(faces: np.ndarray, n_vertices: int, min_faces: int) -> np.ndarray:
    """Faces of the connected pieces (sharing vertices) that have at least ``min_faces`` triangles."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, dtype=np.int64)
    rows = np.concatenate([f[:, 0], f[:, 1]])
    cols = np.concatenate([f[:, 1], f[:, 2]])
    g = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_vertices, n_vertices))
    _, lab = connected_components(g, directed=False)
    flab = lab[f[:, 0]]
    count = np.bincount(flab)
    return f[count[flab] >= min_faces]


ONE_VIEW_TILT_DEG = 80.0      # a one-photo scan: level surfaces face its camera within this of its image-up


def camera_up_vote(T_c2w: np.ndarray) -> np.ndarray:
    """Mean image-up direction (-y of the OpenCV camera) in the world, unit (3,), or zeros if it cancels."""
    v = -T_c2w[:, :3, 1].mean(axis=0)
    n = np.linalg.norm(v)
    return v / n if n > 0.3 else np.zeros(3)


def floor_up(vertices: np.ndarray, faces: np.ndarray, T_c2w: np.ndarray,
             max_tilt_deg: float = 30.0, bin_m: float = 0.03) -> tuple[np.ndarray, dict]:
    """Up direction from the dominant floor plane of a room mesh, helped by a camera "up" vote.

    Horizontal-ish triangles (normal within ``max_tilt_deg`` of the cameras' mean image-up) give the
    dominant level-surface normal; along it, the lowest height band holding a large share of that area
    is the floor; a plane fitted to the floor triangles (area-weighted) gives the final up, signed so that
    the cameras are above the floor.

    Returns
    -------
    up (3,) float64 unit vector in the world frame, and a dict of diagnostics (floor height along up,
    floor area m^2, method).
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    cams = T_c2w[:, :3, 3]
    vote = camera_up_vote(T_c2w)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    cr = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cr, axis=1)
    ok = area2 > 0
    n = np.zeros_like(cr)
    n[ok] = cr[ok] / area2[ok, None]
    area = 0.5 * area2
    cen = (a + b + c) / 3.0
    if not np.any(vote):
        # Cameras rolled every way: the dominant direction of all normals (floors, walls, ceilings) is
        # ambiguous; take the principal axis of the normals and sign it below.
        M = (n * area[:, None]).T @ n
        vote = np.linalg.eigh(M)[1][:, -1]
    cos_t = np.cos(np.radians(max_tilt_deg))
    if len(cams) == 1:
        # one photo (a tabletop capture): its camera may look down at the table far more steeply than
        # max_tilt_deg, and a wall facing it is then nearer its image-up than the table. A floor or table it
        # sees faces it and has an upward normal in its image (within ONE_VIEW_TILT_DEG of image-up); a wall
        # facing it has a downward one, a ceiling faces away
        n = n * np.where(((cams[0] - cen) * n).sum(axis=1) >= 0, 1.0, -1.0)[:, None]
        horiz = n @ vote >= np.cos(np.radians(ONE_VIEW_TILT_DEG))
    else:
        horiz = np.abs(n @ vote) >= cos_t
    if area[horiz].sum() <= 0:
        up = vote if (cams @ vote).mean() >= (cen @ vote).mean() else -vote
        return up, {"method": "camera vote (no level surfaces in the mesh)"}
    nh = n[horiz] * np.sign(n[horiz] @ vote)[:, None]
    M = (nh * area[horiz, None]).T @ nh
    u1 = np.linalg.eigh(M)[1][:, -1]
    u1 = u1 if u1 @ vote >= 0 else -u1
    hgt = cen[horiz] @ u1
    ah = area[horiz]
    lo, hi = hgt.min(), hgt.max()
    nb = max(1, int(np.ceil((hi - lo) / bin_m)) + 1)
    hist = np.bincount(np.clip(((hgt - lo) / bin_m).astype(int), 0, nb - 1), weights=ah, minlength=nb)
    pad = np.pad(hist, 1)
    smooth = pad[:-2] + pad[1:-1] + pad[2:]
    cam_h = float(np.median(cams @ u1))
    below = np.arange(nb) * bin_m + lo < cam_h  # the floor is below the cameras
    if below.any():
        cand = np.nonzero((smooth >= 0.3 * smooth[below].max()) & below)[0]
        fb = int(cand[0])  # the lowest level band holding a large share of the level area
    else:
        fb = int(np.argmax(smooth))
    fh = lo + (fb + 0.5) * bin_m
    sel = np.abs(hgt - fh) <= 1.5 * bin_m
    P, wts = cen[horiz][sel], ah[sel]
    mu = (P * wts[:, None]).sum(0) / wts.sum()
    C = ((P - mu) * wts[:, None]).T @ (P - mu)
    up = np.linalg.eigh(C)[1][:, 0]
    if abs(up @ u1) < cos_t:  # a degenerate (too narrow) floor patch: keep the level-surface normal
        up = u1
    up = up if (cams - mu) @ up @ np.ones(len(cams)) >= 0 else -up
    up = up / np.linalg.norm(up)
    return up, {"method": "floor plane", "floor_height_m": float(mu @ up), "floor_area_m2": float(wts.sum()),
                "camera_height_above_floor_m": float(np.median((cams - mu) @ up))}
