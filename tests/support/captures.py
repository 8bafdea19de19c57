"""Partial captures made from real data (issue 20): a one-view scan from one redkitchen frame (its photo, depth
and pose in the 7-Scenes layout) with a mesh made from that frame's depth alone, and a table cropped out of it.
Neither surrounds its camera; the benchmark (bench/partial.py) and the tests drop objects onto both."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np

from pipeline.scanformats.detect import read_scan
from pipeline.scanformats.mesh import ply_bytes


def one_view_scan(shared_data: Path, out: Path, frame: int = 0, stride: int = 8,
                  max_depth: float = 4.0) -> tuple[Path, Path, np.ndarray, np.ndarray]:
    """Write the scan folder ``out/one-view`` and ``out/mesh.ply``; return both paths and the mesh
    (vertices (V, 3) metres world frame, faces (T, 3)). Depth steps over 5 cm are not bridged."""
    src = shared_data / "scans" / "7scenes-redkitchen"
    scan = out / "one-view"
    (scan / "frames").mkdir(parents=True)
    for f in ("camera-intrinsics.txt", "gravity-direction.txt"):
        if (src / f).is_file():
            shutil.copy(src / f, scan / f)
    for ext in ("color.jpg", "depth.png", "pose.txt"):
        shutil.copy(src / "frames" / f"frame-{frame:06d}.{ext}", scan / "frames" / f"frame-{frame:06d}.{ext}")
    cam = read_scan(scan).camera(0)
    raw = cv2.imread(str(scan / "frames" / f"frame-{frame:06d}.depth.png"), cv2.IMREAD_UNCHANGED)
    d = raw[::stride, ::stride] / 1000.0
    d[(d <= 0) | (d > max_depth)] = np.nan
    v, u = np.mgrid[0:d.shape[0], 0:d.shape[1]] * stride
    P = cam.c2w(cam.unproject(u.ravel(), v.ravel(), d.ravel()))
    idx = np.arange(d.size).reshape(d.shape)
    quads = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    z = d.ravel()[quads]
    ok = np.isfinite(z).all(axis=1)
    ok[ok] = (z[ok].max(axis=1) - z[ok].min(axis=1)) < 0.05
    F = np.concatenate([quads[ok][:, [0, 1, 2]], quads[ok][:, [0, 2, 3]]])
    P = np.nan_to_num(P)
    (out / "mesh.ply").write_bytes(ply_bytes(P, F, None))
    return scan, out / "mesh.ply", P, F


def cropped_table_scan(shared_data: Path, out: Path, frame: int = 0, band: tuple[float, float] = (0.55, 1.0)
                       ) -> tuple[Path, Path, np.ndarray, np.ndarray]:
    """:func:`one_view_scan` with its mesh cropped to the faces whose vertices all lie ``band`` metres above
    the frame's floor (the lowest 2 % of heights along the scan's up): a table and counter without the
    floor, as a tabletop capture has them. Returns the scan folder, ``out/table.ply`` and that mesh."""
    scan, _, P, F = one_view_scan(shared_data, out, frame)
    up = -np.loadtxt(scan / "gravity-direction.txt").ravel()
    up /= np.linalg.norm(up)
    h = P @ up
    used = np.unique(F)
    h0 = np.percentile(h[used], 2)
    keep = np.all((h[F] > h0 + band[0]) & (h[F] < h0 + band[1]), axis=1)
    (out / "table.ply").write_bytes(ply_bytes(P, F[keep], None))
    return scan, out / "table.ply", P, F[keep]
