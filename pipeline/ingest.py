"""Ingest stage: read room scans and object libraries into the run folder.

Items: one per entry of ``scan.paths`` (key = scene name: the folder name made folder-safe and unique)
and one item ``objects``. A scan item writes::

    RUN/ingest/<scene>/scan.json    scalars, paths, format, up, meta (skipped frames, notes)
    RUN/ingest/<scene>/frames.npz   frame_ids (F,) int64, K (F,3,3), T_c2w (F,4,4), depth_K (F,3,3) float64
    RUN/ingest/<scene>/room.ply     room mesh: metres, world frame, uint8 vertex colours

Before the mesh, the colour camera is checked against the data: depth edges seen through it must meet the
photos' edges; where the format gives no colour calibration (7-Scenes) or the check finds a better one,
the estimated camera replaces it (:func:`pipeline.registration.register_scan`; ``ingest.register_color``),
and ``scan.json`` records the alignment before and after (``meta["color_registration"]``).

The room mesh is the scan's own mesh converted (textured OBJ -> vertex colours), or a TSDF reconstruction
(:mod:`pipeline.reconstruct`). The up direction comes from the scan's metadata when it has some (7-Scenes
``gravity-direction.txt``), else from the dominant floor plane of the mesh and the cameras' up vote.

The objects item writes ``RUN/ingest/objects/obj_XXXXXX.npz`` + ``library.json`` (:mod:`pipeline.objects`).

Later stages read these through :mod:`pipeline.runfolder`. A built-in scan (``builtin:demo``) is generated
when the run folder is created (:func:`pipeline.cli.init_run_dir`); ingest reads it like any folder.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import warnings
from pathlib import Path

import numpy as np

from pipeline.config import BUILTIN_PREFIX, Config
from pipeline.errors import InputError
from pipeline.io import atomic_write_bytes
from pipeline.registration import register_scan, registration_figures
from pipeline.runfolder import RESERVED_SCENES, ROOM_PLY, builtin_scan_dir, save_scan
from pipeline.scanformats.common import BadFrameWarning, IngestWarning, read_color, select_frames, subsample
from pipeline.scanformats.mesh import canonical_order, check_mesh_seen_by_cameras, load_mesh_file, ply_bytes
from pipeline.stages import INPUT_PROBLEMS, Item, Stage, StageContext
from pipeline.types import Scan

log = logging.getLogger(__name__)

__all__ = ["STAGE", "ingest_scan", "scene_names"]

OBJECTS_KEY = "objects"


# ---------------------------------------------------------------------------------------------------
# Names
# ---------------------------------------------------------------------------------------------------

def scene_names(paths: tuple[str, ...] | list[str]) -> list[str]:
    """Folder-safe, unique scene names for the entries of ``scan.paths`` (in order).

    The folder's name (``builtin:demo`` -> ``demo``), with characters other than letters, digits, ``-``,
    ``_`` and ``.`` replaced by ``_``; repeated names get ``-2``, ``-3``...; reserved names (``objects``)
    get a ``-scan`` suffix.
    """
    bases = []
    for p in paths:
        base = p[len(BUILTIN_PREFIX):] if p.startswith(BUILTIN_PREFIX) else Path(p.rstrip("/\\")).name
        base = re.sub(r"[^A-Za-z0-9_.-]", "_", base).strip(".") or "scan"
        bases.append(base + "-scan" if base in RESERVED_SCENES else base)
    return unique_names(bases)


def unique_names(bases: list[str]) -> list[str]:
    """``bases`` with repeated names made unique by ``-2``, ``-3``... (in order)."""
    out: list[str] = []
    for base in bases:
        name, k = base, 2
        while name in out:
            name, k = f"{base}-{k}", k + 1
        out.append(name)
    return out


# ---------------------------------------------------------------------------------------------------
# One scan
# ---------------------------------------------------------------------------------------------------

def room_mesh_for(scan: Scan, cfg: Config) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, str]:
    """The room mesh of ``scan``: its own (or ``scan.mesh`` from the config) converted, else reconstructed.

    Returns vertices (V, 3) float64 metres world frame, faces (T, 3) int32, colours (V, 3) uint8 or None,
    and a note saying where it came from.
    """
    src = cfg.scan.mesh or scan.mesh_path
    if src:
        try:
            V, F, C = load_mesh_file(src)
        except InputError as e:
            # transforms.json's ply_file_path is often a point cloud: reconstruct instead when possible
            optional = not cfg.scan.mesh and scan.meta.get("mesh_may_be_point_cloud")
            if not (optional and "no triangle faces" in str(e) and any(scan.depth_paths)):
                raise
            log.info("%s is not a triangle mesh; reconstructing from depth", src)
        else:
            check_mesh_seen_by_cameras(V, [scan.camera(i) for i in range(scan.num_frames)], src)
            V, F, C = canonical_order(V, F, C)
            return V, F, C, f"converted from {src}"
    if not any(scan.depth_paths):
        raise InputError(f"{scan.root}: the scan has no mesh and no depth maps to reconstruct one from; "
                         f"set scan.mesh to the room mesh file (metres, same world frame as the poses)")
    from pipeline.reconstruct import fuse_tsdf

    ic = cfg.ingest
    V, F, C = fuse_tsdf(scan, voxel=ic.tsdf_voxel, trunc=ic.tsdf_trunc, depth_max=ic.depth_max,
                        min_component_faces=ic.min_component_faces)
    return V, F, C, f"TSDF reconstruction (voxel {ic.tsdf_voxel} m, truncation {ic.tsdf_trunc} m)"


def readable_frames(scan: Scan) -> tuple[np.ndarray, list[str]]:
    """Decode every frame's colour image and depth map once; the frames that cannot be read are left out.

    A corrupt or wrongly sized image fails only its own frame: the scan goes on without it, and the
    returned problem (naming the file and the cause) is reported by the run (exit 1).

    Returns
    -------
    indices (N,) int64 of the readable frames, and one line per frame left out.
    """
    from pipeline.scanformats.common import read_depth_raw

    keep, problems = [], []
    for i in range(scan.num_frames):
        try:
            read_color(scan, i)
            if scan.depth_paths[i]:
                read_depth_raw(scan, i)
        except InputError as e:
            problems.append(f"frame {int(scan.frame_ids[i])} left out: {e}")
            log.error("%s: frame %d left out: %s", scan.root, int(scan.frame_ids[i]), e)
            continue
        keep.append(i)
    return np.asarray(keep, np.int64), problems


def color_camera(scan: Scan, cfg: Config) -> tuple[Scan, dict]:
    """The scan with the colour camera its data support (:func:`pipeline.registration.register_scan`),
    and the record for ``scan.json`` (empty when ``ingest.register_color = "off"``)."""
    if cfg.ingest.register_color == "off":
        return scan, {}
    scan, reg = register_scan(scan, frames=cfg.ingest.registration_frames)
    level = logging.WARNING if reg.get("misaligned") else logging.INFO
    log.log(level, "%s: %s", scan.root, reg["note"])
    return scan, reg


def ingest_scan(path: str | Path, name: str, out_dir: str | Path, cfg: Config, frame: int | None = None) -> Scan:
    """Read one scan folder, build its room mesh and up direction, write them to ``out_dir``.

    Parameters
    ----------
    path : scan folder.
    name : scene name (folder-safe).
    out_dir : ``RUN/ingest/<name>``.
    cfg : the run's configuration (``scan`` and ``ingest`` tables).
    frame : one image of a BOP scene without world poses (:func:`pipeline.scanformats.detect.scan_units`).

    Returns
    -------
    The :class:`Scan` as :func:`load_scan` will read it back.
    """
    from pipeline.reconstruct import floor_up
    from pipeline.scanformats.detect import read_scan

    out_dir = Path(out_dir)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", IngestWarning)
        scan = read_scan(path, cfg.scan.format, frame)
    notes = [str(w.message) for w in caught if issubclass(w.category, IngestWarning)]
    broken = [str(w.message) for w in caught if issubclass(w.category, BadFrameWarning)]
    for w in caught:  # re-issue so callers (and pytest) see them; they are also kept in scan.json
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    n_read = scan.num_frames
    idx = subsample(n_read, cfg.scan.max_frames)
    scan = select_frames(scan, idx)
    ok, unreadable = readable_frames(scan)
    if not len(ok):
        raise InputError(f"{path}: none of the scan's {scan.num_frames} frames can be read (first: "
                         f"{unreadable[0]}); restore the frames")
    scan = select_frames(scan, ok)
    scan, reg = color_camera(scan, cfg)
    if reg.get("misaligned"):
        notes.append(f"{path}: depth and photos stay misaligned: median edge distance "
                     f"{reg['median_after_px']:.2f} px ({reg['note']})")
    V, F, C, mesh_note = room_mesh_for(scan, cfg)
    up_meta, up_info = scan.up_w, {}
    up_floor, up_info = floor_up(V, F, scan.T_c2w)
    if np.linalg.norm(up_meta) > 0.5:
        up = up_meta / np.linalg.norm(up_meta)
        source = scan.meta.get("up_source", "metadata")
        up_info["metadata_vs_floor_deg"] = float(np.degrees(np.arccos(np.clip(up @ up_floor, -1, 1))))
    else:
        up, source = up_floor, f"mesh: {up_info.get('method', 'floor plane')}"
    mesh_path = out_dir / ROOM_PLY
    atomic_write_bytes(mesh_path, ply_bytes(V, F, C))
    meta = dict(scan.meta)
    if reg:
        meta["registration"] = (reg["note"] if reg["source"] == "estimated"
                                else f"{meta.get('registration', 'as the format gives it')}; {reg['note']}")
        meta["color_registration"] = reg
        meta["registration_figures"] = registration_figures(reg)
    meta.update({"up_source": source, "up": up_info, "mesh": mesh_note, "frames_read": n_read,
                 "frames_kept": int(len(ok)), "frames_unreadable": broken + unreadable, "warnings": notes, "mesh_vertices": int(len(V)),
                 "mesh_faces": int(len(F))})
    scan = dataclasses.replace(scan, name=name, up_w=up.astype(np.float64), mesh_path=str(mesh_path.resolve()),
                               meta=meta)
    save_scan(out_dir, scan)
    return scan


# ---------------------------------------------------------------------------------------------------
# Stage
# ---------------------------------------------------------------------------------------------------

def plan(ctx: StageContext) -> list[Item]:
    """One item per scan: per entry of ``scan.paths``, or per image of a BOP scene without world poses
    (scene ``<name>-NNNNNN``, :func:`pipeline.scanformats.detect.scan_units`)."""
    from pipeline.scanformats.detect import scan_units

    units = [(n, p, u) for n, p in zip(scene_names(ctx.cfg.scan.paths), ctx.cfg.scan.paths)
             for u in ([None] if p.startswith(BUILTIN_PREFIX) else scan_units(p, ctx.cfg.scan.format))]
    keys = unique_names([n if u is None else f"{n}-{u:06d}" for n, _, u in units])
    items = [Item(key=k, data={"path": p} if u is None else {"path": p, "frame": int(u)})
             for k, (_, p, u) in zip(keys, units)]
    items.append(Item(key=OBJECTS_KEY, data={"paths": list(ctx.cfg.objects.paths)}))
    return items


def run_item(ctx: StageContext, item: Item) -> dict:
    if item.key == OBJECTS_KEY:
        from pipeline.objects import load_library, save_library

        problems: list[str] = []
        models = load_library(tuple(item.data["paths"]), ctx.cfg.objects.scale, problems=problems)
        save_library(ctx.stage_dir / OBJECTS_KEY, models)
        return {"objects": len(models), "ids": [m.obj_id for m in models], INPUT_PROBLEMS: problems}
    path = item.data["path"]
    if path.startswith(BUILTIN_PREFIX):
        path = str(builtin_scan_dir(ctx.run_dir, path[len(BUILTIN_PREFIX):]))
    scan = ingest_scan(path, item.key, ctx.stage_dir / item.key, ctx.cfg, frame=item.data.get("frame"))
    return {"scene": scan.name, "format": scan.format, "frames": scan.num_frames,
            "skipped": scan.meta.get("skipped", {}), "mesh": scan.meta["mesh"],
            "mesh_faces": scan.meta["mesh_faces"], "up_source": scan.meta["up_source"],
            "registration": scan.meta.get("registration", ""),
            INPUT_PROBLEMS: scan.meta["frames_unreadable"]}


STAGE = Stage("ingest", plan, run_item)
