"""Types passed between stages.

Every stage exchanges frozen dataclasses of NumPy arrays. Units are metres, camera axes are OpenCV's
(x right, y down, z forward), poses are rigid 4x4 transforms named with BOP frame suffixes
(``T_c2w`` maps camera coordinates to world coordinates). Millimetres appear only inside the BOP writer.

Each type has a ``save_*``/``load_*`` pair in :mod:`pipeline.io` (or next to the stage that makes it)
with a round-trip test.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.camera import Camera, RGBDRig


@dataclass(frozen=True)
class Scan:
    """A posed RGB-D scan of a room, after ingest, in the pipeline's conventions.

    Frames are structure-of-arrays: index ``i`` of every per-frame field is the same frame.
    Only frames with a valid pose are kept; ``frame_ids`` keeps the scan's own numbering.
    """

    name: str                 # scene name, unique within a run (folder-safe)
    root: str                 # absolute path of the scan folder as given by the user
    format: str               # "7scenes" | "3rscan" | "scannet" | "transforms" | ...
    frame_ids: np.ndarray     # (F,) int64, the scan's own frame numbers
    color_paths: tuple[str, ...]   # (F,) absolute paths of the colour images
    depth_paths: tuple[str, ...]   # (F,) absolute paths of the depth images ("" when a frame has none)
    width: int                # colour image width, pixels
    height: int               # colour image height, pixels
    K: np.ndarray             # (F, 3, 3) float64, colour intrinsics at (width, height), pixels
    T_c2w: np.ndarray         # (F, 4, 4) float64, camera-to-world, metres, OpenCV camera axes
    depth_width: int          # depth image width, pixels
    depth_height: int         # depth image height, pixels
    depth_K: np.ndarray       # (F, 3, 3) float64, depth intrinsics at (depth_width, depth_height)
    depth_scale: float        # metres per depth unit as stored in the files (e.g. 0.001 for uint16 mm)
    depth_registered: bool    # True when depth pixels are aligned with colour pixels (same camera)
    up_w: np.ndarray          # (3,) float64, unit "up" vector (against gravity), world frame
    mesh_path: str            # absolute path of the room mesh (PLY, metres, world frame, vertex colours)
    meta: dict = field(default_factory=dict)  # format-specific extras, JSON-serialisable

    @property
    def num_frames(self) -> int:
        return int(self.frame_ids.shape[0])

    def rig(self, i: int) -> RGBDRig:
        """Frame ``i``'s colour and depth cameras (intrinsics, sizes, ``T_d2c`` from ``meta``)."""
        return RGBDRig(color_K=self.K[i], color_width=self.width, color_height=self.height,
                       depth_K=self.depth_K[i], depth_width=self.depth_width, depth_height=self.depth_height,
                       T_d2c=np.asarray(self.meta.get("T_d2c", np.eye(4)), np.float64))

    def camera(self, i: int) -> Camera:
        """Frame ``i``'s colour camera: the camera of its photo and of everything drawn on it."""
        return Camera(K=self.K[i], T_c2w=self.T_c2w[i], width=self.width, height=self.height)


@dataclass(frozen=True)
class ObjectModel:
    """One 3D object model of the library, in metres, in its own model frame."""

    obj_id: int               # library id (BOP obj_id), >= 1
    name: str                 # human-readable name (file stem or BOP name)
    source_path: str          # absolute path of the file it was loaded from
    vertices: np.ndarray      # (V, 3) float64, metres, model frame
    faces: np.ndarray         # (T, 3) int32, indices into vertices, counter-clockwise seen from outside
    normals: np.ndarray       # (V, 3) float32, unit vertex normals, model frame
    vertex_colors: np.ndarray | None  # (V, 3) uint8 sRGB, or None when a texture is used
    uv: np.ndarray | None     # (V, 2) float32 texture coordinates (OpenGL: v up), or None
    texture: np.ndarray | None  # (H, W, 3) uint8 sRGB base-colour texture, or None
    base_color: tuple[float, float, float] = (0.8, 0.8, 0.8)  # linear RGB used when neither colours nor texture
    metallic: float = 0.0     # [0, 1]
    roughness: float = 0.5    # [0, 1], perceptual roughness (alpha = roughness**2)
    # BOP models_info for this object, in metres (the BOP writer converts to mm):
    # diameter, min_x, min_y, min_z, size_x, size_y, size_z
    info: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Placement:
    """Poses of the objects of one drop (one physics simulation) in the world frame of a scan."""

    scene: str                # Scan.name
    drop: int                 # drop index within the scene
    obj_ids: np.ndarray       # (N,) int32, ObjectModel.obj_id of each instance
    R_m2w: np.ndarray         # (N, 3, 3) float64, model-to-world rotation
    t_m2w: np.ndarray         # (N, 3) float64, model-to-world translation, metres
    at_rest: np.ndarray       # (N,) bool, body was asleep at the end of the simulation
    max_penetration: float    # metres, largest penetration depth seen at the end
    verdict: str              # "accepted" | "rejected:<reason>"
