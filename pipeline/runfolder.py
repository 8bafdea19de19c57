"""The run folder: every path a stage writes, the records one stage hands the next, one lister.

A stage reads another stage's output through this module only, never by importing that stage. The
path templates follow bop_toolkit's ``dataset_params`` ``*_tpath`` style: strings relative to the run
folder, filled with :func:`path` (or :meth:`FrameKey.path` for the per-frame ones)::

    RUN/ingest/<scene>/scan.json, frames.npz, room.ply      ingest: the scan (:func:`load_scan`)
    RUN/ingest/_builtin/<name>/                             a built-in scan, generated with the folder
    RUN/ingest/objects/                                     ingest: the object library
    RUN/select/<scene>/selection.json                       select: kept frames
    RUN/prep/<scene>/room_proxy.npz, room_trace.ply         prep: physics proxy, traced room mesh
    RUN/prep/objects/obj_<id:06d>.npz                       prep: object proxies
    RUN/simulate/<scene>/drop<NNNN>.json                    simulate: a placement
    RUN/raster/<scene>/drop<NNNN>/f<frame:06d>.json/.npz    raster: a frame (:class:`RasterFrame`)
    RUN/raster/<scene>/{scene,real}_depth/f<frame:06d>.npz  raster: per-frame caches shared by drops
    RUN/trace/<scene>/drop<NNNN>/f<frame:06d>.npz           trace: the traced passes
    RUN/composite/<scene>/drop<NNNN>/f<frame:06d>.png       composite: the image (+ ``_depth.npz``)
    RUN/export/dataset/                                     export: BOP, COCO, YOLO
    RUN/{simulate,raster,export}/summary.json               the stage's counts and rejections, by reason
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pipeline.camera import Camera
from pipeline.errors import InputError, UserError
from pipeline.io import atomic_save_npz, atomic_write_json, load_npz, read_json
from pipeline.types import ObjectModel, Placement, Scan

# --- path templates (relative to the run folder) ---------------------------------------------------
SCAN_JSON, FRAMES_NPZ, ROOM_PLY = "scan.json", "frames.npz", "room.ply"   # files of an ingested scene
SCAN_TPATH = "ingest/{scene}/" + SCAN_JSON
FRAMES_TPATH = "ingest/{scene}/" + FRAMES_NPZ
BUILTIN_SCAN_TPATH = "ingest/_builtin/{name}"
OBJECTS_DIR = "ingest/objects"
SELECTION_TPATH = "select/{scene}/selection.json"
ROOM_PROXY_TPATH = "prep/{scene}/room_proxy.npz"
ROOM_TRACE_TPATH = "prep/{scene}/room_trace.ply"
OBJECT_PROXY_TPATH = "prep/objects/obj_{obj_id:06d}.npz"
DROP_TPATH = "{scene}/drop{drop:04d}"
PLACEMENT_TPATH = "simulate/" + DROP_TPATH + ".json"
FRAME_KEY_TPATH = DROP_TPATH + "/f{frame:06d}"
RASTER_TPATH = "raster/" + FRAME_KEY_TPATH           # + .json (every frame) / .npz (ok frames)
SCENE_DEPTH_TPATH = "raster/{scene}/scene_depth/f{frame:06d}.npz"
REAL_DEPTH_TPATH = "raster/{scene}/real_depth/f{frame:06d}.npz"
TRACE_TPATH = "trace/" + FRAME_KEY_TPATH + ".npz"
ROOM_LIGHTS_TPATH = "trace/{scene}/lights.npz"        # the fitted room lights (trace.lighting = "fit")
COMPOSITE_TPATH = "composite/" + FRAME_KEY_TPATH + ".png"
COMPOSITE_DEPTH_TPATH = "composite/" + FRAME_KEY_TPATH + "_depth.npz"
DATASET_DIR = "export/dataset"
SUMMARY_TPATH = "{stage}/summary.json"                 # a stage's counts and rejections (simulate, raster, export)

RESERVED_SCENES = {"objects", "_builtin", "_items"}   # names under ingest/ that are not scenes


def path(run_dir: str | Path, tpath: str, **fields) -> Path:
    """``RUN/<tpath filled with fields>``."""
    return Path(run_dir) / tpath.format(**fields)


def file_stamp(p: Path) -> tuple[str, int, int]:
    """(path, mtime ns, size) of a file, or (path, -1, -1) when it is missing: the key of a per-process
    cache of what is read from it, which changes when the file is rewritten."""
    try:
        st = p.stat()
    except FileNotFoundError:
        return str(p), -1, -1
    return str(p), st.st_mtime_ns, st.st_size


class FrameKey(NamedTuple):
    """One frame of one drop of one scene: the unit raster, trace, composite and export work on (a tuple, so
    it sorts and unpacks as ``(scene, drop, frame)``)."""

    scene: str
    drop: int
    frame: int   # index into the scene's Scan arrays

    def __str__(self) -> str:
        return FRAME_KEY_TPATH.format(scene=self.scene, drop=self.drop, frame=self.frame)

    def path(self, run_dir: str | Path, tpath: str) -> Path:
        return path(run_dir, tpath, scene=self.scene, drop=self.drop, frame=self.frame)


# --- ingest -----------------------------------------------------------------------------------------

def _relative(path: str, out_dir: Path) -> str:
    """``path`` relative to the scene folder when it lies inside the run folder (so run folders can move
    and equal runs give equal bytes), else unchanged (absolute)."""
    if not path:
        return path
    run_dir = out_dir.resolve().parent.parent
    p = Path(path).resolve()
    if p.is_relative_to(run_dir):
        return Path(os.path.relpath(p, out_dir.resolve())).as_posix()
    return path


def _absolute(path: str, out_dir: Path) -> str:
    if not path or Path(path).is_absolute():
        return path
    return os.path.normpath(out_dir.resolve() / path)


def save_scan(out_dir: str | Path, scan: Scan) -> None:
    """Write ``scan.json`` + ``frames.npz`` (the room mesh is written separately)."""
    out_dir = Path(out_dir)
    atomic_save_npz(out_dir / FRAMES_NPZ, frame_ids=scan.frame_ids.astype(np.int64),
                    K=scan.K.astype(np.float64), T_c2w=scan.T_c2w.astype(np.float64),
                    depth_K=scan.depth_K.astype(np.float64))
    rel = lambda p: _relative(p, out_dir)  # noqa: E731
    doc = {"name": scan.name, "root": rel(scan.root), "format": scan.format, "width": scan.width,
           "height": scan.height, "depth_width": scan.depth_width, "depth_height": scan.depth_height,
           "depth_scale": scan.depth_scale, "depth_registered": scan.depth_registered,
           "up_w": [float(x) for x in scan.up_w], "mesh_path": rel(scan.mesh_path),
           "color_paths": [rel(p) for p in scan.color_paths], "depth_paths": [rel(p) for p in scan.depth_paths],
           "num_frames": scan.num_frames, "meta": scan.meta,
           "units": "metres; poses camera-to-world, OpenCV camera axes; K at colour resolution"}
    atomic_write_json(out_dir / SCAN_JSON, doc)


BUILTIN_SCANS = ("demo", "tiny")


def builtin_scan_dir(run_dir: str | Path, name: str) -> Path:
    """The folder of built-in scan ``name`` (generated when the run folder was created)."""
    p = path(run_dir, BUILTIN_SCAN_TPATH, name=name)
    if not p.is_dir():
        raise UserError(f"{p} is missing: built-in scans are generated when the run folder is created; start the "
                        f"run with 'scansynth run CONFIG --out RUN' (or pass --config CONFIG to a stage command)")
    return p


def list_scenes(run_dir: str | Path) -> list[str]:
    """Names of the scenes ingested into ``run_dir`` (sorted)."""
    root = Path(run_dir) / "ingest"
    if not root.is_dir():
        return []
    return sorted(p.parent.name for p in root.glob(f"*/{SCAN_JSON}") if p.parent.name not in RESERVED_SCENES)


def load_scan(run_dir: str | Path, scene: str) -> Scan:
    """The :class:`Scan` that ingest wrote for ``scene``."""
    js = path(run_dir, SCAN_TPATH, scene=scene)
    if not js.is_file():
        raise UserError(f"{js} is missing: scene {scene!r} was not ingested into {run_dir}; "
                        f"run 'scansynth ingest {run_dir}' (scenes there: {', '.join(list_scenes(run_dir)) or 'none'})")
    d = js.parent
    doc = read_json(js)
    a = load_npz(d / FRAMES_NPZ)
    ab = lambda p: _absolute(p, d)  # noqa: E731
    return Scan(name=doc["name"], root=ab(doc["root"]), format=doc["format"], frame_ids=a["frame_ids"],
                color_paths=tuple(ab(p) for p in doc["color_paths"]),
                depth_paths=tuple(ab(p) for p in doc["depth_paths"]),
                width=int(doc["width"]), height=int(doc["height"]), K=a["K"], T_c2w=a["T_c2w"],
                depth_width=int(doc["depth_width"]), depth_height=int(doc["depth_height"]),
                depth_K=a["depth_K"], depth_scale=float(doc["depth_scale"]),
                depth_registered=bool(doc["depth_registered"]), up_w=np.asarray(doc["up_w"], dtype=np.float64),
                mesh_path=ab(doc["mesh_path"]), meta=doc["meta"])


def load_objects(run_dir: str | Path) -> list[ObjectModel]:
    """The normalised object library that ingest wrote (sorted by id)."""
    from pipeline.objects import load_saved_library

    return load_saved_library(Path(run_dir) / OBJECTS_DIR)


def load_room_mesh(scan: Scan) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The room mesh of an ingested scan: vertices (V, 3) float64 metres world frame, faces (T, 3) int32,
    vertex colours (V, 3) uint8 or None."""
    from pipeline.scanformats.mesh import read_room_ply

    if not Path(scan.mesh_path).is_file():
        raise UserError(f"{scan.mesh_path}: room mesh is missing; re-run 'scansynth ingest'")
    return read_room_ply(scan.mesh_path)


# --- select -----------------------------------------------------------------------------------------

def load_selection(run_dir: str | Path, scene: str) -> np.ndarray:
    """Kept frame indices ``(K,) int64`` ascending, written by the select stage (InputError when it has not
    run for ``scene``)."""
    p = path(run_dir, SELECTION_TPATH, scene=scene)
    if not p.is_file():
        raise InputError(f"{p} does not exist: run the select stage for scene {scene!r} first "
                         f"('scansynth select {run_dir}')")
    return np.asarray(read_json(p)["kept"], dtype=np.int64)


def frames_to_render(run_dir: str | Path, scan: Scan) -> list[int]:
    """The select stage's kept frames of ``scan``, or every frame when select has not written any."""
    if path(run_dir, SELECTION_TPATH, scene=scan.name).is_file():
        return [int(f) for f in load_selection(run_dir, scan.name)]
    return list(range(scan.num_frames))


# --- prep -------------------------------------------------------------------------------------------

def _load_proxy(p: Path) -> dict[str, np.ndarray]:
    if not p.is_file():
        raise UserError(f"{p}: {'room' if 'room' in p.name else 'object'} proxy is missing; run the 'prep' "
                        f"stage first")
    return load_npz(p)


def load_object_proxy(run_dir: str | Path, obj_id: int) -> dict[str, np.ndarray]:
    """The object proxy NPZ of ``obj_id`` as a dict of arrays."""
    return _load_proxy(path(run_dir, OBJECT_PROXY_TPATH, obj_id=obj_id))


def room_trace_mesh(run_dir: str | Path, scan: Scan, which: str = "prep") -> str:
    """The room mesh to trace: prep's simplified mesh when present and ``which == "prep"``, else the
    ingest mesh."""
    p = path(run_dir, ROOM_TRACE_TPATH, scene=scan.name)
    return str(p) if which == "prep" and p.is_file() else scan.mesh_path


# --- simulate ---------------------------------------------------------------------------------------

_DROP_RE = re.compile(r"^drop(\d+)\.json$")


def placement_to_dict(p: Placement) -> dict:
    """JSON-able dict of a placement (floats written with round-trip precision)."""
    return {"scene": p.scene, "drop": int(p.drop), "obj_ids": np.asarray(p.obj_ids).astype(int).tolist(),
            "R_m2w": np.asarray(p.R_m2w, float).tolist(), "t_m2w": np.asarray(p.t_m2w, float).tolist(),
            "at_rest": np.asarray(p.at_rest, bool).tolist(), "max_penetration": float(p.max_penetration),
            "verdict": p.verdict}


def save_placement(p: str | Path, placement: Placement, *, extra: dict | None = None) -> Path:
    """Write a placement as JSON, atomically (``extra`` adds keys, e.g. simulated seconds)."""
    doc = placement_to_dict(placement)
    if extra:
        doc.update({f"sim_{k}": v for k, v in extra.items()})
    return atomic_write_json(p, doc)


def read_placement(p: str | Path) -> Placement:
    """Read a placement JSON written by :func:`save_placement`."""
    p = Path(p)
    if not p.is_file():
        raise UserError(f"{p}: placement is missing; run the 'simulate' stage first")
    d = read_json(p)
    try:
        n = len(d["obj_ids"])
        return Placement(scene=str(d["scene"]), drop=int(d["drop"]),
                         obj_ids=np.asarray(d["obj_ids"], np.int32).reshape(n),
                         R_m2w=np.asarray(d["R_m2w"], np.float64).reshape(n, 3, 3),
                         t_m2w=np.asarray(d["t_m2w"], np.float64).reshape(n, 3),
                         at_rest=np.asarray(d["at_rest"], bool).reshape(n),
                         max_penetration=float(d["max_penetration"]), verdict=str(d["verdict"]))
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{p}: not a placement file ({e}); re-run the 'simulate' stage") from None


def load_placement(run_dir: str | Path, scene: str, drop: int) -> Placement:
    return read_placement(path(run_dir, PLACEMENT_TPATH, scene=scene, drop=drop))


def simulated_drops(run_dir: str | Path, scene: str) -> list[int]:
    """Drop indices the simulate stage wrote for ``scene`` (sorted)."""
    d = Path(run_dir) / "simulate" / scene
    if not d.is_dir():
        return []
    return sorted(int(m.group(1)) for p in d.iterdir() if (m := _DROP_RE.match(p.name)))


# --- raster -----------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RasterInstance:
    """One instance of a raster frame: its poses and the annotation record raster wrote (metres)."""

    obj_id: int
    R_m2c: np.ndarray   # (3, 3) float64
    t_m2c: np.ndarray   # (3,) float64, metres
    R_m2w: np.ndarray   # (3, 3) float64
    t_m2w: np.ndarray   # (3,) float64, metres
    annotation: dict    # boxes, pixel counts, visible fraction... (pipeline.annotate)


@dataclass(frozen=True)
class RasterFrame:
    """What the raster stage hands trace, composite and export for one frame."""

    key: FrameKey
    stem: Path                       # RUN/raster/<scene>/drop<NNNN>/f<frame:06d> (+ .json / .npz)
    status: str                      # "ok" | "rejected"
    reason: str                      # why rejected ("" when ok)
    camera: Camera                   # the render camera (K at the render resolution)
    instances: tuple[RasterInstance, ...]
    doc: dict                        # the frame's JSON document as written

    def arrays(self, masks: bool = True) -> dict[str, np.ndarray]:
        """The frame's passes: ``depth`` (H, W) float32 metres, ``labels`` (H, W) uint16, ``written_depth``
        (H, W) float32 metres (the dataset's depth) and, with ``masks``, ``amodal`` and ``visib`` (N, H, W)
        bool."""
        from pipeline import annotate

        if self.status != "ok":
            raise InputError(f"{self.stem}.json: frame status is {self.status!r}, not ok; re-run raster")
        a = load_npz(self.stem.with_suffix(".npz"))
        missing = sorted({"visib", "written_depth"} - set(a) - (set() if masks else {"visib"}))
        if missing:
            raise InputError(f"{self.stem}.npz has no {' or '.join(missing)}: it was written by an older "
                             f"scansynth (before visibility followed bop_toolkit's rule); delete "
                             f"{self.stem.parent.parent.parent} and run again from the raster stage")
        if masks:
            a["amodal"] = annotate.unpack_masks(a["amodal"], self.camera.width)
            a["visib"] = annotate.unpack_masks(a["visib"], self.camera.width)
        return a


def read_raster_frame(stem: str | Path) -> RasterFrame:
    """The raster frame saved at ``stem`` (its JSON; the passes load with :meth:`RasterFrame.arrays`)."""
    stem = Path(stem)
    doc = read_json(stem.with_suffix(".json"))
    T_c2w = np.asarray(doc["T_c2w"], np.float64)
    cam = Camera(K=np.asarray(doc["K"], np.float64), T_c2w=T_c2w, width=int(doc["width"]),
                 height=int(doc["height"]))
    try:
        insts = tuple(RasterInstance(obj_id=int(a["obj_id"]), R_m2c=np.asarray(a["R_m2c"], np.float64),
                                     t_m2c=np.asarray(a["t_m2c"], np.float64),
                                     R_m2w=np.asarray(a["R_m2w"], np.float64),
                                     t_m2w=np.asarray(a["t_m2w"], np.float64), annotation=a)
                      for a in doc.get("instances", []))
    except KeyError as e:
        raise InputError(f"{stem}.json: instance without {e}: it was written by an older scansynth; delete "
                         f"{stem.parent.parent.parent} and run again from the raster stage") from None
    key = _frame_key(stem) or FrameKey(str(doc.get("scene", "")), int(doc.get("drop", 0)), int(doc.get("frame", 0)))
    return RasterFrame(key=key, stem=stem,
                       status=doc["status"], reason=doc.get("reason", ""), camera=cam, instances=insts,
                       doc=doc)


def load_raster_frame(run_dir: str | Path, key: FrameKey) -> RasterFrame:
    """The raster frame ``key`` of the run (see :func:`read_raster_frame`)."""
    return read_raster_frame(key.path(run_dir, RASTER_TPATH))


def _frame_key(stem: Path) -> FrameKey | None:
    """The key of ``RUN/raster/<scene>/drop<NNNN>/f<frame:06d>`` (None for another name)."""
    try:
        return FrameKey(stem.parent.parent.name, int(stem.parent.name.removeprefix("drop")),
                        int(stem.name.removeprefix("f")))
    except ValueError:
        return None


def raster_frames(run_dir: str | Path) -> list[FrameKey]:
    """Every raster frame with status ok, sorted: the one list trace, composite and export work through."""
    root = Path(run_dir) / "raster"
    out = []
    for p in sorted(root.glob("*/drop*/f*.json")) if root.is_dir() else ():
        key = _frame_key(p.with_suffix(""))
        if key is None or not p.with_suffix(".npz").is_file() or read_json(p).get("status") != "ok":
            continue
        out.append(key)
    return sorted(out)


# --- trace ------------------------------------------------------------------------------------------

def load_trace(run_dir: str | Path, key: FrameKey) -> dict[str, np.ndarray]:
    """The arrays the trace stage wrote for a frame (see :mod:`pipeline.trace.stage`)."""
    p = key.path(run_dir, TRACE_TPATH)
    if not p.is_file():
        raise InputError(f"{p} is missing: run 'scansynth trace' first")
    return load_npz(p)
