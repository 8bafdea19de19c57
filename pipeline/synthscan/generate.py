"""Generate a synthetic room scan in a real layout, with its ground truth.

:func:`make_scan` is the entry point; :func:`builtin_scan` makes the named presets ("demo", "tiny").
Everything is a function of the seed: the same arguments give byte-identical files. The room itself
depends only on the seed (not on the size, frame count or layout).

Ground truth, under ``OUT/ground_truth/``:

- ``scan.json``: generator, layout, seed, sizes, intrinsics (OpenCV convention, pixel centres at
  integers), depth camera, ``up_w``, the world-from-canonical transform, exposure, and per frame:
  file names, ``T_c2w`` (metres, OpenCV camera axes), ``pose_valid``, blur label and strength; plus
  the list of every file written (used to clean up when the folder is regenerated).
- ``cameras.npz``: the same numbers as arrays: ``K`` (3, 3), ``depth_K`` (3, 3), ``T_c2w`` (F, 4, 4),
  ``pose_valid`` (F,) bool, ``blur_kind`` (F,) int8 (0 none, 1 motion, 2 defocus), ``blur_strength_px``
  (F,) float64, ``frame_ids`` (F,) int64.
- ``mesh.ply``: the true geometry (metres, world frame), vertex colours = material mean colour,
  vertex ``material_id`` and ``part_id``.
- ``scan_mesh.ply``: the scanner's mesh (also written in the layout's own mesh format where it has one).
- ``materials.json`` (+ ``textures/<material>.png``), ``lights.json`` (corners, normal, radiance, power),
  ``thin_parts.json`` (thin parts, their size and how much of each the scan mesh lost).
- ``depth/frame-XXXXXX.png``: true z-depth at the depth camera, uint16 in units of 0.1 mm (0 = none).
"""

from __future__ import annotations

import logging
import math
import shutil
from dataclasses import dataclass
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np

from pipeline.camera import Camera, transform_points
from pipeline.errors import UserError
from pipeline.io import atomic_save_npz, atomic_write_bytes, atomic_write_json, encode_image, read_json
from pipeline.seeding import item_rng
from pipeline.synthscan.writers import LAYOUTS, encode, frame_files, frame_id, ply_bytes, write_frame, write_static

if TYPE_CHECKING:
    from pipeline.synthscan.degrade import CameraModel
    from pipeline.synthscan.render import PhotoRenderer
    from pipeline.synthscan.room import MeshData, Room

log = logging.getLogger(__name__)

GENERATOR = "pipeline.synthscan"
VERSION = 1
GT_DIR = "ground_truth"
GT_DEPTH_SCALE = 1e-4         # metres per unit of the ground-truth depth PNGs
LIGHT_CELL = 0.10             # metres, tessellation of the true mesh (carries the light map)
PRESETS: Mapping[str, Mapping] = MappingProxyType({
    "demo": MappingProxyType({"layout": "7scenes", "seed": 0, "width": 640, "height": 480, "frames": 50}),
    "tiny": MappingProxyType({"layout": "7scenes", "seed": 0, "width": 160, "height": 120, "frames": 8}),
})
BLUR_CODES: Mapping[str, int] = MappingProxyType({"none": 0, "motion": 1, "defocus": 2})
MAX_SIZE = 4096
MAX_FRAMES = 5000


@dataclass(frozen=True)
class Cameras:
    """Colour and depth cameras of a layout (the depth camera shares the colour camera's centre)."""

    K: np.ndarray             # (3, 3) float64, colour intrinsics, pixels (OpenCV: pixel centres at integers)
    width: int
    height: int
    depth_K: np.ndarray       # (3, 3) float64
    depth_width: int
    depth_height: int


def layout_cameras(layout: str, width: int, height: int, rng: np.random.Generator) -> Cameras:
    """Intrinsics like the real sensor of each layout, scaled to ``width`` x ``height`` (colour)."""
    from pipeline.synthscan.trajectory import intrinsics

    if layout in ("7scenes", "bop"):   # Kinect v1 / Primesense: f = 585 px at 640 x 480, depth registered
        K = intrinsics(width, height, 585.0 / 640.0, rng)
        return Cameras(K, width, height, K.copy(), width, height)
    if layout == "transforms":   # phone: ~65 degree horizontal field of view
        K = intrinsics(width, height, 0.78, rng)
        return Cameras(K, width, height, K.copy(), width, height)
    if layout == "scannet":      # 1296 x 968 colour, 640 x 480 depth, both f/w ~ 0.9
        K = intrinsics(width, height, 1169.6 / 1296.0, rng)
        dw, dh = max(8, round(width * 640 / 1296)), max(8, round(height * 480 / 968))
        dK = intrinsics(dw, dh, 577.6 / 640.0, rng, offset_px=1.0)
        return Cameras(K, width, height, dK, dw, dh)
    if layout == "3rscan":       # 960 x 540 colour, 224 x 172 depth with anisotropic focal lengths
        K = intrinsics(width, height, 877.5 / 960.0, rng)
        dw, dh = max(8, round(width * 224 / 960)), max(8, round(height * 172 / 540))
        dK = intrinsics(dw, dh, 204.75 / 224.0, rng, offset_px=1.0)
        dK[1, 1] = round(279.5 / 172.0 * dh, 3)
        return Cameras(K, width, height, dK, dw, dh)
    raise UserError(f"unknown layout {layout!r}; choose one of {', '.join(LAYOUTS)}")


def _check_args(layout: str, seed: int, width: int, height: int, frames: int) -> None:
    if layout not in LAYOUTS:
        raise UserError(f"--layout {layout!r} is not a scan layout; choose one of {', '.join(LAYOUTS)}")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise UserError(f"--seed {seed!r}: the seed must be an integer >= 0")
    for name, v in (("width", width), ("height", height)):
        if not isinstance(v, (int, np.integer)) or not 16 <= v <= MAX_SIZE:
            raise UserError(f"--size: {name} {v!r} is out of range; give WxH with 16 <= W, H <= {MAX_SIZE}")
    if not isinstance(frames, (int, np.integer)) or not 1 <= frames <= MAX_FRAMES:
        raise UserError(f"--frames {frames!r} is out of range; give 1 to {MAX_FRAMES}")


def _prepare_out(out: Path) -> None:
    """Make ``out`` empty of a previous generation's files; refuse a folder holding anything else."""
    manifest = out / GT_DIR / "scan.json"
    if manifest.is_file():
        try:
            old = read_json(manifest)
            files = list(old.get("files", []))
        except (OSError, ValueError) as e:
            raise UserError(f"{manifest} is unreadable ({e}); delete {out} or choose another output folder") from e
        if old.get("generator") != GENERATOR:
            raise UserError(f"{out} holds a scan not written by {GENERATOR}; choose another output folder")
        for rel in files:
            p = (out / rel).resolve()
            if out.resolve() in p.parents:
                p.unlink(missing_ok=True)
        manifest.unlink(missing_ok=True)
        return
    if out.exists() and not out.is_dir():
        raise UserError(f"{out} is a file; give a folder for the scan")
    if out.is_dir() and any(out.iterdir()):
        raise UserError(f"{out} exists and is not empty; give a new or empty folder (or one written by "
                        f"make-scan before, which is then regenerated)")


def _world_from_canonical(layout: str, first_pose: np.ndarray) -> np.ndarray:
    """7-Scenes' world frame is the first camera's (as KinectFusion writes it); others keep z up."""
    if layout == "7scenes":
        return np.linalg.inv(first_pose)
    return np.eye(4)


def _choose_frames(rng: np.random.Generator, frames: int, layout: str) -> tuple[np.ndarray, np.ndarray]:
    """Per frame: blur kind code (0/1/2) and pose validity (ScanNet loses tracking on a few frames)."""
    kinds = np.zeros(frames, np.int8)
    valid = np.ones(frames, bool)
    candidates = np.arange(1, frames)
    if layout == "scannet" and frames >= 4:
        n_inv = max(1, round(0.04 * frames))
        bad = rng.choice(candidates, size=n_inv, replace=False)
        valid[bad] = False
        candidates = np.setdiff1d(candidates, bad)
    if frames >= 3:
        n = max(1, round(0.1 * frames))
        n = min(n, len(candidates) // 2)
        pick = rng.choice(candidates, size=2 * n, replace=False)
        kinds[pick[:n]] = BLUR_CODES["motion"]
        kinds[pick[n:]] = BLUR_CODES["defocus"]
    return kinds, valid


def _motion_extent(depth: np.ndarray, K: np.ndarray, T_mid: np.ndarray, T_a: np.ndarray, T_b: np.ndarray,
                   step: int = 4) -> float:
    """Median image displacement (px) of the surface points seen at ``T_mid`` between poses ``T_a`` and ``T_b``."""
    d = depth[::step, ::step]
    v, u = np.nonzero(d > 0)
    if len(u) == 0:
        return 0.0
    cam = Camera(K=K, T_c2w=T_mid, width=depth.shape[1], height=depth.shape[0])
    Xw = cam.c2w(cam.unproject(u * step, v * step, d[v, u].astype(np.float64)))
    uv_a, _ = cam.with_pose(T_a).project(Xw)
    uv_b, _ = cam.with_pose(T_b).project(Xw)
    return float(np.median(np.linalg.norm(uv_b - uv_a, axis=1)))


def make_scan(out_dir: str | Path, *, layout: str, seed: int, width: int = 640, height: int = 480,
              frames: int = 50, contact_sheet: str | Path | None = None, photo_mode: str = "raster",
              camera=None) -> Path:
    """Write a synthetic room scan in ``layout`` to ``out_dir``, with its ground truth.

    The steps: the room and its baked light (:func:`bake_light`, from the seed only), the cameras and
    trajectory (:func:`plan_shots`), the frames (:func:`_write_frames`), then the scanner's mesh, the
    layout's static files and the ground truth.

    Parameters
    ----------
    out_dir : folder to write (created; must be empty or hold an earlier make-scan output, which is replaced)
    layout : "7scenes" | "3rscan" | "scannet" | "transforms" | "bop"
    seed : int >= 0
    width, height : colour image size, pixels (depth is smaller for scannet and 3rscan, as in the real data)
    frames : number of frames
    contact_sheet : optional PNG path for a contact sheet of the frames (blurred ones marked)
    photo_mode : "raster" (pyrender) or "traced" (path tracer, see ``render.TracedPhotoRenderer``)
    camera : :class:`~pipeline.synthscan.degrade.CameraModel` or None; traced mode only: the camera's PSF
        and sensor noise on every photo (recorded in ``ground_truth/scan.json`` as ``camera``); None = the
        default sensor noise and no PSF (the outputs of earlier versions, byte for byte)

    Returns
    -------
    Path of the scan folder (``out_dir``).
    """
    from pipeline.synthscan.render import make_photo_renderer
    from pipeline.synthscan.room import make_room, tessellate
    from pipeline.synthscan.scanmesh import make_scan_mesh

    _check_args(layout, seed, width, height, frames)
    if camera is not None and photo_mode != "traced":
        raise UserError(f"make_scan: a camera model is for photo_mode 'traced' only, not {photo_mode!r}")
    seed, width, height, frames = int(seed), int(width), int(height), int(frames)
    out = Path(out_dir)
    _prepare_out(out)
    out.mkdir(parents=True, exist_ok=True)

    # Scene: depends on the seed only.
    room = make_room(item_rng(seed, "synthscan", "room"))
    mesh = tessellate(room, LIGHT_CELL)
    vertex_radiance, exposure = bake_light(room, mesh)
    shots = plan_shots(room, layout, seed, width, height, frames)
    cams, poses, T_wc = shots.cams, shots.poses, shots.T_wc

    renderer = make_photo_renderer(photo_mode, room, mesh, vertex_radiance)
    try:
        written = _write_frames(out, renderer, shots, seed, camera, thumbs=contact_sheet is not None)
    finally:
        renderer.close()
    files = list(written.files)

    # Scanner's mesh and the layout's static files.
    smesh = make_scan_mesh(room, mesh, vertex_radiance, item_rng(seed, "synthscan", "scan_mesh"),
                           cell=0.04 if width * height >= 320 * 240 else 0.08)
    sverts = transform_points(T_wc, smesh.vertices)
    files += write_static(out, layout, scene=shots.scene, K=cams.K, width=width, height=height,
                          depth_K=cams.depth_K, depth_width=cams.depth_width, depth_height=cams.depth_height,
                          up_w=shots.up_w, poses=poses, pose_valid=shots.pose_valid, mesh_vertices=sverts,
                          mesh_faces=smesh.faces, mesh_colors=smesh.colors)

    files += _write_truth(out, room, mesh, smesh, sverts, T_wc, exposure)
    atomic_save_npz(out / GT_DIR / "cameras.npz", K=cams.K, depth_K=cams.depth_K, T_c2w=poses,
                    pose_valid=shots.pose_valid, blur_kind=shots.kinds, blur_strength_px=written.strengths,
                    frame_ids=np.array([frame_id(layout, i) for i in range(frames)], np.int64))
    files.append(f"{GT_DIR}/cameras.npz")

    if contact_sheet is not None:
        from pipeline.synthscan.contact import contact_sheet as make_sheet

        labels = [{"index": d["index"], "blur": d["blur"]["kind"], "strength_px": d["blur"]["strength_px"],
                   "pose_valid": d["pose_valid"]} for d in written.frame_docs]
        sheet = make_sheet(list(written.thumbs), labels)
        atomic_write_bytes(Path(contact_sheet), encode_image(Path(contact_sheet).with_suffix(".png"), sheet))

    doc = _scan_doc(shots, seed=seed, photo_mode=photo_mode, exposure=exposure, frame_docs=written.frame_docs,
                    files=files)
    if camera is not None:
        doc["camera"] = camera.to_dict()
    atomic_write_json(out / GT_DIR / "scan.json", doc)
    log.info("wrote %s scan with %d frames to %s", layout, frames, out)
    return out


def bake_light(room: Room, mesh: MeshData) -> tuple[np.ndarray, float]:
    """The raster photos' light baked on the true mesh's vertices, and the exposure that sets it.

    Exact polygon irradiance per light with soft shadows, plus the ambient radiance times ambient
    occlusion; the exposure puts the median non-emitting vertex at 0.5; lamp parts show their own
    radiance.

    Parameters
    ----------
    room : :class:`~pipeline.synthscan.room.Room`
    mesh : its tessellation (:func:`~pipeline.synthscan.room.tessellate`)

    Returns
    -------
    vertex_radiance : (V, 3) float32, outgoing radiance per unit albedo times the exposure
    exposure : float, radiance-to-sensor scale
    """
    from pipeline.synthscan import lighting

    shadows = lighting.EmbreeShadows(mesh.vertices, mesh.faces, samples=3)
    E = lighting.direct_irradiance(mesh.vertices, mesh.normals.astype(np.float64), room.lights, shadows)
    vmat = room.quad_material[mesh.vertex_quad]
    emitter_v = np.array([m.emitter for m in room.materials])[vmat]
    ao = shadows.ambient_occlusion(mesh.vertices, mesh.normals.astype(np.float64))
    radiance = E / math.pi + room.ambient * ao[:, None]      # outgoing radiance per unit albedo
    exposure = 0.5 / float(np.median(radiance[~emitter_v].mean(axis=1)))
    vertex_radiance = (radiance * exposure).astype(np.float32)
    lamp_L = {L.name: L.radiance for L in room.lights}
    for q, part in enumerate(room.parts):
        if part.name in lamp_L:
            sel = room.quad_part[mesh.vertex_quad] == q
            vertex_radiance[sel] = (lamp_L[part.name] * exposure).astype(np.float32)
    return vertex_radiance, exposure


@dataclass(frozen=True)
class Shots:
    """The cameras, poses and per-frame choices of a scan (:func:`plan_shots`)."""

    layout: str
    width: int                # colour image size, pixels
    height: int
    cams: Cameras
    poses_canon: np.ndarray   # (F, 4, 4) float64, T_c2w in the room's canonical frame (z up), metres
    poses: np.ndarray         # (F, 4, 4) float64, T_c2w in the layout's world frame (written to the files)
    T_wc: np.ndarray          # (4, 4) float64, layout world from canonical
    up_w: np.ndarray          # (3,) float64, up in the layout's world frame
    kinds: np.ndarray         # (F,) int8, blur kind code (BLUR_CODES)
    pose_valid: np.ndarray    # (F,) bool
    scene: str                # the scene's name in the layout


def plan_shots(room: Room, layout: str, seed: int, width: int, height: int, frames: int) -> Shots:
    """The trajectory through ``room``, the layout's cameras, which frames blur and lose tracking, and the
    layout's world frame; each from its own generator of ``seed``."""
    from pipeline.synthscan.trajectory import walk

    poses_canon = walk(room, item_rng(seed, "synthscan", "trajectory", str(frames)), frames)
    cams = layout_cameras(layout, width, height, item_rng(seed, "synthscan", "cameras", layout, f"{width}x{height}"))
    kinds, pose_valid = _choose_frames(item_rng(seed, "synthscan", "frames", layout, str(frames)), frames, layout)
    T_wc = _world_from_canonical(layout, poses_canon[0])
    poses = np.einsum("ij,fjk->fik", T_wc, poses_canon)
    if layout == "7scenes":
        poses[0] = np.eye(4)
    up_w = T_wc[:3, :3] @ np.array([0.0, 0.0, 1.0])
    scene = f"scene{seed % 10000:04d}_00" if layout == "scannet" else f"synth{seed}"
    return Shots(layout=layout, width=width, height=height, cams=cams, poses_canon=poses_canon, poses=poses,
                 T_wc=T_wc, up_w=up_w, kinds=kinds, pose_valid=pose_valid, scene=scene)


@dataclass(frozen=True)
class FramesWritten:
    """What :func:`_write_frames` wrote and measured."""

    files: tuple[str, ...]            # paths written, relative to the scan folder
    frame_docs: tuple[dict, ...]      # per frame: the ``frames_info`` entry of scan.json
    strengths: np.ndarray             # (F,) float64, blur strength, pixels
    thumbs: tuple[np.ndarray, ...]    # contact-sheet thumbnails (empty when not asked)


def _write_frames(out: Path, renderer: PhotoRenderer, shots: Shots, seed: int, camera: CameraModel | None, *,
                  thumbs: bool) -> FramesWritten:
    """Render, degrade and write every frame (photo, depth, pose, ground-truth depth) in the layout.

    Each frame draws from its own generator: the photo's blur, then the camera's noise, then the depth
    sensor's (:func:`_frame_photo`, :func:`~pipeline.synthscan.degrade.camera_photo`,
    :func:`~pipeline.synthscan.degrade.degrade_depth`).
    """
    import cv2

    from pipeline.synthscan import degrade

    layout, width, height, cams, poses = shots.layout, shots.width, shots.height, shots.cams, shots.poses
    frames = len(shots.poses_canon)
    files: list[str] = []
    frame_docs: list[dict] = []
    strengths = np.zeros(frames)
    thumb_list: list[np.ndarray] = []
    tw = 160
    th = max(1, round(height * tw / width))
    for i in range(frames):
        rng = item_rng(seed, "synthscan", "frame", layout, str(i))
        T = shots.poses_canon[i]
        img, blur = _frame_photo(renderer, cams, T, int(shots.kinds[i]), rng, width, height)
        strengths[i] = blur["strength_px"]
        photo = degrade.camera_photo(img, camera, rng)
        true_depth = renderer.render_depth(Camera(cams.depth_K, T, cams.depth_width, cams.depth_height))
        depth_mm = degrade.degrade_depth(true_depth, cams.depth_K, rng)
        files += write_frame(out, layout, i, photo, depth_mm, poses[i], bool(shots.pose_valid[i]))
        gt_rel = f"{GT_DIR}/depth/frame-{i:06d}.png"
        gt_depth = np.clip(np.round(true_depth.astype(np.float64) / GT_DEPTH_SCALE), 0, 65535).astype(np.uint16)
        atomic_write_bytes(out / gt_rel, encode(gt_rel, gt_depth))
        files.append(gt_rel)
        ff = frame_files(layout, i)
        frame_docs.append({"index": i, "frame_id": frame_id(layout, i), "color": ff.color, "depth": ff.depth,
                           "pose": ff.pose, "gt_depth": gt_rel, "pose_valid": bool(shots.pose_valid[i]),
                           "T_c2w": poses[i].tolist(), "blur": blur})
        if thumbs:
            thumb_list.append(cv2.resize(photo, (tw, th), interpolation=cv2.INTER_AREA))
        log.debug("frame %d/%d done (%s)", i + 1, frames, blur["kind"])
    return FramesWritten(files=tuple(files), frame_docs=tuple(frame_docs), strengths=strengths,
                         thumbs=tuple(thumb_list))


def _frame_photo(renderer: PhotoRenderer, cams: Cameras, T: np.ndarray, kind: int, rng: np.random.Generator, width: int,
                 height: int) -> tuple[np.ndarray, dict]:
    """The frame's linear colour image (H, W, 3) float32 before the camera's noise, and its blur label.

    Motion blur averages sub-frames rendered along a random exposure path (its strength is measured on
    the depth at ``T``); defocus convolves with a disk of random radius; both scale with the width.
    """
    from pipeline.synthscan import degrade
    from pipeline.synthscan.trajectory import exposure_path

    blur: dict = {"kind": "none", "strength_px": 0.0}
    if kind == BLUR_CODES["motion"]:
        target = rng.uniform(6.0, 18.0) * width / 640.0
        psi = rng.uniform(0, 2 * math.pi)
        mag = target / cams.K[0, 0]
        omega = mag * np.array([math.sin(psi), math.cos(psi), rng.uniform(-0.3, 0.3)])
        vel = rng.normal(0.0, 0.01, 3)
        n_sub = int(np.clip(math.ceil(target / 1.5), 6, 16))
        subs = exposure_path(T, omega, vel, n_sub)
        img = np.zeros((height, width, 3), np.float32)
        for S in subs:
            img += renderer.render_color(Camera(cams.K, S, width, height))
        img /= n_sub
        depth_c = renderer.render_depth(Camera(cams.K, T, width, height))
        strength = _motion_extent(depth_c, cams.K, T, subs[0], subs[-1])
        blur = {"kind": "motion", "strength_px": round(strength, 4), "sub_frames": n_sub,
                "omega_rad": omega.tolist(), "velocity_m": vel.tolist()}
    else:
        img = renderer.render_color(Camera(cams.K, T, width, height))
        if kind == BLUR_CODES["defocus"]:
            r = round(float(rng.uniform(2.0, 5.0) * width / 640.0), 4)
            img = degrade.defocus(img, r)
            blur = {"kind": "defocus", "strength_px": r, "psf": "disk", "radius_px": r}
    return img, blur


def _scan_doc(shots: Shots, *, seed: int, photo_mode: str, exposure: float, frame_docs: tuple[dict, ...],
              files: list[str]) -> dict:
    """The ``ground_truth/scan.json`` document (without the optional ``camera``)."""
    cams = shots.cams
    return {
        "generator": GENERATOR, "version": VERSION, "layout": shots.layout, "seed": seed, "scene": shots.scene,
        "photo_mode": photo_mode, "width": shots.width, "height": shots.height, "frames": len(shots.poses),
        "K": cams.K.tolist(), "depth_K": cams.depth_K.tolist(), "depth_width": cams.depth_width,
        "depth_height": cams.depth_height, "depth_scale": 0.001, "gt_depth_scale": GT_DEPTH_SCALE,
        "depth_registered": True, "up_w": shots.up_w.tolist(), "T_world_from_canonical": shots.T_wc.tolist(),
        "exposure": exposure, "conventions": {
            "K": "OpenCV: pixel (u, v) centred at integer coordinates; transforms.json stores cx, cy + 0.5 "
                 "(nerfstudio centres pixels at i + 0.5)",
            "T_c2w": "camera-to-world, metres, OpenCV camera axes (x right, y down, z forward)",
            "blur": "motion: the photo averages sub-frames rendered along the exposure path (strength = median "
                    "image displacement over the exposure, px); defocus: disk PSF (strength = radius, px); "
                    "depth maps are never blurred (taken at the frame's pose)",
            "invalid_pose": "pose_valid false: the layout's pose file says tracking was lost (ScanNet -inf); "
                            "ingest must skip these frames",
        },
        "num_valid_poses": int(shots.pose_valid.sum()),
        "frames_info": list(frame_docs),
        "files": sorted(files + [f"{GT_DIR}/scan.json"]),
    }


def _write_truth(out: Path, room, mesh, smesh, sverts: np.ndarray, T_wc: np.ndarray, exposure: float) -> list[str]:
    """Ground-truth mesh, materials, lights and thin parts, in the layout's world frame."""
    from pipeline.color import encode_u8

    files: list[str] = []
    g = out / GT_DIR
    vmat = room.quad_material[mesh.vertex_quad]
    base = np.array([m.base_color for m in room.materials], np.float32)
    vcol = encode_u8(base[vmat])
    verts_w = transform_points(T_wc, mesh.vertices)
    atomic_write_bytes(g / "mesh.ply", ply_bytes(
        verts_w, mesh.faces, vcol, vertex_ints={"material_id": vmat, "part_id": room.quad_part[mesh.vertex_quad]},
        comments=("synthscan true geometry, metres, world frame",)))
    atomic_write_bytes(g / "scan_mesh.ply", ply_bytes(sverts, smesh.faces, smesh.colors,
                                                      comments=("synthscan scanner-like mesh, metres",)))
    files += [f"{GT_DIR}/mesh.ply", f"{GT_DIR}/scan_mesh.ply"]

    mats = []
    for m in room.materials:
        rel = f"{GT_DIR}/textures/{m.name}.png"
        atomic_write_bytes(out / rel, encode(rel, room.textures[m.id]))
        files.append(rel)
        mats.append({"id": m.id, "name": m.name, "texture_kind": m.kind, "base_color_linear": list(m.base_color),
                     "metres_per_repeat": m.metres_per_repeat, "roughness": m.roughness, "metallic": 0.0,
                     "emitter": m.emitter, "texture": rel})
    atomic_write_json(g / "materials.json", {"materials": mats})

    R = T_wc[:3, :3]
    lights = []
    for L in room.lights:
        c = transform_points(T_wc, L.corners)
        lights.append({"name": L.name, "kind": L.kind, "corners": c.tolist(), "position": c.mean(0).tolist(),
                       "normal": (R @ L.normal).tolist(), "size_m": [float(np.linalg.norm(L.corners[1] - L.corners[0])),
                                                                   float(np.linalg.norm(L.corners[3] - L.corners[0]))],
                       "area_m2": L.area, "radiance": L.radiance.tolist(), "power": L.power.tolist()})
    atomic_write_json(g / "lights.json", {
        "units": "relative radiometric units: radiance W/(m^2 sr), power W; photo pixel (linear) = "
                 "exposure * albedo * outgoing radiance per unit albedo, clipped at 1",
        "exposure": exposure, "ambient_radiance": room.ambient, "lights": lights,
        "shading": "raster mode: Lambert; exact polygon irradiance per light with 3x3-ray soft shadows, "
                   "plus ambient radiance times ambient occlusion (16 rays, 0.6 m), baked on vertices every "
                   "0.1 m; no inter-reflection"})

    thin = []
    for pi, p in enumerate(room.parts):
        if not p.thin:
            continue
        sel = np.isin(mesh.vertex_quad, np.arange(p.quad_start, p.quad_stop))
        pv = verts_w[sel]
        thin.append({"name": p.name, "part_id": pi, "material": room.materials[p.material_id].name,
                     "thickness_m": p.thickness, "bbox_min": pv.min(0).tolist(), "bbox_max": pv.max(0).tolist(),
                     "scan_mesh_missing_fraction": smesh.thin_missing.get(p.name, 0.0)})
    atomic_write_json(g / "thin_parts.json", {"thin_parts": thin})
    files += [f"{GT_DIR}/materials.json", f"{GT_DIR}/lights.json", f"{GT_DIR}/thin_parts.json"]
    return files


def builtin_scan(name: str, out_dir: str | Path) -> Path:
    """Write the preset scan ``name`` ("demo": 640x480, 50 frames; "tiny": 160x120, 8 frames; both in the
    7scenes layout, seed 0) to ``out_dir`` and return ``out_dir``.

    A folder that already holds the same preset from this generator version is reused as it is.
    """
    if name not in PRESETS:
        raise UserError(f"builtin:{name} is not a built-in scan; choose one of "
                        f"{', '.join('builtin:' + k for k in PRESETS)}")
    p = PRESETS[name]
    out = Path(out_dir)
    manifest = out / GT_DIR / "scan.json"
    if manifest.is_file():
        try:
            doc = read_json(manifest)
        except (OSError, ValueError):
            doc = {}
        same = (doc.get("generator") == GENERATOR and doc.get("version") == VERSION
                and all(doc.get(k) == v for k, v in p.items()))
        if same and all((out / rel).is_file() for rel in doc.get("files", [])):
            return out
    return make_scan(out, **p)


def remove_scan(out_dir: str | Path) -> None:
    """Delete a folder written by :func:`make_scan` (refuses any other folder)."""
    out = Path(out_dir)
    if not (out / GT_DIR / "scan.json").is_file():
        raise UserError(f"{out} is not a folder written by make-scan (no {GT_DIR}/scan.json)")
    shutil.rmtree(out)
