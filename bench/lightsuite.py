"""Independent ground-truth suite: six procedural rooms under the light set-ups real rooms have (and a seventh
for tuning only, :data:`DEV_ROOMS`), written as 7-Scenes scans, with the true images of the same rooms with LM-O
objects at known poses, all path-traced by Mitsuba 3.

Run: ``nice -n 10 .venv/bin/python -m bench.lightsuite --out bench/cache/lightsuite [--rooms a,b] [--spp N]
[--tiny]``. Generated once and cached: a room with ``OUT/<room>/done.json`` (written last) is skipped, an
unfinished one resumes at its first unfinished frame (``plan.json`` keeps its poses, objects and exposure;
with other parameters it starts again; a complete one is only rendered again with ``--rebuild``). The tests call :func:`build_suite` with :data:`TINY` (2 rooms, 2 frames
at 160x120: seconds).

What it builds, per room (:data:`ROOMS`, one light set-up each):

- a 4 x 5 x 2.6 m box room (world: z up, metres), a table (1.2 x 0.8 m top at 0.75 m, four legs) near the
  middle, a shelf, a cabinet and a cardboard box that cast shadows; Lambertian surfaces (``diffuse``, two-
  sided) with the scan generator's procedural textures as bitmaps, albedo clipped to 0.05-0.85;
- the emitters (one-sided rectangles, constant radiance each): ``ceiling`` three warm ceiling panels no photo
  sees; ``lamp_in_view`` a wall panel behind the table, seen and clipped in the photos, and a ceiling fill;
  ``window`` a cool 1.5 x 1 m window on a side wall, no ceiling lamp; ``spot`` a 10 cm square light 1.2 m
  above the table (hard shadows) with a weak ceiling fill, metered lower (:data:`LEVEL_SPOT`) so that the
  objects under it do not clip; ``coloured_walls`` deep red and green walls under white ceiling panels;
  ``dim`` one small lamp, exposed to a mean sRGB code of ~50; for tuning only (:data:`DEV_ROOMS`, built when
  asked for, never in the headline) ``coloured_dev``: yellow, blue and teal walls under two white ceiling
  panels placed elsewhere;
- 8 cameras (640x480, fx = fy = 525, cx = 319.5, cy = 239.5) on an arc around the table (1.4-2.2 m away,
  1.3-1.7 m high, looking at the table with jitter); the ceiling is never in view (checked analytically);
- three LM-O models (mm -> m; :data:`OBJ_IDS`) standing on the table top (lowest vertex on it, random yaw,
  footprints apart, each >= 40 % visible in every frame), material :data:`OBJECT_BSDF` (Mitsuba
  ``principled``: the vertex colours sRGB -> linear as base colour, metallic 0, roughness 0.5, specular 0.5,
  i.e. F0 = 0.04: the pipeline's default object material).

Files (``OUT/<room>/``)::

    scan/                       the room WITHOUT objects, 7-Scenes layout (pipeline.scanformats.sevenscenes)
      frames/frame-XXXXXX.color.png   8-bit sRGB of (Mitsuba radiance x exposure), values > 1 clipped
      frames/frame-XXXXXX.depth.png   uint16 mm z-depth (exact: ray cast at pixel centres), 0 = none
      frames/frame-XXXXXX.pose.txt    4x4 camera-to-world, OpenCV camera axes
      camera-intrinsics.txt, gravity-direction.txt (0 0 -1)
    truth/
      frame-XXXXXX.png          the same view WITH the objects, same exposure and encoding
      frame-XXXXXX.photo.npy    (H, W, 3) float16 linear photo (after exposure, before clipping)
      frame-XXXXXX.truth.npy    (H, W, 3) float16 linear truth (idem)
      frame-XXXXXX.mask.png     uint8 instance index at pixel centres: k = objects.json[k - 1], 0 = none
      frame-XXXXXX.renders.npz  float16 crop pair (photo_crop, truth_crop), beta, object boxes (boxK, boxK_rect)
      frame-XXXXXX.json         crop, object boxes, seeds, seconds, emitter and object pixels, mean level
      frame-000000.rerender.png/.npy  frame 0's truth rendered again with other seeds (the noise ceiling)
      noise_ceiling.json        PSNR of truth vs rerender over object pixels and the crop's background
      objects.json              [{"obj_id", "model" (path, mm), "R_m2w" 3x3, "t_m2w" metres}]
      lights.json               [{"name", "type": "area", "shape": "rectangle", "one_sided", "corners" 4x3,
                                  "normal", "centre", "area_m2", "radiance" (RGB given to Mitsuba),
                                  "radiance_photo" (= exposure x radiance), "note", "frames_visible"}]
      room.json                 exposure, spp, sampler, integrator, seeds, K, materials (texture, mean
                                linear albedo), object BSDF, seconds per frame, noise ceiling, frames_info
    mitsuba/                    the PLYs and textures Mitsuba read
    plan.json, done.json

How the truth is rendered (the budget: ~50 min for 48 frames on 2 cores): the photo is a full-frame render
of the empty room at :data:`SPP_PHOTO`. The truth equals the photo outside a crop window holding the
objects, their shadows on the table top (objects projected from every emitter corner) and a margin of
>= :data:`CROP_MARGIN` px. Inside it, the crop is rendered twice at :data:`SPP_CROP` with the same seed, with
and without the objects (one scene, the objects moved out of the room in between: Mitsuba then traces the
same paths until one meets an object, so the difference is the objects' effect with little noise);
background pixels are ``with + beta (photo - without)``, beta = the local shadow ratio from the neighbouring
pixels (1 where the objects change nothing: the truth is the photo plus the difference; towards 0 in their
shadows), unbiased for any beta independent of the pixel's own samples (:func:`truth_image`). Object pixels
(pixel centre on an object) come from an independent render of tight boxes at :data:`SPP_OBJECTS`. Rare
negative sums are clipped to 0 and counted. The ``multijitter`` sampler (stratified per sample) keeps paths
in step after one diverges and has about half the variance of ``independent`` here. The renders are kept
(``frame-XXXXXX.renders.npz``) so that the truth can be recomposed without rendering.

Not bit-reproducible: Mitsuba's multi-threaded ``scalar_rgb`` rendering gives other Monte Carlo noise from
one generation to the next with the same seeds (the tiny suite twice: exposures 1.1252 and 1.1280, photos
0.24 % apart on average; block scheduling across threads is the likely cause, as reported upstream for
Mitsuba 0.6, mitsuba-renderer/mitsuba issue 184; not checked further). Statistically the same suite, but
the pipeline's light fit reads that noise: two generations of the full suite give the same code's fit objects
PSNR up to 1.4 dB apart in a room at run seed 0. Compare variants on one cached suite, as bench/lighting.py does
(each room's render fingerprint, ``render`` in its results, says which generation a figure is on).

Why it is independent of our tracer: Mitsuba 3 (``scalar_rgb``, ``path`` integrator, max_depth
:data:`MAX_DEPTH`) renders every image from the geometry, materials and emitters defined here, not from the
scan mesh, photos or lights the pipeline estimates; depth and masks come from Open3D ray casting, not from
the pipeline's rasterizer; object models are parsed here. The pipeline sees only ``scan/`` (as a real
7-Scenes scan, mesh reconstructed by its ingest) and the object poses.

What it does not show: camera effects (no blur, sensor noise model, vignetting or tone curve other than
sRGB; depth without sensor noise or holes), glossy room surfaces, clutter, real materials (the objects
carry the pipeline's default material: the suite measures lighting and compositing, not material
estimation). The truth carries Monte Carlo noise (``noise_ceiling`` in ``room.json``); the photos carry
more (:data:`SPP_PHOTO`), as a real photo carries sensor noise.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tests.support.reference import masked_psnr, raycast
from pipeline.color import encode_u8, srgb_to_linear
from pipeline.geometry import look_at
from pipeline.io import atomic_write_bytes, atomic_write_image, atomic_write_json

log = logging.getLogger("bench.lightsuite")

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
LMO = SHARED_DATA / "objects" / "lmo" / "models"

ROOMS = ("ceiling", "lamp_in_view", "window", "spot", "coloured_walls", "dim")
# rooms for tuning only, never in the headline: the tuned half of ROOMS has no room whose walls are strongly
# coloured, so nothing tuned on it could be checked on the albedo / illumination ambiguity but on a held-out room
DEV_ROOMS = ("coloured_dev",)

OBJ_IDS = (1, 5, 9)            # ape (brown), watering can (white/grey), duck (yellow)
WIDTH, HEIGHT = 640, 480
FX = FY = 525.0                # at 640x480; scaled with the width for smaller images
FRAMES = 8
ROOM_SIZE = (4.0, 5.0, 2.6)    # interior x, y, z (metres)
TABLE_CENTRE = (2.0, 2.7)
TABLE_SIZE = (1.2, 0.8)        # top x, y
TABLE_HEIGHT = 0.75            # top surface z
MAX_DEPTH = 7                  # Mitsuba path length (camera segment included): 6 bounces
CROP_MARGIN = 32               # px at 640x480 (scaled with the width)
SPP_PHOTO = 16                 # defaults for the full suite (chosen from measured seconds per frame)
SPP_CROP = 36                  # the truth's crop pair (room with and without the objects)
SPP_OBJECTS = 784              # the truth's object pixels (tight boxes)
# What the tests render: build_suite(out, rooms=("ceiling", "spot"), **TINY) takes seconds.
TINY = {"frames": 2, "width": 160, "height": 120, "spp": 4, "spp_crop": 16, "spp_objects": 144, "texture_size": 64}
VERSION = 2                    # bump when the rendering changes: cached rooms are then rendered again
SPP_EXPOSURE = 16              # pre-pass for the room's exposure (quarter resolution, 4 frames)
LEVEL = 105.0                  # target mean 8-bit sRGB code of the photos (sets each room's exposure)
LEVEL_DIM = 50.0
LEVEL_SPOT = 72.0              # metered lower, as a camera metering the lit table would: the objects stay unclipped
SEED = 2024
SAMPLER = "multijitter"        # stratified: ~2x less variance than "independent" here; per-sample
                               # seeding keeps paths of two renders in step after one of them diverges

# The object material: the pipeline's default object material as Mitsuba's principled BSDF. One place, so
# that it can change with the pipeline's BSDF.
OBJECT_BSDF = {"type": "principled",
               "base_color": {"type": "mesh_attribute", "name": "vertex_color"},
               "metallic": 0.0, "roughness": 0.5, "specular": 0.5}

WARM = np.array([1.0, 0.86, 0.70])
NEUTRAL = np.array([1.0, 0.97, 0.92])
COOL = np.array([0.72, 0.85, 1.0])


# ---------------------------------------------------------------------------------------------------
# Room description
# ---------------------------------------------------------------------------------------------------

@dataclass
class Surface:
    """A set of rectangles of one diffuse material. Each rectangle: origin o, edges a, b (a x b = normal,
    towards the room's air side)."""

    name: str
    quads: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    kind: str                       # texture kind of pipeline.synthscan.textures (or "plain")
    base: tuple[float, float, float]  # linear mean albedo asked of the texture
    metres_per_repeat: float = 1.0


@dataclass
class Emitter:
    """A one-sided Lambertian rectangle: corners c0..c3 in order; emits along ``normal``."""

    name: str
    corners: np.ndarray             # (4, 3)
    normal: np.ndarray              # (3,)
    radiance: np.ndarray            # (3,) linear RGB given to Mitsuba
    note: str = ""

    @property
    def area(self) -> float:
        return float(np.linalg.norm(np.cross(self.corners[1] - self.corners[0], self.corners[3] - self.corners[0])))

    @property
    def centre(self) -> np.ndarray:
        return self.corners.mean(axis=0)


@dataclass
class RoomSpec:
    name: str
    surfaces: list[Surface]
    emitters: list[Emitter]
    level: float                    # target mean sRGB code of the photos (sets the exposure)
    white_balance: bool = False     # the camera's grey-world white balance on the photos and the truth


def _box(centre, size) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Axis-aligned box as six outward rectangles (a x b = outward normal)."""
    c = np.asarray(centre, float)
    sx, sy, sz = (float(s) for s in size)
    ex, ey, ez = np.eye(3) * [[sx], [sy], [sz]]
    lo = c - 0.5 * (ex + ey + ez)
    return [(lo, ey, ex), (lo + ez, ex, ey), (lo, ex, ez), (lo + ey, ez, ex), (lo, ez, ey), (lo + ex, ey, ez)]


def _rect(centre, u, v) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rectangle with centre, full edges u, v (u x v = normal)."""
    c, u, v = (np.asarray(x, float) for x in (centre, u, v))
    return c - 0.5 * u - 0.5 * v, u, v


def _panel(name, centre, u, v, radiance, note="") -> Emitter:
    o, a, b = _rect(centre, u, v)
    corners = np.stack([o, o + a, o + a + b, o + b])
    n = np.cross(a, b)
    return Emitter(name, corners, n / np.linalg.norm(n), np.asarray(radiance, float), note)


def room_list(text: str, default=ROOMS) -> list[str]:
    """The rooms of a ``--rooms a, b`` option (``default`` when empty); spaces around the names dropped."""
    return [r.strip() for r in (text.split(",") if text else default) if r.strip()]


def tuning_rooms_need_out(rooms, out, example: str) -> str | None:
    """Why a run on ``rooms`` may not write to the default results (``out`` empty): the tuning-only rooms
    (:data:`DEV_ROOMS`) stay out of the headline; ``example`` an --out to suggest. None when it may."""
    dev = sorted(set(rooms) & set(DEV_ROOMS))
    if out or not dev:
        return None
    return (f"{', '.join(dev)} is for tuning only and stays out of the headline results: give --out, e.g. "
            f"--out {example}")


def room_spec(name: str) -> RoomSpec:
    """Geometry, materials and emitters of room ``name`` (one of :data:`ROOMS` or :data:`DEV_ROOMS`)."""
    if name not in ROOMS + DEV_ROOMS:
        raise ValueError(f"unknown room {name!r}; choose from {', '.join(ROOMS + DEV_ROOMS)}")
    X, Y, Z = ROOM_SIZE
    ex, ey, ez = np.eye(3)
    walls = {"x0": (0.62, 0.60, 0.55), "x1": (0.62, 0.60, 0.55), "y0": (0.62, 0.60, 0.55), "y1": (0.55, 0.58, 0.60)}
    if name == "coloured_walls":
        walls = {"x0": (0.60, 0.07, 0.06), "x1": (0.07, 0.42, 0.09), "y0": (0.62, 0.60, 0.55), "y1": (0.60, 0.07, 0.06)}
    elif name == "coloured_dev":   # other hues, other places, and other lamps than coloured_walls
        walls = {"x0": (0.58, 0.46, 0.07), "x1": (0.08, 0.15, 0.50), "y0": (0.62, 0.60, 0.55), "y1": (0.07, 0.38, 0.33)}
    tx, ty = TABLE_CENTRE
    top_t, leg = 0.04, 0.05
    legs = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            c = (tx + sx * (TABLE_SIZE[0] / 2 - 0.06), ty + sy * (TABLE_SIZE[1] / 2 - 0.06), (TABLE_HEIGHT - top_t) / 2)
            legs += _box(c, (leg, leg, TABLE_HEIGHT - top_t))
    surfaces = [
        Surface("floor", [(np.zeros(3), X * ex, Y * ey)], "tiles", (0.45, 0.42, 0.38), 0.6),
        Surface("ceiling", [(np.array([0, 0, Z]), Y * ey, X * ex)], "paint", (0.80, 0.80, 0.78), 1.0),
        Surface("wall_x0", [(np.zeros(3), Y * ey, Z * ez)], "paint", walls["x0"], 1.0),
        Surface("wall_x1", [(np.array([X, 0, 0]), Z * ez, Y * ey)], "paint", walls["x1"], 1.0),
        Surface("wall_y0", [(np.zeros(3), Z * ez, X * ex)], "paint", walls["y0"], 1.0),
        Surface("wall_y1", [(np.array([0, Y, 0]), X * ex, Z * ez)], "paint", walls["y1"], 1.0),
        Surface("table_top", _box((tx, ty, TABLE_HEIGHT - top_t / 2), (*TABLE_SIZE, top_t)), "wood",
                (0.42, 0.26, 0.14), 0.8),
        Surface("table_legs", legs, "plain", (0.25, 0.15, 0.08)),
        Surface("shelf", _box((0.85, Y - 0.21, 0.9), (1.1, 0.40, 1.8)), "wood", (0.55, 0.42, 0.28), 0.6),
        Surface("cabinet", _box((0.26, 3.4, 0.45), (0.50, 1.0, 0.9)), "paint", (0.75, 0.75, 0.72), 1.0),
        Surface("box", _box((3.45, 4.0, 0.25), (0.6, 0.6, 0.5)), "cardboard", (0.45, 0.30, 0.15), 0.6),
    ]
    zc = Z - 0.005                           # ceiling panels 5 mm below the ceiling, facing down
    down_u, down_v = 0.6 * ey, 0.6 * ex      # ey x ex = -z
    emitters: list[Emitter]
    level = LEVEL
    if name == "ceiling":
        emitters = [_panel(f"ceiling_{i}", (x, y, zc), down_u, down_v, 12.0 * WARM,
                           "ceiling panel 0.6 x 0.6 m, warm white")
                    for i, (x, y) in enumerate([(1.3, 1.8), (2.8, 2.9), (1.6, 4.1)])]
    elif name == "lamp_in_view":
        emitters = [_panel("wall_panel", (2.35, Y - 0.005, 1.45), 0.5 * ex, 0.8 * ez, 40.0 * WARM,
                           "wall panel 0.5 x 0.8 m behind the table, facing -y, seen and clipped"),
                    _panel("ceiling_fill", (2.0, 2.0, zc), down_u, down_v, 5.0 * NEUTRAL, "ceiling panel, neutral")]
    elif name == "window":
        emitters = [_panel("window", (X - 0.005, 2.6, 1.7), 1.0 * ez, 1.5 * ey, 30.0 * COOL,
                           "window 1.5 (y) x 1 (z) m on wall x = 4, facing -x, cool daylight")]
    elif name == "spot":
        level = LEVEL_SPOT
        emitters = [_panel("spot", (tx, ty, TABLE_HEIGHT + 1.2), 0.1 * ey, 0.1 * ex, 1500.0 * NEUTRAL,
                           "10 cm square light 1.2 m above the table, facing down: hard shadows"),
                    _panel("ceiling_fill", (2.0, 1.5, zc), 1.0 * ey, 1.0 * ex, 1.0 * NEUTRAL, "weak ceiling fill")]
    elif name in ("coloured_walls", "coloured_dev"):
        places = [(1.5, 2.0), (2.5, 3.6)] if name == "coloured_walls" else [(1.2, 3.3), (2.9, 1.9)]
        emitters = [_panel(f"ceiling_{i}", (x, y, zc), down_u, down_v, 12.0 * NEUTRAL, "ceiling panel, white")
                    for i, (x, y) in enumerate(places)]
    else:  # dim
        emitters = [_panel("ceiling_small", (2.6, 3.6, zc), 0.3 * ey, 0.3 * ex, 10.0 * WARM, "small warm ceiling lamp")]
        level = LEVEL_DIM
    for e in emitters:  # every emitter's corners must turn around its normal
        n = np.cross(e.corners[1] - e.corners[0], e.corners[3] - e.corners[0])
        assert np.dot(n, e.normal) > 0, e.name
    return RoomSpec(name, surfaces, emitters, level)


# ---------------------------------------------------------------------------------------------------
# Meshes and files
# ---------------------------------------------------------------------------------------------------

def quads_mesh(quads, metres_per_repeat: float = 1.0):
    """Two triangles per rectangle: vertices (4Q, 3), normals, uv (metres / repeat), faces (2Q, 3)."""
    V, N, UV, F = [], [], [], []
    for k, (o, a, b) in enumerate(quads):
        V.append(np.stack([o, o + a, o + a + b, o + b]))
        n = np.cross(a, b)
        N.append(np.tile(n / np.linalg.norm(n), (4, 1)))
        la, lb = np.linalg.norm(a) / metres_per_repeat, np.linalg.norm(b) / metres_per_repeat
        UV.append(np.array([[0, 0], [la, 0], [la, lb], [0, lb]], float))
        F.append(np.array([[0, 1, 2], [0, 2, 3]]) + 4 * k)
    return np.concatenate(V), np.concatenate(N), np.concatenate(UV), np.concatenate(F)


def write_ply(path: Path, v: np.ndarray, f: np.ndarray, n: np.ndarray | None = None, uv: np.ndarray | None = None,
              rgb: np.ndarray | None = None) -> str:
    """Binary PLY for Mitsuba: float positions, optional normals, uv, RGB float colours in [0, 1]."""
    cols, names = [np.asarray(v, np.float32)], ["x", "y", "z"]
    if n is not None:
        cols.append(np.asarray(n, np.float32))
        names += ["nx", "ny", "nz"]
    if uv is not None:
        cols.append(np.asarray(uv, np.float32))
        names += ["u", "v"]
    if rgb is not None:
        cols.append(np.asarray(rgb, np.float32))
        names += ["r", "g", "b"]
    head = ["ply", "format binary_little_endian 1.0", f"element vertex {len(v)}"]
    head += [f"property float {c}" for c in names]
    head += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    face = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", 3)])
    face["n"] = 3
    face["i"] = f
    path.write_bytes(("\n".join(head) + "\n").encode() + np.concatenate(cols, axis=1).astype("<f4").tobytes()
                     + face.tobytes())
    return str(path)


def read_model(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A BOP model PLY (mm): vertices (V, 3) metres, faces (T, 3), normals (V, 3) or None, colours (V, 3) uint8.

    Parsed here (ASCII, as the LM-O files are; trimesh for binary), not by the pipeline's loader."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header") + len(b"end_header\n")
    header = raw[:end].decode("ascii").splitlines()
    if "format ascii 1.0" not in header:
        import trimesh

        m = trimesh.load(path, process=False)
        vc = np.asarray(m.visual.vertex_colors)[:, :3]
        return (np.asarray(m.vertices) / 1000.0, np.asarray(m.faces), np.asarray(m.vertex_normals), vc)
    nv = nf = 0
    props = []
    elem = None
    for line in header:
        p = line.split()
        if p[:1] == ["element"]:
            elem = p[1]
            if elem == "vertex":
                nv = int(p[2])
            elif elem == "face":
                nf = int(p[2])
        elif p[:1] == ["property"] and elem == "vertex":
            props.append(p[-1])
    lines = raw[end:].decode("ascii").split("\n")
    vert = np.array([ln.split() for ln in lines[:nv]], np.float64)
    faces = np.array([ln.split()[1:4] for ln in lines[nv:nv + nf]], np.int64)
    col = {p: i for i, p in enumerate(props)}
    V = vert[:, [col["x"], col["y"], col["z"]]] / 1000.0
    N = vert[:, [col["nx"], col["ny"], col["nz"]]] if "nx" in col else None
    C = vert[:, [col["red"], col["green"], col["blue"]]].astype(np.uint8)
    return V, faces, N, C


# ---------------------------------------------------------------------------------------------------
# Cameras and objects
# ---------------------------------------------------------------------------------------------------

def intrinsics(width: int, height: int) -> np.ndarray:
    s = width / WIDTH
    return np.array([[FX * s, 0, (width - 1) / 2], [0, FY * s, (height - 1) / 2], [0, 0, 1.0]])


def _ray_box_t(o, d):
    """Distance along unit rays d from o (inside the room box) to the box's walls; returns t and the hit face
    index (0/1: x walls, 2/3: y walls, 4: floor, 5: ceiling)."""
    lo, hi = np.zeros(3), np.asarray(ROOM_SIZE)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = np.where(d > 0, (hi - o) / d, np.inf)
        t_lo = np.where(d < 0, (lo - o) / d, np.inf)
    t = np.minimum(t_hi, t_lo)
    axis = np.argmin(t, axis=-1)
    return np.min(t, axis=-1), axis, d[np.arange(len(d)), axis] > 0


def ceiling_in_view(T: np.ndarray, K: np.ndarray, width: int, height: int) -> bool:
    """Whether a pixel ray of the camera reaches the ceiling before any wall (furniture ignored: conservative).
    Checks the image border (the topmost rays reach highest) densely."""
    u = np.concatenate([np.arange(width), np.arange(width), np.zeros(height), np.full(height, width - 1)])
    v = np.concatenate([np.zeros(width), np.full(width, height - 1), np.arange(height), np.arange(height)])
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], 1) @ T[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    _, axis, pos = _ray_box_t(T[:3, 3], d)
    return bool(np.any((axis == 2) & pos))


def cameras(rng: np.random.Generator, frames: int, width: int, height: int) -> np.ndarray:
    """``frames`` camera-to-world poses on an arc in front of the table (azimuths spread over the arc)."""
    K = intrinsics(width, height)
    tx, ty = TABLE_CENTRE
    target0 = np.array([tx, ty, TABLE_HEIGHT])
    X, Y, _ = ROOM_SIZE
    az = np.linspace(-50, 50, frames) if frames > 1 else np.zeros(1)
    poses = []
    for a in az:
        for _ in range(1000):
            r = rng.uniform(1.4, 2.2)
            h = rng.uniform(1.3, 1.7)
            th = np.radians(a + rng.uniform(-4, 4))
            eye = np.array([tx + r * np.sin(th), ty - r * np.cos(th), h])
            if not (0.3 <= eye[0] <= X - 0.3 and 0.3 <= eye[1] <= Y - 0.3):
                continue
            T = look_at(eye, target0 + rng.uniform(-0.08, 0.08, 3) * [1, 1, 0.5])
            if not ceiling_in_view(T, K, width, height):
                poses.append(T)
                break
        else:
            raise RuntimeError(f"no camera pose at azimuth {a}")
    return np.stack(poses)


def place_objects(rng: np.random.Generator, models: dict) -> list[dict]:
    """Upright on the table top (lowest vertex at its height), random yaw, centres within 0.3 m of the table
    centre, footprints (bounding circles) 2 cm apart."""
    tx, ty = TABLE_CENTRE
    for _ in range(10000):
        out, circles = [], []
        for oid, (V, *_rest) in models.items():
            yaw = rng.uniform(0, 2 * np.pi)
            c, s = np.cos(yaw), np.sin(yaw)
            R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
            W = V @ R.T
            xy_c = 0.5 * (W[:, :2].min(0) + W[:, :2].max(0))
            rad = float(np.max(np.linalg.norm(W[:, :2] - xy_c, axis=1)))
            p = np.array([tx, ty]) + rng.uniform(-1, 1, 2) * [0.28, 0.16]
            t = np.array([p[0] - xy_c[0], p[1] - xy_c[1], TABLE_HEIGHT - W[:, 2].min()])
            out.append({"obj_id": int(oid), "R_m2w": R, "t_m2w": t, "radius": rad, "centre": p})
            circles.append((p, rad))
        ok = all(np.linalg.norm(a[0] - b[0]) > a[1] + b[1] + 0.02
                 for i, a in enumerate(circles) for b in circles[i + 1:])
        ok &= all(abs(p[0] - tx) + r < TABLE_SIZE[0] / 2 - 0.05 and abs(p[1] - ty) + r < TABLE_SIZE[1] / 2 - 0.05
                  for p, r in circles)
        if ok:
            return out
    raise RuntimeError("could not place the objects")


# ---------------------------------------------------------------------------------------------------
# Ray casting (depth, masks): Open3D, independent of the pipeline's rasterizer
# ---------------------------------------------------------------------------------------------------

def room_triangles(spec: RoomSpec) -> tuple[np.ndarray, np.ndarray]:
    """Every surface and emitter of the room as one triangle mesh (vertices, faces)."""
    quads = [q for s in spec.surfaces for q in s.quads]
    quads += [(e.corners[0], e.corners[1] - e.corners[0], e.corners[3] - e.corners[0]) for e in spec.emitters]
    V, _, _, F = quads_mesh(quads)
    return V, F


# ---------------------------------------------------------------------------------------------------
# Mitsuba
# ---------------------------------------------------------------------------------------------------

def _mi():
    import mitsuba as mi

    if mi.variant() != "scalar_rgb":
        mi.set_variant("scalar_rgb")   # the llvm variants abort on this machine (known traps)
    return mi


def _texture(surface: Surface, rng: np.random.Generator, size: int) -> np.ndarray:
    from pipeline.synthscan.textures import make_texture

    tex = make_texture(surface.kind, rng, surface.base, size)
    lin = np.clip(srgb_to_linear(tex), 0.05, 0.85)
    return encode_u8(lin)


def scene_files(spec: RoomSpec, objects: list[dict], models: dict, folder: Path, seed: int,
                texture_size: int = 256) -> dict:
    """Write the room's PLYs and textures into ``folder``; return the material record (per surface: texture
    file, mean linear albedo)."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    mats = {}
    for s in spec.surfaces:
        V, N, UV, F = quads_mesh(s.quads, s.metres_per_repeat)
        write_ply(folder / f"{s.name}.ply", V, F, N, UV)
        tex = _texture(s, rng, texture_size if s.kind != "plain" else 8)
        cv2.imwrite(str(folder / f"{s.name}.png"), tex[..., ::-1])
        mats[s.name] = {"bsdf": "diffuse (twosided)", "texture": f"{s.name}.png", "kind": s.kind,
                        "metres_per_repeat": s.metres_per_repeat,
                        "mean_albedo_linear": srgb_to_linear(tex).reshape(-1, 3).mean(0).round(4).tolist()}
    for o in objects:
        V, F, N, C = models[o["obj_id"]]
        W = V @ o["R_m2w"].T + o["t_m2w"]
        Nw = None if N is None else N @ o["R_m2w"].T
        write_ply(folder / f"obj_{o['obj_id']:06d}.ply", W, F, Nw, rgb=srgb_to_linear(C))
    return mats


def mitsuba_scene(spec: RoomSpec, objects: list[dict] | None, folder: Path):
    """The Mitsuba scene: the room, its emitters and ``objects`` (their PLYs written by :func:`scene_files`)."""
    mi = _mi()
    d: dict = {"type": "scene", "integrator": {"type": "path", "max_depth": MAX_DEPTH}}
    for s in spec.surfaces:
        d[s.name] = {"type": "ply", "filename": str(folder / f"{s.name}.ply"),
                     "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {
                         "type": "bitmap", "filename": str(folder / f"{s.name}.png"), "raw": False,
                         "filter_type": "bilinear", "wrap_mode": "repeat"}}}}
    for e in spec.emitters:
        c = e.centre
        a, b = e.corners[1] - e.corners[0], e.corners[3] - e.corners[0]
        M = np.eye(4)
        M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = a / 2, b / 2, e.normal, c
        d[f"emitter_{e.name}"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f(M.tolist()),
                                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
                                  "emitter": {"type": "area",
                                              "radiance": {"type": "rgb", "value": e.radiance.tolist()}}}
    for o in objects or []:
        d[f"obj_{o['obj_id']:06d}"] = {"type": "ply", "filename": str(folder / f"obj_{o['obj_id']:06d}.ply"),
                                       "bsdf": dict(OBJECT_BSDF)}
    return mi.load_dict(d)


def mitsuba_sensor(T: np.ndarray, K: np.ndarray, width: int, height: int, spp: int,
                   crop: tuple[int, int, int, int] | None = None):
    """Perspective sensor for the OpenCV camera (pixel centres at integers: cx = (width - 1) / 2)."""
    mi = _mi()
    assert abs(K[0, 2] - (width - 1) / 2) < 1e-9 and abs(K[1, 2] - (height - 1) / 2) < 1e-9 and K[0, 0] == K[1, 1]
    eye = T[:3, 3]
    film = {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb", "rfilter": {"type": "box"}}
    if crop is not None:
        x0, y0, x1, y1 = crop
        film.update(crop_offset_x=int(x0), crop_offset_y=int(y0), crop_width=int(x1 - x0), crop_height=int(y1 - y0))
    return mi.load_dict({
        "type": "perspective", "fov_axis": "x", "fov": float(np.degrees(2 * np.arctan(width / (2 * K[0, 0])))),
        "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(), target=(eye + T[:3, 2]).tolist(),
                                                   up=(-T[:3, 1]).tolist()),
        "film": film, "sampler": {"type": SAMPLER, "sample_count": int(spp)}})


class Renderer:
    """One Mitsuba scene holding the room and the objects; the empty room is the same scene with the objects
    moved 10 m below the floor (outside the closed room). Loading the scene once keeps Mitsuba's emitter
    order (which differs from load to load) fixed, so that renders of the room with and without the objects
    at the same crop, seed and spp follow the same paths until one meets an object: their difference is the
    objects' effect with little noise."""

    def __init__(self, spec: RoomSpec, objects: list[dict], folder: Path):
        self.mi = _mi()
        self.scene = mitsuba_scene(spec, objects, folder)
        self.params = self.mi.traverse(self.scene)
        self.keys = [f"obj_{o['obj_id']:06d}.vertex_positions" for o in objects]
        self.pos = {k: np.array(self.params[k], np.float32) for k in self.keys}
        self.present = True

    def set_objects(self, present: bool) -> None:
        if present == self.present or not self.keys:
            self.present = present
            return
        for k in self.keys:
            v = self.pos[k].reshape(-1, 3).copy()
            if not present:
                v[:, 2] -= 10.0
            self.params[k] = type(self.params[k])(v.ravel())
        self.params.update()
        self.present = present

    def render(self, T, K, width, height, spp, seed, crop=None, objects: bool = True) -> np.ndarray:
        self.set_objects(objects)
        img = self.mi.render(self.scene, sensor=mitsuba_sensor(T, K, width, height, spp, crop), seed=int(seed),
                             spp=int(spp))
        return np.array(img, dtype=np.float32)[..., :3]


def choose_exposure(renderer: Renderer, poses, K, width, height, level: float, spp: int, seed: int,
                    white_balance: bool = False) -> float | np.ndarray:
    """Exposure making the mean 8-bit sRGB code of a few quarter-resolution renders of the empty room
    equal ``level``; with ``white_balance`` per channel (3,), as a camera's automatic white balance sets it:
    the gains that make the renders' mean grey (grey world) at unchanged luminance, times that exposure."""
    w, h = max(16, width // 4), max(12, height // 4)
    Kq = intrinsics(w, h)
    Kq[0, 0] = Kq[1, 1] = K[0, 0] * (w / width)
    idx = np.unique(np.linspace(0, len(poses) - 1, min(4, len(poses))).round().astype(int))
    imgs = np.stack([renderer.render(poses[i], Kq, w, h, spp, seed + i, objects=False) for i in idx])
    gains = np.ones(3)
    if white_balance:
        from pipeline.color import LUMINANCE_F64
        mean = imgs.reshape(-1, 3).mean(axis=0)
        gains = float(mean @ LUMINANCE_F64) / np.maximum(mean, 1e-12)
        imgs = imgs * gains
    lo, hi = -20.0, 20.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        m = float(encode_u8(imgs * math.exp(mid)).mean())
        lo, hi = (mid, hi) if m < level else (lo, mid)
    e = math.exp(0.5 * (lo + hi))
    return e * gains if white_balance else float(e)


# ---------------------------------------------------------------------------------------------------
# Per room
# ---------------------------------------------------------------------------------------------------

def crop_window(objects, models, spec: RoomSpec, T, K, width, height, margin: int) -> tuple[int, int, int, int]:
    """Pixel window (x0, y0, x1, y1) holding the objects and their shadows on the table top (projected from
    every emitter's corners and centre), grown by ``margin``."""
    pts = []
    tx, ty = TABLE_CENTRE
    for o in objects:
        V = models[o["obj_id"]][0]
        W = V[:: max(1, len(V) // 400)] @ o["R_m2w"].T + o["t_m2w"]
        pts.append(W)
        for e in spec.emitters:
            for L in list(e.corners) + [e.centre]:
                dz = L[2] - W[:, 2]
                ok = dz > 0.02
                s = (W[ok, 2] - TABLE_HEIGHT) / dz[ok]           # from W away from L down to the table plane
                P = W[ok] + (W[ok] - L) * s[:, None]
                P[:, 0] = np.clip(P[:, 0], tx - TABLE_SIZE[0] / 2, tx + TABLE_SIZE[0] / 2)
                P[:, 1] = np.clip(P[:, 1], ty - TABLE_SIZE[1] / 2, ty + TABLE_SIZE[1] / 2)
                pts.append(P)
    P = np.concatenate(pts)
    Pc = (P - T[:3, 3]) @ T[:3, :3]
    Pc = Pc[Pc[:, 2] > 0.05]
    u = K[0, 0] * Pc[:, 0] / Pc[:, 2] + K[0, 2]
    v = K[1, 1] * Pc[:, 1] / Pc[:, 2] + K[1, 2]
    x0 = int(max(0, math.floor(u.min()) - margin))
    y0 = int(max(0, math.floor(v.min()) - margin))
    x1 = int(min(width, math.ceil(u.max()) + 1 + margin))
    y1 = int(min(height, math.ceil(v.max()) + 1 + margin))
    return x0, y0, x1, y1


def _write_npy(path: Path, arr: np.ndarray) -> None:
    import io

    b = io.BytesIO()
    np.save(b, arr)
    atomic_write_bytes(path, b.getvalue())


def _write_npz(path: Path, arrays: dict) -> None:
    import io

    b = io.BytesIO()
    np.savez_compressed(b, **{k: (v.astype(np.float16) if v.dtype.kind == "f" else v) for k, v in arrays.items()})
    atomic_write_bytes(path, b.getvalue())


def load_models(obj_ids=OBJ_IDS, folder: Path = LMO) -> dict:
    models = {}
    for oid in obj_ids:
        p = Path(folder) / f"obj_{oid:06d}.ply"
        if not p.is_file():
            raise SystemExit(f"bench.lightsuite needs the LM-O models at {folder} (see shared/data/README.md)")
        models[oid] = read_model(p)
    return models


def _frame_done(root: Path, i: int) -> bool:
    t, s = root / "truth", root / "scan" / "frames"
    return all((t / f"frame-{i:06d}.{x}").is_file() for x in ("png", "photo.npy", "truth.npy", "mask.png", "json")) \
        and all((s / f"frame-{i:06d}.{x}").is_file() for x in ("color.png", "depth.png", "pose.txt"))


def object_boxes(mask: np.ndarray, pad: int = 2) -> list[tuple[int, int, int, int]]:
    """Boxes (x0, y0, x1, y1) around each instance of ``mask`` grown by ``pad``, overlapping ones merged."""
    h, w = mask.shape
    boxes = []
    for k in np.unique(mask[mask > 0]):
        ys, xs = np.nonzero(mask == k)
        boxes.append([max(0, xs.min() - pad), max(0, ys.min() - pad), min(w, xs.max() + 1 + pad),
                      min(h, ys.max() + 1 + pad)])
    merged = True
    while merged:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    boxes[i] = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return [tuple(int(v) for v in b) for b in boxes]


def blend_weight(tc: np.ndarray, pc: np.ndarray, bg: np.ndarray, sigma: float) -> np.ndarray:
    """Per-pixel weight beta in [0, 1] of the photo term: the local ratio (truth / photo) of the crop pair's
    luminance over the neighbouring background pixels (Gaussian of ``sigma`` px, centre pixel left out, so
    that beta is independent of the pixel's own samples and the estimate stays unbiased)."""
    import cv2

    r = max(1, int(math.ceil(3 * sigma)))
    x = np.arange(-r, r + 1)
    k = np.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / (2 * sigma ** 2))
    k[r, r] = 0.0
    k = (k / k.sum()).astype(np.float32)
    lum = np.array([0.2126, 0.7152, 0.0722], np.float32)
    w = bg.astype(np.float32)
    f = lambda img: cv2.filter2D(img.astype(np.float32), -1, k, borderType=cv2.BORDER_REFLECT)  # noqa: E731
    num, den, cover = f((tc @ lum) * w), f((pc @ lum) * w), f(w)
    beta = np.clip(num / np.maximum(den, 1e-12), 0.0, 1.0)
    return np.where((cover > 0.2) & (den > 1e-9), beta, 1.0).astype(np.float32)


def truth_image(R: Renderer, photo: np.ndarray, mask: np.ndarray, T, K, width, height, crop, boxes,
                spp_crop: int, spp_objects: int, seed: int, exposure: float | np.ndarray
                ) -> tuple[np.ndarray, dict, dict]:
    """The true image (linear, after exposure) and the renders it is made of.

    Outside ``crop``: the photo. Background pixels inside it: ``tc + beta (photo - pc)``, where ``tc`` and
    ``pc`` render the crop with and without the objects at the same seed and spp (correlated paths: their
    difference is the objects' effect with little noise) and ``beta`` (:func:`blend_weight`) is the local
    shadow ratio: 1 where the objects change nothing (the truth is the photo plus the difference), towards
    0 in their shadows (where the paths diverged and the photo's noise would only add). Unbiased for any
    beta independent of the pixel's samples. Object pixels (pixel centre on an object): an independent
    render of the tight ``boxes`` at ``spp_objects``. Returns the image, timings, and the crop renders."""
    x0, y0, x1, y1 = crop
    t0 = time.perf_counter()
    pc = R.render(T, K, width, height, spp_crop, seed, crop, objects=False) * exposure
    tc = R.render(T, K, width, height, spp_crop, seed, crop, objects=True) * exposure
    t1 = time.perf_counter()
    bg = mask[y0:y1, x0:x1] == 0
    beta = blend_weight(tc, pc, bg, max(1.0, 2.0 * width / WIDTH))
    truth = photo.copy()
    truth[y0:y1, x0:x1] = tc + beta[..., None] * (photo[y0:y1, x0:x1] - pc)
    negative = int(((truth[y0:y1, x0:x1] < 0).any(-1) & bg).sum())   # object pixels are replaced below
    np.maximum(truth, 0, out=truth)
    renders = {"crop": np.array(crop), "photo_crop": pc, "truth_crop": tc, "beta": beta}
    for k, (bx0, by0, bx1, by1) in enumerate(boxes):
        ob = R.render(T, K, width, height, spp_objects, seed + 1, (bx0, by0, bx1, by1), objects=True) * exposure
        sel = mask[by0:by1, bx0:bx1] > 0
        truth[by0:by1, bx0:bx1][sel] = ob[sel]
        renders[f"box{k}"], renders[f"box{k}_rect"] = ob, np.array([bx0, by0, bx1, by1])
    t2 = time.perf_counter()
    return truth, {"seconds_crop_pair": t1 - t0, "seconds_objects": t2 - t1, "negative_clipped_px": negative}, renders


def build_room(out: Path, name: str, *, frames: int = FRAMES, width: int = WIDTH, height: int = HEIGHT,
               spp_photo: int = SPP_PHOTO, spp_crop: int = SPP_CROP, spp_objects: int = SPP_OBJECTS,
               seed: int = SEED, obj_ids=OBJ_IDS, texture_size: int = 256, rebuild: bool = False,
               spec: RoomSpec | None = None, room_seed: int | None = None) -> dict:
    """Render one room into ``out/<name>`` and return its room.json record. A complete room is kept (with a
    warning when its parameters differ, unless ``rebuild``); an unfinished one resumes at its first
    unfinished frame, or starts again when its parameters differ. ``spec`` and ``room_seed``: a room that is
    not one of the suite's (:mod:`bench.lightgen`'s), by default :func:`room_spec` of ``name``."""
    from pipeline.synthscan.writers import matrix_text, write_frame

    root = Path(out) / name
    done = root / "done.json"
    spec = room_spec(name) if spec is None else spec
    room_seed = seed + 100_000 * (ROOMS + DEV_ROOMS).index(name) if room_seed is None else room_seed
    scan, truth_dir, work = root / "scan", root / "truth", root / "mitsuba"
    models = load_models(obj_ids)
    K = intrinsics(width, height)
    margin = max(8, int(round(CROP_MARGIN * width / WIDTH)))
    params = {"frames": frames, "width": width, "height": height, "spp_photo": spp_photo, "spp_crop": spp_crop,
              "spp_objects": spp_objects, "sampler": SAMPLER, "seed": seed, "obj_ids": list(obj_ids),
              "texture_size": texture_size, "max_depth": MAX_DEPTH, "version": VERSION}
    plan_path = root / "plan.json"
    plan = json.loads(plan_path.read_text()) if plan_path.is_file() else None
    if plan is not None and done.is_file() and (plan["params"] == params or not rebuild):
        if plan["params"] != params:
            log.warning("%s: complete, rendered with other parameters (%s); kept (rebuild=True renders it again)",
                        name, {k: v for k, v in plan["params"].items() if params.get(k) != v})
        return json.loads((truth_dir / "room.json").read_text())
    if plan is not None and plan["params"] != params:
        log.info("%s: parameters changed; rendering the room again", name)
        shutil.rmtree(root)
        plan = None
    for d in (scan / "frames", truth_dir, work):
        d.mkdir(parents=True, exist_ok=True)
    t_room = time.perf_counter()
    rV, rF = room_triangles(spec)
    if plan is None:
        rng = np.random.default_rng(room_seed)
        poses = cameras(rng, frames, width, height)
        for _ in range(200):
            objects = place_objects(rng, models)
            obj_meshes = [(models[o["obj_id"]][0] @ o["R_m2w"].T + o["t_m2w"], models[o["obj_id"]][1]) for o in objects]
            ok = True
            for T in poses:    # each object visible (>= 40 % of its pixels, >= 30 px at 640x480) in every frame
                _, idx = raycast([(rV, rF)] + obj_meshes, K, T, width, height)
                for k, om in enumerate(obj_meshes):
                    _, alone = raycast([om], K, T, width, height)
                    vis, amodal = int((idx == k + 1).sum()), int((alone == 0).sum())
                    ok &= amodal > 0 and vis >= max(30 * (width / WIDTH) ** 2, 0.4 * amodal)
                if not ok:
                    break
            if ok:
                break
        else:
            raise RuntimeError(f"{name}: no object placement visible in every frame")
        scene_files(spec, objects, models, work, room_seed, texture_size)
        t0 = time.perf_counter()
        exposure = choose_exposure(Renderer(spec, objects, work), poses, K, width, height, spec.level, SPP_EXPOSURE,
                                   room_seed + 7, spec.white_balance)
        plan = {"params": params, "poses": poses.tolist(), "exposure": np.asarray(exposure).tolist(),
                "seconds_exposure": time.perf_counter() - t0,
                "objects": [{"obj_id": o["obj_id"], "R_m2w": o["R_m2w"].tolist(), "t_m2w": o["t_m2w"].tolist()}
                            for o in objects]}
        atomic_write_json(plan_path, plan)
    poses = np.asarray(plan["poses"])
    exposure = plan["exposure"]
    exposure = float(exposure) if np.ndim(exposure) == 0 else np.asarray(exposure, np.float64)
    objects = [{"obj_id": o["obj_id"], "R_m2w": np.asarray(o["R_m2w"]), "t_m2w": np.asarray(o["t_m2w"])}
               for o in plan["objects"]]
    mats = scene_files(spec, objects, models, work, room_seed, texture_size)
    R = Renderer(spec, objects, work)
    obj_meshes = [(models[o["obj_id"]][0] @ o["R_m2w"].T + o["t_m2w"], models[o["obj_id"]][1]) for o in objects]
    lights_mesh = [quads_mesh([(e.corners[0], e.corners[1] - e.corners[0], e.corners[3] - e.corners[0])])
                   for e in spec.emitters]
    atomic_write_bytes(scan / "camera-intrinsics.txt", matrix_text(K, "%.18e"))
    atomic_write_bytes(scan / "gravity-direction.txt", matrix_text(np.array([[0.0], [0.0], [-1.0]]), "%.18e"))
    for i, T in enumerate(poses):
        if _frame_done(root, i):
            continue
        fs = room_seed + 1000 * i
        depth, _ = raycast([(rV, rF)], K, T, width, height)
        _, idx = raycast([(rV, rF)] + obj_meshes, K, T, width, height)
        mask = np.where(idx >= 1, idx, 0).astype(np.uint8)
        _, lidx = raycast([(m[0], m[3]) for m in lights_mesh], K, T, width, height)
        crop = crop_window(objects, models, spec, T, K, width, height, margin)
        boxes = object_boxes(mask)
        t0 = time.perf_counter()
        photo = R.render(T, K, width, height, spp_photo, fs, objects=False) * exposure
        t_photo = time.perf_counter() - t0
        truth, tinfo, renders = truth_image(R, photo, mask, T, K, width, height, crop, boxes, spp_crop,
                                            spp_objects, fs + 1, exposure)
        photo_u8, truth_u8 = encode_u8(photo), encode_u8(truth)
        if i == 0:   # the noise ceiling: the truth again with other seeds (the photo is the scan's: kept)
            t0 = time.perf_counter()
            rer, _, _ = truth_image(R, photo, mask, T, K, width, height, crop, boxes, spp_crop, spp_objects,
                                    fs + 500, exposure)
            rer_u8 = encode_u8(rer)
            atomic_write_image(truth_dir / "frame-000000.rerender.png", rer_u8)
            _write_npy(truth_dir / "frame-000000.rerender.npy", rer.astype(np.float16))
            obj_px = mask > 0
            bg = np.zeros_like(obj_px)
            bg[crop[1]:crop[3], crop[0]:crop[2]] = True
            bg &= ~obj_px
            near = bg & (np.abs(truth - photo).max(-1) > 0.01 * max(1e-6, float(photo[bg].mean())))
            atomic_write_json(truth_dir / "noise_ceiling.json", {
                "psnr_objects_db": masked_psnr(truth_u8, rer_u8, obj_px),
                "psnr_crop_background_db": masked_psnr(truth_u8, rer_u8, bg),
                "psnr_crop_background_changed_db": masked_psnr(truth_u8, rer_u8, near),
                "changed_background_px": int(near.sum()),
                "rel_rmse_objects_linear": float(np.sqrt(np.mean((truth[obj_px] - rer[obj_px]) ** 2))
                                                 / max(1e-12, float(np.mean(truth[obj_px])))),
                "object_px": int(obj_px.sum()), "seconds": time.perf_counter() - t0,
                "note": "8-bit sRGB PSNR of frame 0's truth against the same truth rendered with other seeds; "
                        "'changed' = background pixels of the crop where truth and photo differ by > 1 % of "
                        "the crop's mean (the objects' shadows and light)"})
        depth_mm = np.round(depth * 1000.0)
        depth_mm = np.where((depth_mm > 0) & (depth_mm < 65535), depth_mm, 0).astype(np.uint16)
        _write_npy(truth_dir / f"frame-{i:06d}.photo.npy", photo.astype(np.float16))
        _write_npy(truth_dir / f"frame-{i:06d}.truth.npy", truth.astype(np.float16))
        _write_npz(truth_dir / f"frame-{i:06d}.renders.npz", renders)
        atomic_write_image(truth_dir / f"frame-{i:06d}.mask.png", mask)
        atomic_write_image(truth_dir / f"frame-{i:06d}.png", truth_u8)
        write_frame(scan, "7scenes", i, photo_u8, depth_mm, T, True)
        rec = {"frame": i, "crop": list(crop), "object_boxes": [list(b) for b in boxes],
               "seconds_photo": t_photo, **tinfo,
               "seconds": t_photo + tinfo["seconds_crop_pair"] + tinfo["seconds_objects"],
               "seed_photo": fs, "seed_crop": fs + 1, "seed_objects": fs + 2,
               "lights_visible_px": {e.name: int((lidx == k).sum()) for k, e in enumerate(spec.emitters)},
               "object_px": {str(o["obj_id"]): int((mask == k + 1).sum()) for k, o in enumerate(objects)},
               "mean_srgb_photo": float(photo_u8.mean()), "clipped_fraction_photo": float((photo > 1).any(-1).mean())}
        atomic_write_json(truth_dir / f"frame-{i:06d}.json", rec)
        log.info("%s frame %d: %.1f s (photo %.1f, crop pair %.1f, objects %.1f), crop %s, mean sRGB %.0f", name, i,
                 rec["seconds"], t_photo, tinfo["seconds_crop_pair"], tinfo["seconds_objects"], crop,
                 rec["mean_srgb_photo"])
    recs = [json.loads((truth_dir / f"frame-{i:06d}.json").read_text()) for i in range(len(poses))]
    atomic_write_json(truth_dir / "objects.json", [
        {"obj_id": o["obj_id"], "model": str((LMO / f"obj_{o['obj_id']:06d}.ply").resolve()),
         "R_m2w": o["R_m2w"].tolist(), "t_m2w": o["t_m2w"].tolist()} for o in objects])
    atomic_write_json(truth_dir / "lights.json", [
        {"name": e.name, "type": "area", "shape": "rectangle", "one_sided": True, "corners": e.corners.tolist(),
         "normal": e.normal.tolist(), "centre": e.centre.tolist(), "area_m2": e.area,
         "radiance": e.radiance.tolist(), "radiance_photo": (exposure * e.radiance).tolist(), "note": e.note,
         "frames_visible": [i for i, r in enumerate(recs) if r["lights_visible_px"][e.name] > 0]}
        for e in spec.emitters])
    room = {
        "room": name, "exposure": np.asarray(exposure).tolist(), "target_mean_srgb": spec.level,
        "white_balance": spec.white_balance,
        "mean_srgb_photo": float(np.mean([r["mean_srgb_photo"] for r in recs])),
        "spp": {"photo": spp_photo, "crop_pair": spp_crop, "objects": spp_objects, "exposure_prepass": SPP_EXPOSURE},
        "sampler": SAMPLER, "integrator": {"type": "path", "max_depth": MAX_DEPTH},
        "mitsuba": {"variant": "scalar_rgb", "version": R.mi.__version__},
        "seed": seed, "room_seed": room_seed, "frames": len(poses), "width": width, "height": height,
        "K": K.tolist(), "crop_margin_px": margin, "room_size_m": list(ROOM_SIZE),
        "table": {"centre_xy": list(TABLE_CENTRE), "top_size_xy": list(TABLE_SIZE), "top_z": TABLE_HEIGHT},
        "materials": mats, "object_bsdf": OBJECT_BSDF,
        "object_colour": "PLY vertex colours (sRGB uint8) -> linear float r, g, b; Mitsuba mesh_attribute vertex_color",
        "seconds_per_frame": float(np.mean([r["seconds"] for r in recs])),
        "seconds_photo_per_frame": float(np.mean([r["seconds_photo"] for r in recs])),
        "seconds_crop_pair_per_frame": float(np.mean([r["seconds_crop_pair"] for r in recs])),
        "seconds_objects_per_frame": float(np.mean([r["seconds_objects"] for r in recs])),
        "seconds_exposure": plan.get("seconds_exposure"),
        "seconds_this_run": time.perf_counter() - t_room,
        "noise_ceiling": json.loads((truth_dir / "noise_ceiling.json").read_text()),
        "frames_info": recs,
        "world": "z up, metres; poses camera-to-world, OpenCV camera axes (x right, y down, z forward)",
    }
    atomic_write_json(truth_dir / "room.json", room)
    atomic_write_json(done, {"room": name, "finished": time.time()})
    return room


def square_spp(n: float) -> int:
    """The nearest perfect square >= 1 (the multijitter sampler's counts: it rounds others up, unrecorded)."""
    return max(1, round(math.sqrt(n))) ** 2


def build_suite(out: str | Path, rooms=ROOMS, *, frames: int = FRAMES, width: int = WIDTH, height: int = HEIGHT,
                spp: int | None = None, spp_crop: int | None = None, spp_objects: int | None = None,
                seed: int = SEED, texture_size: int = 256, rebuild: bool = False) -> dict[str, dict]:
    """Render ``rooms`` into ``out`` (skipping complete ones, resuming unfinished ones: :func:`build_room`);
    returns each room's room.json record.

    ``spp`` is the photo's samples per pixel (default :data:`SPP_PHOTO`); unless given, the truth's crop pair
    and object boxes keep their ratios to it (:data:`SPP_CROP`, :data:`SPP_OBJECTS`). Counts are rounded to
    perfect squares (:func:`square_spp`)."""
    sp = square_spp(SPP_PHOTO if spp is None else spp)
    sc = square_spp(spp_crop if spp_crop is not None else sp * SPP_CROP / SPP_PHOTO)
    so = square_spp(spp_objects if spp_objects is not None else sp * SPP_OBJECTS / SPP_PHOTO)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    res = {}
    for r in rooms:
        t0 = time.perf_counter()
        res[r] = build_room(out, r, frames=frames, width=width, height=height, spp_photo=sp, spp_crop=sc,
                            spp_objects=so, seed=seed, texture_size=texture_size, rebuild=rebuild)
        log.info("room %s ready (%.0f s)", r, time.perf_counter() - t0)
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default="bench/cache/lightsuite")
    p.add_argument("--rooms", default=",".join(ROOMS))
    p.add_argument("--spp", type=int, default=None,
                   help=f"photo spp (default {SPP_PHOTO}; unless given, crop pair x{SPP_CROP / SPP_PHOTO:g}, "
                        f"objects x{SPP_OBJECTS / SPP_PHOTO:g})")
    p.add_argument("--spp-crop", type=int, default=None)
    p.add_argument("--spp-objects", type=int, default=None)
    p.add_argument("--frames", type=int, default=FRAMES)
    p.add_argument("--rebuild", action="store_true", help="render complete rooms again if their parameters differ")
    p.add_argument("--tiny", action="store_true", help="2 frames at 160x120, few spp (what the tests render)")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", stream=sys.stdout)
    rooms = [r.strip() for r in a.rooms.split(",") if r.strip()]
    kw = dict(frames=a.frames, spp=a.spp, spp_crop=a.spp_crop, spp_objects=a.spp_objects, rebuild=a.rebuild)
    if a.tiny:
        kw.update({k: v for k, v in TINY.items() if not k.startswith("spp") or kw.get(k) is None})
    t0 = time.perf_counter()
    res = build_suite(a.out, rooms, **kw)
    for r, rec in res.items():
        print(f"{r:15s} exposure {rec['exposure']:.4g}  mean sRGB {rec['mean_srgb_photo']:.0f}  "
              f"{rec['seconds_per_frame']:.1f} s/frame  noise ceiling {rec['noise_ceiling']['psnr_objects_db']:.1f} dB")
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
