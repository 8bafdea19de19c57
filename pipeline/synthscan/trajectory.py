"""Handheld-like camera trajectory and camera intrinsics.

The camera walks most of a loop around the room at chest height, looking across the room and slightly
down, with smooth hand jitter in position and orientation. Poses are camera-to-world, OpenCV axes.
Blurred frames get a short exposure path (sub-frame poses around the frame's pose) whose image-space
extent is recorded as the blur strength.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.geometry import look_at
from pipeline.synthscan.room import Room


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (3,) in rad -> (3, 3) rotation matrix."""
    theta = float(np.linalg.norm(r))
    if theta < 1e-15:
        return np.eye(3)
    k = r / theta
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * Kx + (1 - math.cos(theta)) * Kx @ Kx


def _smooth_jitter(rng: np.random.Generator, t: np.ndarray, amplitude: float, dims: int = 3) -> np.ndarray:
    """Sum of three sinusoids per dimension with random frequencies/phases; (len(t), dims)."""
    out = np.zeros((len(t), dims))
    for _ in range(3):
        f = rng.uniform(0.5, 3.0, dims)
        ph = rng.uniform(0, 2 * np.pi, dims)
        out += np.sin(2 * np.pi * f[None, :] * t[:, None] + ph[None, :]) / 3.0
    return amplitude * out


def walk(room: Room, rng: np.random.Generator, frames: int) -> np.ndarray:
    """Camera-to-world poses (frames, 4, 4) float64 of a handheld walk inside ``room`` (canonical frame)."""
    x0, x1, y0, y1 = room.walkable
    c = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    rx, ry = (x1 - x0) / 2 * 0.8, (y1 - y0) / 2 * 0.8
    t = np.linspace(0.0, 1.0, frames, endpoint=False) if frames > 1 else np.zeros(1)
    phi0 = rng.uniform(0, 2 * np.pi)
    sweep = 2 * np.pi * rng.uniform(0.75, 0.9)
    phi = phi0 + sweep * t
    height = rng.uniform(1.35, 1.6)
    pos_j = _smooth_jitter(rng, t, 0.04)
    ang_j = _smooth_jitter(rng, t, math.radians(3.0))
    look_off = rng.uniform(-0.5, 0.5)
    poses = np.empty((frames, 4, 4))
    for i in range(frames):
        eye = np.array([c[0] + rx * math.cos(phi[i]), c[1] + ry * math.sin(phi[i]), height]) + pos_j[i]
        a = phi[i] + math.pi + look_off * math.sin(2 * math.pi * t[i])
        target = np.array([c[0] + 1.2 * rx * math.cos(a), c[1] + 1.2 * ry * math.sin(a), 0.6])
        T = look_at(eye, target, roll=ang_j[i, 2])
        T[:3, :3] = T[:3, :3] @ rotvec_to_matrix(np.array([ang_j[i, 0], ang_j[i, 1], 0.0]))
        poses[i] = T
    return poses


def intrinsics(width: int, height: int, f_over_w: float, rng: np.random.Generator, offset_px: float = 2.0) -> np.ndarray:
    """Pinhole K (3, 3) float64 with fx = fy = ``f_over_w * width`` and a small principal-point offset.

    Values are rounded to 1e-3 px so that every layout's text format stores them exactly.
    """
    f = round(f_over_w * width, 3)
    cx = round((width - 1) / 2 + rng.uniform(-offset_px, offset_px), 3)
    cy = round((height - 1) / 2 + rng.uniform(-offset_px, offset_px), 3)
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def exposure_path(T_c2w: np.ndarray, omega: np.ndarray, velocity: np.ndarray, n: int) -> np.ndarray:
    """Sub-frame poses (n, 4, 4) over one exposure centred on ``T_c2w``.

    The camera turns by ``omega`` (rotation vector, rad, camera axes) and moves by ``velocity``
    (metres, world frame) over the whole exposure, at constant rates.
    """
    out = np.empty((n, 4, 4))
    for k, s in enumerate(np.linspace(-0.5, 0.5, n)):
        T = T_c2w.copy()
        T[:3, :3] = T_c2w[:3, :3] @ rotvec_to_matrix(s * omega)
        T[:3, 3] = T_c2w[:3, 3] + s * velocity
        out[k] = T
    return out
