"""Configuration: one TOML table and one frozen dataclass per stage.

A config file has the tables ``[run]``, ``[scan]``, ``[objects]`` and one per stage (``[ingest]``,
``[select]``, ...). Every table and key is optional; missing keys take the defaults below. Unknown
tables and keys, wrong types and out-of-range values are :class:`~pipeline.errors.ConfigError` that name
the key, the value and the valid choices. ``--set table.key=value`` overrides a value on the command
line (the value is parsed as TOML, falling back to a plain string).

Validation is declared on each field with :func:`option` (help text, choices, bounds, path checks) and
applied once, at load time, by :func:`load_config`; stages never re-validate.

Examples
--------
>>> cfg = build_config({"run": {"seed": 3}, "simulate": {"drops": 2}})
>>> cfg.run.seed, cfg.simulate.drops
(3, 2)
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.errors import ConfigError

BUILTIN_PREFIX = "builtin:"  # scan/object paths that name a built-in generator instead of a folder


def option(default: Any, help: str, *, choices: tuple | None = None, min: float | None = None,
           max: float | None = None, min_exclusive: bool = False, path: str | None = None) -> Any:
    """Declare a config field with its validation rules.

    Parameters
    ----------
    default
        Default value (tuples for lists).
    help
        One-line description, with the unit; shown in errors and the configuration reference.
    choices
        Allowed values (for strings, or for every element of a tuple of strings).
    min, max
        Inclusive bounds for numbers (``min`` exclusive when ``min_exclusive``).
    path
        ``"file"``, ``"dir"`` or ``"any"``: the value is a path (or paths) that must exist, resolved
        relative to the config file's folder. Empty strings and ``builtin:...`` values are not checked.
    """
    meta = {"help": help, "choices": choices, "min": min, "max": max,
            "min_exclusive": min_exclusive, "path": path}
    if isinstance(default, (list, dict)):
        raise TypeError("config defaults must be immutable (use a tuple)")
    return field(default=default, metadata=meta)


# ---------------------------------------------------------------------------------------------------
# Tables
# ---------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RunConfig:
    """Run-wide settings."""

    seed: int = option(0, "root random seed; every stage, scene, drop and frame derives its own from it", min=0)
    preset: str = option("default", "quality preset: sets defaults for sampling and detail (keys given "
                         "explicitly win)", choices=("fast", "default", "high"))
    workers: int = option(1, "worker processes for per-item work; 0 = one per core", min=0)
    executor: str = option("local", "where items run", choices=("local", "ray"))
    ray_address: str = option("", "Ray cluster address to join (executor = 'ray'); empty = start a local one")
    progress: str = option("auto", "progress bars on stderr: auto = only when stderr is a terminal",
                           choices=("auto", "on", "off"))


@dataclass(frozen=True)
class ScanConfig:
    """Which room scans to use."""

    paths: tuple[str, ...] = option(("builtin:demo",),
                                    "scan folders, or 'builtin:demo' for the built-in synthetic scan",
                                    path="dir")
    format: str = option("auto", "scan layout; auto = detect from the folder's files",
                         choices=("auto", "7scenes", "3rscan", "scannet", "transforms", "bop"))
    mesh: str = option("", "room mesh file for layouts without one (transforms.json); empty = reconstruct",
                       path="file")
    max_frames: int = option(0, "use at most this many frames per scan, evenly spaced; 0 = all", min=0)


@dataclass(frozen=True)
class ObjectsConfig:
    """Which object models to insert."""

    paths: tuple[str, ...] = option(("builtin:shapes",),
                                    "object files or folders (BOP models/, .ply/.obj/.gltf/.glb); "
                                    "'builtin:shapes' = procedural demo objects", path="any")
    scale: float = option(0.0, "metres per model unit; 0 = from the format (BOP: mm, glTF: m, else m)", min=0.0)


@dataclass(frozen=True)
class IngestConfig:
    """Reading scans and object libraries; room reconstruction when a scan has no mesh."""

    tsdf_voxel: float = option(0.02, "TSDF voxel size, metres", min=0.0, min_exclusive=True)
    tsdf_trunc: float = option(0.08, "TSDF truncation distance, metres", min=0.0, min_exclusive=True)
    depth_max: float = option(4.0, "ignore depth beyond this distance during fusion, metres",
                              min=0.0, min_exclusive=True)
    min_component_faces: int = option(0, "drop reconstructed mesh pieces with fewer triangles than this; "
                                      "0 = keep all", min=0)
    register_color: str = option("auto", "colour camera: auto = estimate it from depth and photo edges "
                                 "(pipeline/registration.py) and use it when it lines them up at least 0.2 px "
                                 "better than the format's own; off = always the format's", choices=("auto", "off"))
    registration_frames: int = option(30, "auto: frames (with depth, evenly spread) the colour camera is fitted "
                                      "on and checked against", min=2)


@dataclass(frozen=True)
class SelectConfig:
    """Frame selection: drop blurred frames, keep diverse views."""

    method: str = option("relative", "blur scoring method: relative = detail against the frame's neighbours "
                         "(pipeline/blur.py), thesis = published Canny/Laplacian rule, none = keep all",
                         choices=("thesis", "none", "relative"))
    min_angle_deg: float = option(10.0, "a view within this angle AND min_baseline_m of a kept one is a "
                                  "near-duplicate and skipped, degrees; 0 = keep all", min=0.0)
    min_baseline_m: float = option(0.1, "see min_angle_deg: camera travel below which views count as the same "
                                   "spot, metres", min=0.0)
    max_frames: int = option(0, "keep at most this many frames per scan; 0 = no limit", min=0)
    window: int = option(5, "relative: neighbour frames on each side that set a frame's sharp reference", min=1)
    min_relative: float = option(0.5, "relative: drop a frame whose detail is below this share of its "
                                 "neighbours' sharp reference (0..1)", min=0.0, max=1.0)
    min_brightness: float = option(0.02, "relative: drop frames whose mean brightness is below this share "
                                   "of full scale (black frames), 0..1", min=0.0, max=1.0)
    scan_blur_max: float = option(0.45, "relative: flag the whole scan as blurred when even its sharpest "
                                  "tenth of frames has a blur effect (Crete 2007, 0 sharp..1) above this",
                                  min=0.0, max=1.0)
    thesis_edge_range: str = option("0-255", "thesis: scale of the Canny edge map whose mean must reach 0.5 "
                                    "(0-1 keeps no real frame; see pipeline/blur.py)", choices=("0-255", "0-1"))
    contact_sheet: bool = option(True, "write contact_sheet.png of kept and dropped frames with their scores")


@dataclass(frozen=True)
class PrepConfig:
    """Mesh preparation (meshprep) of the room and the objects for physics and tracing."""

    room_max_error: float = option(0.005, "largest deviation allowed when simplifying the room, metres",
                                   min=0.0)
    room_spacing: float = option(0.02, "grid spacing of the room's distance field for physics, metres",
                                 min=0.0, min_exclusive=True)
    density: float = option(700.0, "density given to every object for its mass, kg/m^3",
                            min=0.0, min_exclusive=True)


@dataclass(frozen=True)
class SimulateConfig:
    """Rigid-body drops of objects into the room."""

    drops: int = option(1, "drops (simulations) per scan", min=0)
    objects_per_drop: int = option(5, "objects spawned per drop", min=1)
    timestep: float = option(0.02, "simulation step, seconds", min=0.0, min_exclusive=True)
    max_time: float = option(40.0, "simulated time limit per drop, seconds", min=0.0, min_exclusive=True)
    repeat_objects: bool = option(True, "sample the library with repetition (false: distinct objects)")
    p_velocity: float = option(0.0, "probability that an object gets a random initial velocity and spin",
                               min=0.0, max=1.0)
    friction: float = option(0.5, "Coulomb friction coefficient of every contact", min=0.0)
    room_thickness: float = option(0.01, "half-thickness given to the scan's paper-thin surfaces while objects "
                                   "fall and tumble (bridges small holes, stops tunnelling), metres",
                                   min=0.0, min_exclusive=True)
    rest_thickness: float = option(0.001, "once a drop rests, the shell shrinks to this and the objects settle "
                                   "onto the scanned surface itself (their own hull vertices touch it), metres; "
                                   ">= room_thickness: objects stay on the thick shell", min=0.0,
                                   min_exclusive=True)
    max_penetration: float = option(0.002, "reject drops whose final penetration is deeper, metres",
                                    min=0.0, min_exclusive=True)
    retries: int = option(2, "a drop rejected as never-settled, left-room or penetration is simulated again "
                          "with a new draw (objects, spawn poses) up to this many times", min=0)


@dataclass(frozen=True)
class RasterConfig:
    """Depth, label and mask passes and the annotations derived from them."""

    visib_threshold: float = option(0.3, "an instance counts as visible from this visible fraction on",
                                    min=0.0, max=1.0)
    min_visible_area: float = option(0.01, "reject frames whose visible object pixels cover less than "
                                     "this share of the image", min=0.0, max=1.0)
    image_scale: float = option(1.0, "render at this multiple of the scan's resolution",
                                min=0.0, min_exclusive=True)
    poses: str = option("", "JSON file of chosen object poses to render instead of the simulate stage's "
                        "drops (schema in pipeline/raster.py); empty = use simulate", path="file")
    real_depth_fusion: bool = option(True, "let the real sensor depth occlude objects where it is valid and "
                                     "nearer (thin parts missing from the scan mesh)")
    fusion_tol_abs: float = option(0.02, "real depth must be nearer than the object by more than this "
                                   "plus fusion_tol_rel x depth to occlude it, metres", min=0.0)
    fusion_tol_rel: float = option(0.01, "depth-proportional part of the fusion tolerance, metres per metre",
                                   min=0.0)
    frames_per_drop: int = option(0, "a simulated drop is rastered on the kept frames predicted to see it "
                                  "(pipeline/frame_views.py); at most this many, the best-seeing first; "
                                  "0 = all of them", min=0)


@dataclass(frozen=True)
class TraceConfig:
    """Path-traced ambient occlusion and physically based shading of the objects."""

    spp: int = option(8, "samples per pixel (upper bound when adaptive)", min=1)
    lighting: str = option("fit", "light source: fit = emitters recovered from the photos by inverse rendering "
                           "(pipeline/trace/lightfit/), scan = the room mesh's own radiance with clipped-photo "
                           "lights, published = the published four lights",
                           choices=("fit", "scan", "published"))
    spp_min: int = option(8, "samples per pixel before the adaptive stop may end a pixel", min=1)
    noise_target: float = option(0.03, "adaptive stop: standard error of a pixel's mean below this share of "
                                 "its mean luminance; 0 = always take spp samples", min=0.0)
    max_depth: int = option(3, "scattering events per path (inter-reflections between objects)", min=1)
    edge_band: int = option(1, "pixels traced around the label mask for anti-aliased edges", min=0)
    ao_samples: int = option(2, "ambient-occlusion rays per camera sample (0 = no AO pass); traced only for "
                             "composite.mode = \"published\", the one blend that reads it", min=0)
    ao_distance: float = option(0.25, "ambient occlusion: occluders farther than this do not count, metres",
                                min=0.0, min_exclusive=True)
    radiance_scale: float = option(1.0, "room radiance = this x the room's linear (decoded sRGB) colours",
                                   min=0.0, min_exclusive=True)
    light_threshold: int = option(250, "room vertices with every sRGB channel >= this (0..255) are clipped "
                                  "lamps/windows, sampled as lights", min=0, max=255)
    light_gain: float = option(4.0, "radiance gain of clipped light regions (their true radiance is above the "
                               "sensor's maximum); 0 = no light detection", min=0.0)
    env_radiance: float = option(-1.0, "radiance of rays escaping through holes in the scan; negative = the "
                                 "room's mean radiance")
    published_power: float = option(1.0, "published lighting: radiance of a white floor at the room centre")
    shadow_samples: int = option(16, "shadow-ratio hemisphere rays per room point (0 = no shadow pass)", min=0)
    shadow_min_effect: float = option(0.04, "shadow ratio traced only where objects can change the light by "
                                      "more than this share (a loose bound: on 7-Scenes the true change left "
                                      "out at 0.04 has p99 0.8 %)", min=0.0, min_exclusive=True, max=1.0)
    object_shadows: int = option(1, "fit lighting: light samples per room point that an object's path meets "
                                 "near the objects, to take the objects' shadows out of the light the room sends "
                                 "them (the photos show the room without them); 0 = the room as photographed",
                                 min=0)
    shadow_stride: int = option(2, "shadow ratio traced on every n-th pixel in x and y away from the objects "
                                "(every pixel within 3 px of them), then interpolated", min=1)
    shadow_smooth: float = option(1.0, "Gaussian smoothing of the shadow ratio away from the objects (sigma, "
                                  "traced-grid pixels; 0 = none)", min=0.0)
    room_mesh: str = option("prep", "room mesh traced: prep = RUN/prep/<scene>/room_trace.ply when present "
                            "(simplified by geometry only: flat coloured detail such as windows may merge), "
                            "ingest = the full reconstructed mesh", choices=("prep", "ingest"))
    denoise: str = option("auto", "denoise the PBR and AO passes: oidn = Intel Open Image Denoise (pyoidn), "
                          "bilateral = joint bilateral filter, auto = oidn when installed",
                          choices=("off", "auto", "oidn", "bilateral"))
    photo_frames: int = option(24, "photo-based lighting: frames (spread over the scan) whose clipped pixels mark "
                               "lights on the room mesh and whose rays leaving the mesh give an environment map "
                               "for rays escaping through holes; 0 = room mesh colours and env_radiance only",
                               min=0)
    room_albedo: float = option(0.5, "photo-based lighting: typical room albedo (grey-world prior) for the energy "
                                "balance that sets the radiance of directions no photo saw; 0 = env_radiance "
                                "there", min=0.0, max=1.0)
    fit_points: int = option(16000, "fit lighting: room points the photos saw that the light fit explains at most "
                             "(drawn at random; where the light comes from is found on every other one, the choice among "
                             "the third stage's lamps on every fourth, its power "
                             "and the albedo level on all; fewer points make the fit faster and its answer depend "
                             "more on the run seed)",
                             min=50)
    fit_cell: float = option(0.4, "fit lighting: cell size of the box that closes the room's holes (each cell "
                             "an unknown emitter), metres", min=0.05)
    fit_sparsity: float = option(0.4, "fit lighting: weight of the few-bright-emitters prior (L1 on emission, each "
                                 "cell weighed by the light it sends to the photographed points; lower values let "
                                 "spurious lamps appear near the cameras)", min=0.0)
    fit_level_tolerance: float = option(0.05, "fit lighting, first stage (where the light is): each channel's room "
                                        "albedo is the highest level whose objective is within this share of the "
                                        "best (the least light that explains the photos); the second stage takes "
                                        "its minimum with the emitters found", min=0.0)
    fit_emitters: int = option(24, "fit lighting: at most this many cells of the closing box emit in the fit's second "
                               "stage (the rest reflect); 0 = one stage, emission anywhere", min=0)
    fit_refine: float = option(0.1, "fit lighting, third stage: each emitting cell is refined into lamps of this size, "
                               "metres, at the box or hanging up to 0.75 m below a ceiling cell where no photo saw "
                               "free space (a small spot over a table); 0 = keep the cells", min=0.0)
    fit_polish: int = option(60, "fit lighting, third stage: objective evaluations placing and sizing each cluster "
                             "of touching lamps hung below the ceiling (holding at least a tenth of the lamps' "
                             "power) as one rectangle: its height between the stage's depths, 0.25 m apart, its "
                             "place and its size; 0 = keep the squares of fit_refine metres where they were found",
                             min=0)
    fit_albedo_group: float = option(0.03, "fit lighting: the room's surfaces whose photo chromaticity (r, g of "
                                     "r + g + b) falls in one bin this wide, and that face one way, share one albedo "
                                     "(one per material, seen under different light); 0 = one albedo per 0.5 m cell",
                                     min=0.0, max=1.0)
    fit_white_prior: float = option(0.1, "fit lighting, last stage: pull of the fitted light's colour toward the "
                                    "photos' white, against each channel's own best albedo level (the objective "
                                    "is nearly flat there and the light's colour follows the level steeply: deep "
                                    "red walls otherwise come out lit red), where fit_white_patch is 0 or the fit "
                                    "found no lamps; 0 = each channel's own minimum", min=0.0)
    fit_white_patch: float = option(1.0, "fit lighting, last stage: pull of the albedo of the room's brightest "
                                    "surfaces (the largest patches of the brightest tenth of the photographed "
                                    "points) toward grey, against each channel's own best albedo level; it sets "
                                    "the light's colour in place of fit_white_prior (a warm lamp then stays warm "
                                    "over white walls, and deep red walls do not make the light red); 0 = "
                                    "fit_white_prior's pull on the light instead", min=0.0)
    fit_ceiling_albedo: float = option(0.8, "fit lighting: albedo of the ceiling where no photo saw it, grey (white "
                                       "paint; EN 12464-1 recommends 0.7-0.9); it sets how much of the room's light "
                                       "comes back down from above; 0 = the albedo of the upper walls the photos saw",
                                       min=0.0, max=0.95)
    fit_edge_colour: bool = option(True, "fit lighting: the lights the photos saw clipped (a lamp or a window in view) "
                                   "take the colour of the unclipped pixels their edges cover in part, over the "
                                   "surface around them, where at least 30 such pixels show it; false = the "
                                   "colour the fit finds, which the albedo's colour sets")
    fit_capture_views: int = option(3, "fit lighting: a scan with fewer photos than this (a one-view capture) cannot pin "
                                    "the light's level or colour: the fitted lights turn white (the camera's white "
                                    "balance) and are scaled by the fitted mean albedo of the photographed "
                                    "surfaces over fit_capture_albedo (the camera's auto exposure); 0 = never",
                                    min=0)
    fit_capture_albedo: float = option(0.18, "fit lighting, captures of fewer than fit_capture_views photos: mean "
                                       "albedo (linear luminance) of the photographed surfaces, the average scene's "
                                       "reflectance that exposure meters assume", min=0.01, max=0.95)
    lights_file: str = option("", "fit lighting: JSON file of emitters you know, [{\"corners\": 4 x [x, y, z] world "
                              "metres, \"radiance\": [r, g, b] linear, 1 = sensor white}]; each emits on the side "
                              "its corners turn counter-clockwise around (normal (c1 - c0) x (c2 - c0)); they light the "
                              "room as given and the fit explains only the rest (the scan's surface within 5 cm of "
                              "one, a lamp in view, is that light, not a second one); read before any stage runs",
                              path="file")
    lights_complete: bool = option(False, "fit lighting: the lights of lights_file are every light in the room: the "
                                   "fit adds none of its own (the unseen surfaces only reflect) and fits the albedo "
                                   "under them as given; false = it also finds the lights the file leaves out, and "
                                   "says so when it adds more than half their power")
    frames_per_item: int = option(8, "frames of one drop traced per work item: each item builds the drop's "
                                  "scene once; fewer frames per item = finer load balance over workers", min=1)


@dataclass(frozen=True)
class CompositeConfig:
    """Fusing the rendered objects into the real photo."""

    mode: str = option("full", "blend: published = PBR x AO inside the mask; full = edges, shadows, camera look",
                       choices=("published", "full"))
    soft_edges: bool = option(True, "full mode: anti-aliased edges from the traced coverage (false = hard label mask)")
    shadows: bool = option(True, "full mode: darken the room by the traced shadow ratio (differential rendering)")
    blur_sigma: float = option(-1.0, "full mode: Gaussian blur of the objects, pixels; negative = match the "
                               "photo's measured blur level")
    noise_sigma: float = option(-1.0, "full mode: sensor noise added to the objects, gray levels (0..255); "
                                "negative = measured from the photo; 0 = none")
    exposure: float = option(1.0, "photo exposure relative to the scan's room colours (rendered radiance x "
                             "this / trace.radiance_scale is encoded with the sRGB curve)", min=0.0,
                             min_exclusive=True)
    match_exposure: bool = option(True, "full mode: scale the objects by the photo's exposure relative to the room "
                                  "mesh colours, measured per frame by the trace stage (auto-exposure cameras)")
    depth_fill: str = option("none", "depth output where the real depth is invalid: none = keep 0, room = the "
                             "room mesh's rendered depth", choices=("none", "room"))


@dataclass(frozen=True)
class ExportConfig:
    """Dataset writers."""

    formats: tuple[str, ...] = option(("bop", "coco"), "dataset formats to write", choices=("bop", "coco", "yolo"))
    image_format: str = option("jpg", "colour image files", choices=("jpg", "png"))
    chunk_size: int = option(1000, "images per BOP scene folder", min=1)
    depth_scale: float = option(0.1, "BOP depth PNG unit: millimetres per stored uint16 value "
                                "(0.1 = 0.1 mm steps, up to 6.55 m)", min=0.0, min_exclusive=True)
    jpeg_quality: int = option(95, "JPEG quality of colour images (image_format = 'jpg')", min=1, max=100)
    yolo_task: str = option("detect", "YOLO labels/: detect = one 'class cx cy w h' line per instance (visible "
                            "box); segment = one 'class x1 y1 x2 y2 ...' polygon of the visible mask",
                            choices=("detect", "segment"))
    yolo_split: str = option("drop", "YOLO train/val split unit: whole drops or whole scan scenes (never single "
                             "frames: neighbouring frames of a drop are near-duplicates)", choices=("drop", "scene"))
    yolo_val_fraction: float = option(0.2, "share of the drops (or scenes) that go to YOLO's val split, drawn "
                                      "from run.seed", min=0.0, max=1.0)


@dataclass(frozen=True)
class Config:
    """The whole configuration: one attribute per TOML table."""

    run: RunConfig = RunConfig()
    scan: ScanConfig = ScanConfig()
    objects: ObjectsConfig = ObjectsConfig()
    ingest: IngestConfig = IngestConfig()
    select: SelectConfig = SelectConfig()
    prep: PrepConfig = PrepConfig()
    simulate: SimulateConfig = SimulateConfig()
    raster: RasterConfig = RasterConfig()
    trace: TraceConfig = TraceConfig()
    composite: CompositeConfig = CompositeConfig()
    export: ExportConfig = ExportConfig()


TABLES: dict[str, type] = {f.name: typing.get_type_hints(Config)[f.name] for f in dataclasses.fields(Config)}


# ---------------------------------------------------------------------------------------------------
# Loading and validation
# ---------------------------------------------------------------------------------------------------

def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is tuple:
        return f"list of {_type_name(typing.get_args(tp)[0])}"
    return {int: "integer", float: "number", str: "string", bool: "true/false"}.get(tp, str(tp))


def _coerce(key: str, value: Any, tp: Any, meta: dict) -> Any:
    """Check ``value`` against the field type ``tp`` and the rules in ``meta``; return the typed value."""
    origin = typing.get_origin(tp)
    if origin is tuple:
        elem = typing.get_args(tp)[0]
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key} = {value!r}: expected a {_type_name(tp)}; "
                              f"{meta['help']}")
        return tuple(_coerce(key, v, elem, meta) for v in value)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key} = {value!r}: expected true or false; {meta['help']}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key} = {value!r}: expected an integer; {meta['help']}")
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key} = {value!r}: expected a number; {meta['help']}")
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{key} = {value!r}: expected a finite number; {meta['help']}")
    elif tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key} = {value!r}: expected a string; {meta['help']}")
    if meta["choices"] is not None and value not in meta["choices"]:
        valid = ", ".join(repr(c) for c in meta["choices"])
        raise ConfigError(f"{key} = {value!r}: not a valid choice; valid: {valid}")
    lo, hi = meta["min"], meta["max"]
    if lo is not None and (value < lo or (meta["min_exclusive"] and value == lo)):
        rel = ">" if meta["min_exclusive"] else ">="
        raise ConfigError(f"{key} = {value!r}: must be {rel} {lo}; {meta['help']}")
    if hi is not None and value > hi:
        raise ConfigError(f"{key} = {value!r}: must be <= {hi}; {meta['help']}")
    return value


def _resolve_path(key: str, value: str, kind: str, base: Path) -> str:
    if value == "" or value.startswith(BUILTIN_PREFIX):
        return value
    p = Path(value).expanduser()
    if not p.is_absolute():
        p = (base / p)
    p = Path(str(p.resolve()))
    if not p.exists():
        raise ConfigError(f"{key} = {value!r}: {p} does not exist; fix the path "
                          f"(relative paths are read from the config file's folder {base})")
    if kind == "file" and not p.is_file():
        raise ConfigError(f"{key} = {value!r}: {p} is a folder, expected a file")
    if kind == "dir" and not p.is_dir():
        raise ConfigError(f"{key} = {value!r}: {p} is a file, expected a folder")
    return str(p)


# Keys that configs written for earlier versions may still set: what became of each, said with the fix.
REMOVED_KEYS = {
    "trace.fit_albedo_shrink": "it had no effect at its default 0",
    "trace.fit_light_colour": "the fitted lights always share one colour per kind of emitter, as 'shared' did",
}


def _build_table(name: str, cls: type, raw: Any, base: Path) -> Any:
    if not isinstance(raw, dict):
        raise ConfigError(f"[{name}] must be a table, got {raw!r}", key=name)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(raw) - set(fields))
    removed = [k for k in unknown if f"{name}.{k}" in REMOVED_KEYS]
    if removed:
        key = f"{name}.{removed[0]}"
        raise ConfigError(f"{key} is no longer an option ({REMOVED_KEYS[key]}); delete it", key=key)
    if unknown:
        raise ConfigError(f"unknown key {name}.{unknown[0]}; valid keys in [{name}]: {', '.join(fields)}",
                          key=f"{name}.{unknown[0]}")
    kwargs = {}
    for key, value in raw.items():
        meta = fields[key].metadata
        try:
            v = _coerce(f"{name}.{key}", value, hints[key], meta)
            if meta.get("path"):
                if isinstance(v, tuple):
                    v = tuple(_resolve_path(f"{name}.{key}", x, meta["path"], base) for x in v)
                else:
                    v = _resolve_path(f"{name}.{key}", v, meta["path"], base)
        except ConfigError as e:
            e.key = f"{name}.{key}"
            raise
        kwargs[key] = v
    return cls(**kwargs)


def build_config(raw: dict, *, base_dir: str | Path = ".") -> Config:
    """Build and validate a :class:`Config` from nested plain dicts (a parsed TOML document).

    Parameters
    ----------
    raw
        ``{table: {key: value}}``; missing tables and keys take defaults.
    base_dir
        Folder that relative paths are resolved against (the config file's folder).
    """
    if not isinstance(raw, dict):
        raise ConfigError(f"config must be a table of tables, got {type(raw).__name__}")
    unknown = sorted(set(raw) - set(TABLES))
    if unknown:
        raise ConfigError(f"unknown table [{unknown[0]}]; valid tables: {', '.join(TABLES)}", key=unknown[0])
    base = Path(base_dir).resolve()
    raw = _with_preset(raw)
    cfg = Config(**{name: _build_table(name, TABLES[name], raw.get(name, {}), base) for name in TABLES})
    if cfg.trace.lights_complete and not cfg.trace.lights_file:
        raise ConfigError("trace.lights_complete = true: it says trace.lights_file holds every light, but no "
                          "lights_file is given; name the file, or leave lights_complete false",
                          key="trace.lights_complete")
    return cfg


def _with_preset(raw: dict) -> dict:
    """``raw`` layered over the defaults of its ``run.preset`` (explicit keys win)."""
    from pipeline.presets import PRESETS

    run = raw.get("run", {})
    name = run.get("preset", "default") if isinstance(run, dict) else "default"
    if name not in PRESETS:
        raise ConfigError(f"run.preset = {name!r}: not a valid choice; valid: "
                          f"{', '.join(map(repr, PRESETS))}", key="run.preset")
    merged = {table: dict(values) for table, values in PRESETS[name].items()}
    for table, values in raw.items():
        if isinstance(values, dict) and isinstance(merged.get(table), dict):
            merged[table].update(values)
        else:
            merged[table] = values
    return merged


def parse_override(text: str) -> tuple[str, str, Any]:
    """Parse ``table.key=value`` from ``--set``; the value is TOML, else a bare string."""
    if "=" not in text or "." not in text.split("=", 1)[0]:
        raise ConfigError(f"--set {text!r}: expected table.key=value, e.g. --set run.seed=3")
    lhs, rhs = text.split("=", 1)
    table, key = lhs.strip().split(".", 1)
    try:
        value = tomllib.loads(f"v = {rhs.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = rhs.strip()
    return table, key, value


def load_config(path: str | Path | None, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Read a TOML config file (or only defaults when ``path`` is None) and apply ``--set`` overrides."""
    raw: dict = {}
    base = Path.cwd()
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"config file {p} does not exist; pass an existing .toml file "
                              f"(examples in configs/)")
        try:
            raw = tomllib.loads(p.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"{p}: not valid TOML: {e}") from None
        except UnicodeDecodeError as e:
            raise ConfigError(f"{p}: not a UTF-8 text file ({e.reason}); is this a TOML config?") from None
        base = p.resolve().parent
    set_by: dict[str, str] = {}     # what --set gave: "table.key" (and a table it brought) -> its text
    for text in overrides:
        table, key, value = parse_override(text)
        if table not in raw:
            set_by[table] = text
        raw.setdefault(table, {})
        if not isinstance(raw[table], dict):
            raise ConfigError(f"--set {text!r}: [{table}] is not a table")
        raw[table][key] = value
        set_by[f"{table}.{key}"] = text
    try:
        return build_config(raw, base_dir=base)
    except ConfigError as e:
        # say where the bad key or value came from: the file, or the command line
        if e.key in set_by:
            raise ConfigError(f"--set {set_by[e.key]!r}: {e}", key=e.key) from None
        if path is not None:
            raise ConfigError(f"{path}: {e}", key=e.key) from None
        raise


def config_to_dict(cfg: Config) -> dict:
    """Plain nested dict of a config (tuples become lists), for saving."""
    out = {}
    for f in dataclasses.fields(cfg):
        table = getattr(cfg, f.name)
        out[f.name] = {k: list(v) if isinstance(v, tuple) else v
                       for k, v in dataclasses.asdict(table).items()}
    return out


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")


def dump_config(cfg: Config) -> str:
    """TOML text of a resolved config; :func:`load_config` reads it back to an equal config."""
    lines = []
    for table, values in config_to_dict(cfg).items():
        lines.append(f"[{table}]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in values.items()]
        lines.append("")
    return "\n".join(lines)


def template_toml(header: str = "") -> str:
    """A complete config with every key at its default and its help as a comment above it."""
    lines = [header.rstrip(), ""] if header else []
    for table, cls in TABLES.items():
        lines.append(f"# {cls.__doc__.strip().splitlines()[0]}")
        lines.append(f"[{table}]")
        for f in dataclasses.fields(cls):
            m = f.metadata
            extra = f" One of: {', '.join(map(repr, m['choices']))}." if m["choices"] else ""
            lines.append(f"# {m['help']}.{extra}")
            lines.append(f"{f.name} = {_toml_value(f.default)}")
        lines.append("")
    return "\n".join(lines)


def reference_markdown() -> str:
    """Markdown configuration reference generated from the field declarations (for docs/config.md): one section
    per table, one list item per key with its default and meaning (a list, not a table: some meanings run to a
    paragraph)."""
    out = []
    for table, cls in TABLES.items():
        out.append(f"## `[{table}]` - {cls.__doc__.strip().splitlines()[0]}\n")
        for f in dataclasses.fields(cls):
            m = f.metadata
            extra = f" (one of {', '.join(map(repr, m['choices']))})" if m["choices"] else ""
            out.append(f"- `{f.name}` = `{_toml_value(f.default)}`: {m['help']}{extra}")
        out.append("")
    return "\n".join(out)

