"""Sensor degradation: photo noise and 8-bit encoding, defocus and motion blur, depth-sensor errors.

All functions are pure: arrays and a seeded generator in, arrays out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.camera import image_plane
from pipeline.color import linear_to_srgb

# Kinect-like depth sensor (Nguyen, Izadi, Lovell 2012: axial noise of the Kinect v1).
DEPTH_NOISE_A = 0.0012        # metres, sigma at 0.4 m
DEPTH_NOISE_B = 0.0019        # metres / m^2, growth with (z - 0.4)^2
DEPTH_MIN = 0.4               # metres, nearer is invalid
DEPTH_FAR_START = 3.5         # metres, beyond this pixels start to drop out
DEPTH_FAR_END = 4.5           # metres, all invalid beyond
GRAZING_START_DEG = 70.0      # incidence angle where dropout starts
GRAZING_END_DEG = 82.0        # incidence angle beyond which every pixel is invalid
EDGE_JUMP = 0.05              # metres: a depth step larger than this is an occlusion edge
EDGE_DROPOUT = 0.5            # probability that a pixel on an occlusion edge is invalid
SPECKLE_DROPOUT = 0.003       # probability of a random invalid pixel

SRGB_LUT_4096 = np.round(linear_to_srgb(np.linspace(0.0, 1.0, 4096)) * 255.0).astype(np.uint8)
SRGB_LUT_4096.flags.writeable = False


def encode_photo(linear: np.ndarray, rng: np.random.Generator, *, read_noise: float = 0.004,
                 shot_noise: float = 0.012) -> np.ndarray:
    """Linear exposure units -> 8-bit sRGB photo with mild sensor noise (clipped at white).

    Parameters
    ----------
    linear : (H, W, 3) float32, 1.0 = sensor white
    rng : seeded generator
    read_noise : sigma of additive noise, linear units
    shot_noise : sigma of signal-dependent noise at 1.0 (scales with sqrt(signal))

    Returns
    -------
    (H, W, 3) uint8
    """
    x = np.clip(linear, 0.0, 1.0).astype(np.float32)
    sigma = np.sqrt(np.float32(read_noise ** 2) + np.float32(shot_noise ** 2) * x)
    x += sigma * rng.standard_normal(x.shape, dtype=np.float32)
    np.clip(x, 0.0, 1.0, out=x)
    # sRGB encoding through a 4096-entry table (within half an 8-bit step of the formula).
    return SRGB_LUT_4096[(x * 4095.0 + 0.5).astype(np.int32)]


@dataclass(frozen=True)
class CameraModel:
    """An optional camera for traced photos: optics PSF and sensor noise, applied in linear light.

    The same model, with the same noise draws, is applied to a traced photo and to the truth render
    of the same view with objects inserted (:func:`camera_photo`), so that a compositor benchmark sees
    a camera whose blur and noise the compositor has to measure from the photo and match.

    exposure : multiplies the linear image before everything else (a frame's automatic exposure)
    blur_sigma : Gaussian PSF sigma, pixels (lens softness, slight defocus); 0 = none
    defocus_radius : disk PSF radius, pixels (thin-lens defocus), applied after the Gaussian; 0 = none
    read_noise, shot_noise : as :func:`encode_photo` (linear units; shot noise at 1.0)
    """

    blur_sigma: float = 0.0
    defocus_radius: float = 0.0
    exposure: float = 1.0
    read_noise: float = 0.004
    shot_noise: float = 0.012

    def to_dict(self) -> dict:
        return {"blur_sigma": self.blur_sigma, "defocus_radius": self.defocus_radius, "exposure": self.exposure,
                "read_noise": self.read_noise, "shot_noise": self.shot_noise}


def camera_psf(linear: np.ndarray, camera: CameraModel) -> np.ndarray:
    """The camera's optics on a linear (H, W, 3) float32 image: Gaussian then disk PSF, reflecting borders."""
    import cv2

    img = np.asarray(linear, np.float32)
    if camera.blur_sigma > 0:
        k = 2 * int(math.ceil(3.0 * camera.blur_sigma)) + 1
        img = cv2.GaussianBlur(img, (k, k), sigmaX=float(camera.blur_sigma), sigmaY=float(camera.blur_sigma),
                               borderType=cv2.BORDER_REFLECT)
    if camera.defocus_radius > 0:
        img = defocus(img, camera.defocus_radius)
    return img


def camera_photo(linear: np.ndarray, camera: CameraModel | None, rng: np.random.Generator) -> np.ndarray:
    """Linear exposure units -> 8-bit sRGB photo through ``camera`` (None = :func:`encode_photo` defaults).

    Parameters
    ----------
    linear : (H, W, 3) float32, 1.0 = sensor white
    camera : CameraModel or None
    rng : seeded generator (the sensor's noise draws)

    Returns
    -------
    (H, W, 3) uint8
    """
    if camera is None:
        return encode_photo(linear, rng)
    lin = np.asarray(linear, np.float32)
    if camera.exposure != 1.0:
        lin = lin * np.float32(camera.exposure)
    return encode_photo(camera_psf(lin, camera), rng, read_noise=camera.read_noise, shot_noise=camera.shot_noise)


def motion_kernel(length: int, angle: float) -> np.ndarray:
    """(L, L) float32 line kernel of ``length`` px at ``angle`` radians, sum 1 (linear motion blur)."""
    k = np.zeros((length, length), np.float32)
    c = (length - 1) / 2.0
    for t in np.linspace(-c, c, 4 * length):
        k[int(round(c + t * np.sin(angle))), int(round(c + t * np.cos(angle)))] += 1.0
    return k / k.sum()


def disk_kernel(radius: float) -> np.ndarray:
    """Normalised anti-aliased disk of ``radius`` pixels (a thin lens's defocus PSF); (k, k) float32."""
    r = max(float(radius), 0.5)
    n = int(math.ceil(r)) + 1
    y, x = np.mgrid[-n:n + 1, -n:n + 1].astype(np.float32)
    k = np.clip(r + 0.5 - np.sqrt(x * x + y * y), 0.0, 1.0)
    return (k / k.sum()).astype(np.float32)


def defocus(linear: np.ndarray, radius: float) -> np.ndarray:
    """Defocus blur: convolve a linear image with a disk of ``radius`` pixels; same shape and dtype."""
    import cv2

    return cv2.filter2D(linear, -1, disk_kernel(radius), borderType=cv2.BORDER_REFLECT)


def depth_normals_cos(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """|cos| of the angle between each pixel's viewing ray and the surface normal, from the depth map.

    Normals come from central differences of the back-projected points.

    Parameters
    ----------
    depth : (H, W) float32 metres, 0 = no surface
    K : (3, 3) intrinsics

    Returns
    -------
    (H, W) float32 in [0, 1]; 1 where the normal cannot be estimated (image border)
    """
    z = depth.astype(np.float32)
    h, w = z.shape
    u, v = image_plane(K, w, h, np.float32)
    u, v = u[None, :], v[:, None]
    X, Y = u * z, v * z
    cos = np.ones((h, w), np.float32)
    # d/dx and d/dy of the point (X, Y, Z) on the interior.
    ax, ay, az = X[1:-1, 2:] - X[1:-1, :-2], Y[1:-1, 2:] - Y[1:-1, :-2], z[1:-1, 2:] - z[1:-1, :-2]
    bx, by, bz = X[2:, 1:-1] - X[:-2, 1:-1], Y[2:, 1:-1] - Y[:-2, 1:-1], z[2:, 1:-1] - z[:-2, 1:-1]
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    rx, ry = np.broadcast_to(u[:, 1:-1], nx.shape), np.broadcast_to(v[1:-1, :], nx.shape)
    dot = np.abs(nx * rx + ny * ry + nz)
    nn = np.sqrt(nx * nx + ny * ny + nz * nz) * np.sqrt(rx * rx + ry * ry + 1.0)
    cos[1:-1, 1:-1] = np.where(nn > 0, dot / np.maximum(nn, np.float32(1e-20)), 1.0)
    return np.clip(cos, 0.0, 1.0)


def degrade_depth(depth: np.ndarray, K: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Sensor-like depth from true depth: axial noise growing with z^2, invalid pixels, mm quantisation.

    Invalid (0): no surface, nearer than :data:`DEPTH_MIN`, far range (ramp from
    :data:`DEPTH_FAR_START` to :data:`DEPTH_FAR_END`), grazing incidence (ramp from
    :data:`GRAZING_START_DEG` to :data:`GRAZING_END_DEG`), occlusion edges (probability
    :data:`EDGE_DROPOUT`) and random speckles.

    Parameters
    ----------
    depth : (H, W) float32, true z-depth in metres, 0 = no surface
    K : (3, 3) depth-camera intrinsics
    rng : seeded generator

    Returns
    -------
    (H, W) uint16, millimetres, 0 = invalid
    """
    z = depth.astype(np.float32)
    valid = z > DEPTH_MIN
    cos = depth_normals_cos(z, K)
    inc = np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))
    p_graze = np.clip((inc - GRAZING_START_DEG) / (GRAZING_END_DEG - GRAZING_START_DEG), 0.0, 1.0)
    p_far = np.clip((z - DEPTH_FAR_START) / (DEPTH_FAR_END - DEPTH_FAR_START), 0.0, 1.0)
    jump = np.zeros(z.shape, bool)
    dzx = np.abs(np.diff(z, axis=1)) > EDGE_JUMP
    dzy = np.abs(np.diff(z, axis=0)) > EDGE_JUMP
    jump[:, 1:] |= dzx
    jump[:, :-1] |= dzx
    jump[1:, :] |= dzy
    jump[:-1, :] |= dzy
    p_drop = 1.0 - (1.0 - p_graze) * (1.0 - p_far) * (1.0 - EDGE_DROPOUT * jump) * (1.0 - SPECKLE_DROPOUT)
    u = rng.random(z.shape, dtype=np.float32)
    valid &= u >= p_drop
    sigma = DEPTH_NOISE_A + DEPTH_NOISE_B * (z - 0.4) ** 2
    noisy = z + sigma * rng.standard_normal(z.shape, dtype=np.float32)
    mm = np.round(noisy * 1000.0)
    mm = np.where(valid, np.clip(mm, 1, 65535), 0)
    return mm.astype(np.uint16)
