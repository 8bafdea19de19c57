"""The pinhole camera: the only place where pinhole maths and camera axis conventions live.

Conventions (as everywhere in the pipeline):

* OpenCV camera axes: x right, y down, z forward; metres.
* Pixel centres at integer coordinates: pixel ``(row r, column c)`` covers the unit square centred on
  the image point ``u = c, v = r`` (bop_toolkit's ``misc.project_pts`` convention).
* Poses are camera-to-world (``T_c2w``), rigid 4x4, with BOP frame suffixes.

A scan may have a colour camera and a depth camera that differ: other intrinsics, another resolution
and a rigid offset ``T_d2c`` (depth camera coordinates -> colour camera coordinates). :class:`RGBDRig`
holds that pair; its :meth:`RGBDRig.depth` turns a colour camera pose into the depth camera's.

The rasterizer's OpenGL camera is derived here too (:meth:`Camera.gl_pose`, :meth:`Camera.gl_intrinsics`):
OpenGL looks down -z with y up, and samples pixel ``c`` at ``c + 0.5``.

Examples
--------
>>> import numpy as np
>>> cam = Camera(K=np.array([[500., 0, 319.5], [0, 500., 239.5], [0, 0, 1]]), T_c2w=np.eye(4),
...              width=640, height=480)
>>> uv, z = cam.project(np.array([[0.0, 0.0, 2.0]]))
>>> uv.tolist(), z.tolist()
([[319.5, 239.5]], [2.0])
>>> cam.unproject(uv[:, 0], uv[:, 1], z).tolist()
[[0.0, 0.0, 2.0]]
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Camera", "RGBDRig", "CV_TO_GL", "scaled_intrinsics", "transform_points", "project_points",
           "unproject_points", "image_plane", "gl_camera_pose", "gl_intrinsics"]

# OpenCV camera axes (x right, y down, z forward) -> OpenGL camera axes (x right, y up, z backward).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
CV_TO_GL.flags.writeable = False


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points (N, 3)`` moved by the rigid 4x4 ``T`` (float64)."""
    T = np.asarray(T, np.float64)
    return np.asarray(points, np.float64) @ T[:3, :3].T + T[:3, 3]


def project_points(K: np.ndarray, points_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) -> image points ``uv (N, 2)`` float64 and depths ``z (N,)``.

    Points at or behind the camera (``z <= 0``) give non-finite or meaningless ``uv``: check ``z``.
    """
    p = np.asarray(points_c, np.float64)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * p[:, 0] / z + K[0, 2]
        v = K[1, 1] * p[:, 1] / z + K[1, 2]
    return np.stack([u, v], axis=1), z


def unproject_points(K: np.ndarray, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Image points ``(u, v)`` at camera depths ``z`` (shapes that broadcast) -> camera-frame points
    ``(..., 3)`` float64."""
    z = np.asarray(z, np.float64)
    x = (np.asarray(u, np.float64) - K[0, 2]) / K[0, 0] * z
    y = (np.asarray(v, np.float64) - K[1, 2]) / K[1, 1] * z
    x, y, z = np.broadcast_arrays(x, y, z)
    return np.stack([x, y, z], axis=-1)


def image_plane(K: np.ndarray, width: int, height: int, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    """Where the rays through the pixel centres meet the plane ``z = 1``: ``x (width,)`` and ``y (height,)``
    in ``dtype``, so the ray through pixel ``(r, c)`` is ``(x[c], y[r], 1)``."""
    dt = np.dtype(dtype).type
    x = (np.arange(width, dtype=dtype) - dt(K[0, 2])) / dt(K[0, 0])
    y = (np.arange(height, dtype=dtype) - dt(K[1, 2])) / dt(K[1, 1])
    return x, y


def gl_camera_pose(T_c2w: np.ndarray) -> np.ndarray:
    """(4, 4) float64 camera-to-world with OpenGL camera axes (y up, looking down -z), as pyrender expects,
    of an OpenCV camera-to-world pose."""
    return np.asarray(T_c2w, dtype=np.float64) @ CV_TO_GL


def gl_intrinsics(K: np.ndarray, x0: int = 0, y0: int = 0) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` for an OpenGL renderer (pyrender's IntrinsicsCamera) drawing the window whose
    top-left pixel is ``(x0, y0)`` of the image of intrinsics ``K`` (may be negative or beyond the image).

    The principal point moves to the window and shifts by half a pixel: OpenGL samples pixel ``c`` at
    ``c + 0.5``, OpenCV's pixel centre is ``c``.
    """
    return (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) - x0 + 0.5, float(K[1, 2]) - y0 + 0.5)


def scaled_intrinsics(K: np.ndarray, width: int, height: int, scale: float) -> tuple[np.ndarray, int, int]:
    """Intrinsics and size of an image resampled to ``scale`` times ``width x height``.

    Pixel centres stay consistent: a point at pixel ``u`` maps to ``(u + 0.5) * s - 0.5`` where ``s`` is
    the actual (rounded) size ratio.

    Returns
    -------
    K : (3, 3) float64, width : int, height : int
    """
    w, h = int(round(width * scale)), int(round(height * scale))
    sx, sy = w / width, h / height
    Ks = np.array(K, dtype=np.float64)
    Ks[0, 0] *= sx
    Ks[1, 1] *= sy
    Ks[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    Ks[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return Ks, w, h


@dataclass(frozen=True)
class Camera:
    """A posed pinhole camera, OpenCV axes, pixel centres at integer coordinates."""

    K: np.ndarray        # (3, 3) float64 intrinsics, pixels
    T_c2w: np.ndarray    # (4, 4) float64 camera-to-world, metres
    width: int           # pixels
    height: int          # pixels

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, np.float64))
        object.__setattr__(self, "T_c2w", np.asarray(self.T_c2w, np.float64))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # --- size and intrinsics ---------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)``, the shape of an image of this camera."""
        return self.height, self.width

    def scaled(self, scale: float) -> "Camera":
        """The same camera rendering ``scale`` times the resolution (see :func:`scaled_intrinsics`)."""
        K, w, h = scaled_intrinsics(self.K, self.width, self.height, scale)
        return Camera(K=K, T_c2w=self.T_c2w, width=w, height=h)

    def with_pose(self, T_c2w: np.ndarray) -> "Camera":
        """The same intrinsics at another pose."""
        return Camera(K=self.K, T_c2w=T_c2w, width=self.width, height=self.height)

    # --- extrinsics -------------------------------------------------------------------------------
    @property
    def T_w2c(self) -> np.ndarray:
        """(4, 4) float64 world-to-camera (the general inverse, as bop_toolkit computes it)."""
        return np.linalg.inv(self.T_c2w)

    @property
    def center(self) -> np.ndarray:
        """(3,) float64 camera centre, world frame."""
        return self.T_c2w[:3, 3].copy()

    def w2c(self, points_w: np.ndarray) -> np.ndarray:
        """World points (N, 3) -> camera-frame points (N, 3) float64."""
        return transform_points(self.T_w2c, points_w)

    def c2w(self, points_c: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) -> world points (N, 3) float64."""
        return transform_points(self.T_c2w, points_c)

    def poses_m2c(self, R_m2w: np.ndarray, t_m2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-from-model poses of N instances placed by ``R_m2w (N, 3, 3)``, ``t_m2w (N, 3)`` metres.

        Returns ``R_m2c (N, 3, 3)`` and ``t_m2c (N, 3)`` float64.
        """
        T_w2c = self.T_w2c
        R_w2c, t_w2c = T_w2c[:3, :3], T_w2c[:3, 3]
        R_m2c = np.einsum("ij,njk->nik", R_w2c, np.asarray(R_m2w, dtype=np.float64))
        t_m2c = np.asarray(t_m2w, dtype=np.float64) @ R_w2c.T + t_w2c
        return R_m2c, t_m2c

    # --- projection -------------------------------------------------------------------------------
    def project_cam(self, points_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points (N, 3) -> image points and depths (see :func:`project_points`)."""
        return project_points(self.K, points_c)

    def project(self, points_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) -> image points ``uv (N, 2)`` and camera depths ``z (N,)`` (see
        :meth:`project_cam`)."""
        return self.project_cam(self.w2c(points_w))

    def unproject(self, u: np.ndarray, v: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Image points ``(u, v)`` at camera depths ``z`` -> camera-frame points (see :func:`unproject_points`)."""
        return unproject_points(self.K, u, v, z)

    # --- rays -------------------------------------------------------------------------------------
    def rays(self, pixels: np.ndarray, jitter: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-space rays through flat pixel indices ``pixels (R,)`` at offsets ``jitter (R, 2)`` in
        [0, 1): the ray goes through image point ``(x + jx - 0.5, y + jy - 0.5)``.

        Returns
        -------
        origins (R, 3) float32, unit directions (R, 3) float32, world frame.
        """
        K = self.K
        jit = np.asarray(jitter, np.float32)
        x = (pixels % self.width).astype(np.float32) + (jit[:, 0] - np.float32(0.5 + K[0, 2]))
        y = (pixels // self.width).astype(np.float32) + (jit[:, 1] - np.float32(0.5 + K[1, 2]))
        d = np.stack([x / np.float32(K[0, 0]), y / np.float32(K[1, 1]), np.ones_like(x)], axis=1)
        n = np.sqrt(np.einsum("ij,ij->i", d, d))
        d = (d / np.maximum(n, 1e-20)[:, None]) @ self.T_c2w[:3, :3].T.astype(np.float32)
        o = np.broadcast_to(self.T_c2w[:3, 3].astype(np.float32), d.shape)
        return np.ascontiguousarray(o), d

    # --- OpenGL -----------------------------------------------------------------------------------
    def gl_pose(self) -> np.ndarray:
        """(4, 4) float64 camera-to-world with OpenGL camera axes (see :func:`gl_camera_pose`)."""
        return gl_camera_pose(self.T_c2w)

    def gl_intrinsics(self, x0: int = 0, y0: int = 0) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)`` for an OpenGL renderer drawing the window at ``(x0, y0)`` (see
        :func:`gl_intrinsics`)."""
        return gl_intrinsics(self.K, x0, y0)


@dataclass(frozen=True)
class RGBDRig:
    """A colour camera and a depth camera rigidly mounted together.

    Poses handed to :meth:`color` and :meth:`depth` are the colour camera's (the pipeline's poses are
    always the colour camera's); the depth camera sits at ``T_c2w @ T_d2c``.
    """

    color_K: np.ndarray          # (3, 3) float64, colour intrinsics at (color_width, color_height)
    color_width: int
    color_height: int
    depth_K: np.ndarray          # (3, 3) float64, depth intrinsics at (depth_width, depth_height)
    depth_width: int
    depth_height: int
    T_d2c: np.ndarray = field(default_factory=lambda: np.eye(4))  # (4, 4) depth camera -> colour camera, metres

    def color(self, T_c2w: np.ndarray) -> Camera:
        """The colour camera at colour pose ``T_c2w``."""
        return Camera(K=self.color_K, T_c2w=T_c2w, width=self.color_width, height=self.color_height)

    def depth(self, T_c2w: np.ndarray) -> Camera:
        """The depth camera when the colour camera is at ``T_c2w``."""
        T = np.asarray(T_c2w, np.float64) @ np.asarray(self.T_d2c, np.float64)
        return Camera(K=self.depth_K, T_c2w=T, width=self.depth_width, height=self.depth_height)

    @property
    def registered(self) -> bool:
        """True when depth pixels are colour pixels (same intrinsics, size and centre)."""
        return (self.color_width == self.depth_width and self.color_height == self.depth_height
                and np.allclose(self.color_K, self.depth_K, atol=1e-9)
                and np.allclose(self.T_d2c, np.eye(4), atol=1e-9))
