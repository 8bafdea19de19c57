"""The peer on the accuracy/speed chart: Blender Cycles rendering the light suite's frames from the same scan
mesh, photos and lights as the pipeline's oracle variant, composited and scored the same way.

Run: ``nice -n 5 .venv/bin/python -m bench.cycles [--suite bench/cache/lightsuite] [--rooms spot,coloured_walls,dim]
[--frames 8] [--spp 4,16,64]``; writes bench/results/cycles.json and cycles.png. Needs ``bpy`` (Blender as a
Python module; 4.2 is the release for Python 3.11), a bench-only dependency that neither the lock files nor
``bin/test`` install (about 500 MB)::

    .venv/bin/pip install --no-deps bpy==4.2.0

``--no-deps``: bpy's wheel asks for ``numpy`` unpinned, ``cython``, ``requests`` and ``zstandard``; none of them
is needed to render, and the venv's numpy stays as locked. Blender runs in its own process
(``python -m bench.cycles --blender SPEC OUT``), so that none of its libraries share a process with the
pipeline's.

What is compared, per room of the suite (:mod:`bench.lightsuite`; the held-out rooms by default) and frame:

- ours: :mod:`bench.lighting`'s oracle variant (``trace.lighting = "fit"`` with the suite's true emitters as
  ``trace.lights_file`` and ``trace.lights_complete``) at the presets of :mod:`pipeline.presets` (fast,
  default, high), run through the real CLI by :func:`bench.lighting.run_room`;
- Cycles (CPU device, :data:`THREADS` threads, OIDN with albedo and normal guides, box pixel filter as the
  truth's, Blender's defaults otherwise: adaptive sampling, light tree) at :data:`SPP` samples per pixel, given
  what the oracle run holds at the default preset: the room the tracer sees (``RUN/trace/<scene>/lights.npz``:
  the scan mesh (``RUN/prep/<scene>/room_trace.ply``) closed by the fit's box) as a diffuse surface whose
  albedo is the oracle fit's per-vertex albedo (the albedo our tracer's object shadows use; Cycles computes the
  room's light from it and the emitters, where our tracer reads it from the photos), the same emitters
  (``oracle_lights.json``: the true rectangles, lifted off their surface as for our tracer, one-sided, as
  Blender area lights of the same radiance), the objects from the ingested library at their poses with the
  suite's material (principled, base colour the vertex colours sRGB -> linear, metallic 0, roughness 0.5,
  specular 0.5), the raster frame's camera (K and pose), :data:`BOUNCES` bounces (the truth's path length:
  Cycles has to carry the room's inter-reflections that our tracer reads from the photos), the region our
  trace stage traced (object pixels, their edge band and the shadow ratio's pixels, plus :data:`MARGIN` px) as
  a border render. The room is Cycles' shadow catcher: one render gives the objects premultiplied by their
  coverage (transparent film) and the shadow catcher pass (the room's light with the objects over without
  them, the catcher's indirect light included). Those are written as the trace stage's passes (``pbr``,
  ``coverage``, ``shadow_ratio`` = the catcher pass's channel mean, ``albedo``, ``normal``, ``spp``, and the
  oracle run's ``exposure``) into a copy of the oracle run folder, whose composite stage then runs through the
  CLI (``--from composite``), and :func:`bench.lighting.run_room` scores it as it scores our variants (objects
  and band PSNR against the truth).

Seconds per image, all measured in one run on the same machine: Cycles, the render calls (wall and CPU of its
process; persistent data on, so the scene's BVH is built once per room, in the first frame's render; Blender's
start-up and the scene's set-up from arrays outside), plus the composite stage's CPU seconds per image
(``cpu_s_per_image``); also Cycles' whole process (``process_cpu_s_per_image``: start-up and set-up
included). Ours: the trace and composite stages' CPU seconds per image less the light fit's
(:mod:`bench.lighting`'s ``trace_composite_cpu_s_per_frame``: Cycles reads the fit's albedo, so the fit is a
shared input), which include the stages' process start-up and scene building, spread over the room's frames.
The ratio (``ratio_cpu``, and ``ratio_cpu_whole_process``): Cycles' mean objects PSNR over the rooms is
interpolated against log seconds at our default preset's mean objects PSNR; where Cycles never reaches it, the
ratio is given against its highest sample count and said so.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
SUITE = ROOT / "bench" / "cache" / "lightsuite"
WORK = ROOT / "runs" / "bench-cycles"
HELD_OUT = ("spot", "coloured_walls", "dim")
SPP = (4, 16, 64)
PRESETS = ("fast", "default", "high")
THREADS = 2
BOUNCES = 6            # the truth's path length (bench.lightsuite.MAX_DEPTH 7 = camera segment + 6 bounces)
MARGIN = 8             # px at 640 width around the region our trace stage traced
SCENE = "scan"         # bench.lighting's scene name

log = logging.getLogger("bench.cycles")


# ---------------------------------------------------------------------------------------------------
# Inputs: what the oracle run folder holds, as plain arrays for Blender's process
# ---------------------------------------------------------------------------------------------------

def scene_spec(run: Path, lights_file: Path, true_lights: Path, frames: int) -> tuple[dict, dict]:
    """The Cycles scene of an oracle run folder: ``(arrays, meta)``.

    ``arrays``: ``room_v`` (V, 3) float32 metres, ``room_f`` (T, 3) int32, ``room_albedo`` (V, 3) float32 linear
    (the oracle fit's room without its light triangles); ``obj{k}_v``, ``obj{k}_f``, ``obj{k}_n``,
    ``obj{k}_albedo`` per placed instance (world frame, linear base colour). ``meta``: ``lights`` (corners 4 x 3,
    normal, radiance x ``trace.radiance_scale``), ``frames`` (frame number, K, T_c2w, width, height, border
    ``[x0, y0, x1, y1)`` px, exposure), ``objects`` (count).
    """
    from pipeline.cli import CONFIG_NAME
    from pipeline.config import load_config
    from pipeline.io import load_npz
    from pipeline.runfolder import FrameKey, load_objects, load_raster_frame
    from pipeline.trace.lightfit import RoomLights
    from pipeline.trace.pbr import trace_mask
    from pipeline.trace.scene import instance_from_model

    cfg = load_config(run / CONFIG_NAME)
    rl = RoomLights.load(run / "trace" / SCENE / "lights.npz")
    if rl.albedo is None or not np.any(rl.albedo):
        raise RuntimeError(f"{run}: the oracle fit holds no albedo (fitted: {rl.summary.get('fitted')}, "
                           f"{rl.summary.get('note')!r}); Cycles needs the room's albedo")
    keep = ~np.asarray(rl.light_tri, bool)
    used = np.unique(rl.faces[keep])
    remap = np.full(len(rl.vertices), -1, np.int64)
    remap[used] = np.arange(len(used))
    arrays = {"room_v": rl.vertices[used].astype(np.float32), "room_f": remap[rl.faces[keep]].astype(np.int32),
              "room_albedo": np.clip(rl.albedo[used], 0.0, 1.0).astype(np.float32)}
    known = json.loads(lights_file.read_text())
    normals = [e["normal"] for e in json.loads(true_lights.read_text())]
    if len(normals) != len(known):
        raise RuntimeError(f"{lights_file} has {len(known)} emitters, {true_lights} {len(normals)}")
    lights = [{"corners": e["corners"], "normal": n,
               "radiance": (np.asarray(e["radiance"], np.float64) * cfg.trace.radiance_scale).tolist()}
              for e, n in zip(known, normals)]
    library = {o.obj_id: o for o in load_objects(run)}
    fr_meta = []
    for f in range(frames):
        rf = load_raster_frame(run, FrameKey(SCENE, 0, f))
        if f == 0:
            for k, inst in enumerate(rf.instances):
                ob = instance_from_model(library[inst.obj_id], inst.R_m2w, inst.t_m2w)
                arrays[f"obj{k}_v"] = np.asarray(ob.vertices, np.float32)
                arrays[f"obj{k}_f"] = np.asarray(ob.faces, np.int32)
                arrays[f"obj{k}_n"] = np.asarray(ob.normals, np.float32)
                arrays[f"obj{k}_albedo"] = np.asarray(ob.albedo, np.float32)
            nobj = len(rf.instances)
        tr = load_npz(run / "trace" / SCENE / "drop0000" / f"f{f:06d}.npz")
        labels = load_npz(rf.stem.with_suffix(".npz"))["labels"]
        region = trace_mask(labels, cfg.trace.edge_band) | (tr["shadow_ratio"] != 1.0) | (tr["spp"] > 0)
        cam = rf.camera
        m = max(1, round(MARGIN * cam.width / 640))
        ys, xs = np.nonzero(region)
        box = ([max(0, int(xs.min()) - m), max(0, int(ys.min()) - m), min(cam.width, int(xs.max()) + 1 + m),
                min(cam.height, int(ys.max()) + 1 + m)] if len(xs) else [0, 0, cam.width, cam.height])
        fr_meta.append({"frame": f, "K": cam.K.tolist(), "T_c2w": cam.T_c2w.tolist(), "width": cam.width,
                        "height": cam.height, "border": box, "exposure": float(tr["exposure"])})
    return arrays, {"lights": lights, "frames": fr_meta, "objects": nobj}


def blender_camera(K: np.ndarray, width: int, height: int, sensor_width: float = 36.0) -> dict:
    """Blender camera settings of an OpenCV pinhole ``K`` (pixel centres at integer coordinates) for an image
    ``width`` x ``height``: ``lens`` (mm), ``sensor_width`` (mm, horizontal fit), ``shift_x``, ``shift_y``
    (fractions of the width). Blender's pixel ``i`` spans ``[i, i + 1)``, so OpenCV's ``cx`` is at ``cx + 0.5``;
    a positive shift moves the view right / up, the principal point left / down."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if abs(fx / fy - 1.0) > 1e-4:
        raise ValueError(f"fx {fx} != fy {fy}: bench.cycles renders square pixels only")
    return {"lens": fx * sensor_width / width, "sensor_width": sensor_width,
            "shift_x": (width / 2 - (cx + 0.5)) / width, "shift_y": ((cy + 0.5) - height / 2) / width}


def light_frame(corners: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, float, float]:
    """A Blender area light's (4, 4) object matrix and its sizes (x, y) for the rectangle ``corners`` (4, 3)
    emitting towards ``normal`` (3,): Blender's area lights emit along their local -Z."""
    c = np.asarray(corners, np.float64)
    ex, ey = c[1] - c[0], c[3] - c[0]
    sx, sy = float(np.linalg.norm(ex)), float(np.linalg.norm(ey))
    x, y = ex / sx, ey / sy
    z = -np.asarray(normal, np.float64) / np.linalg.norm(normal)
    if np.dot(np.cross(x, y), z) < 0:
        y = -y
    y = np.cross(z, x)            # orthonormal, right-handed (the corners make a rectangle)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = c.mean(axis=0)
    return T, sx, sy


# ---------------------------------------------------------------------------------------------------
# Blender's process
# ---------------------------------------------------------------------------------------------------

def _mesh(bpy, name: str, v: np.ndarray, f: np.ndarray, colour: np.ndarray, normals: np.ndarray | None):
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(v))
    me.vertices.foreach_set("co", np.ascontiguousarray(v, np.float32).ravel())
    me.loops.add(3 * len(f))
    me.loops.foreach_set("vertex_index", np.ascontiguousarray(f, np.int32).ravel())
    me.polygons.add(len(f))
    me.polygons.foreach_set("loop_start", np.arange(0, 3 * len(f), 3, dtype=np.int32))
    me.update(calc_edges=True)
    me.polygons.foreach_set("use_smooth", np.ones(len(f), bool))
    attr = me.color_attributes.new("albedo", "FLOAT_COLOR", "POINT")
    rgba = np.concatenate([np.asarray(colour, np.float32), np.ones((len(v), 1), np.float32)], axis=1)
    attr.data.foreach_set("color", rgba.ravel())
    if normals is not None:
        me.normals_split_custom_set_from_vertices([tuple(n) for n in np.asarray(normals, np.float64)])
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)
    return ob


def _material(bpy, name: str, principled: bool):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    att = nt.nodes.new("ShaderNodeAttribute")
    att.attribute_name = "albedo"
    if principled:     # bench.lightsuite.OBJECT_BSDF: metallic 0, roughness 0.5, specular 0.5 (F0 0.04)
        b = nt.nodes.new("ShaderNodeBsdfPrincipled")
        b.inputs["Metallic"].default_value = 0.0
        b.inputs["Roughness"].default_value = 0.5
        b.inputs["IOR"].default_value = 1.5
        b.inputs["Specular IOR Level"].default_value = 0.5
        nt.links.new(att.outputs["Color"], b.inputs["Base Color"])
    else:
        b = nt.nodes.new("ShaderNodeBsdfDiffuse")
        b.inputs["Roughness"].default_value = 0.0
        nt.links.new(att.outputs["Color"], b.inputs["Color"])
    nt.links.new(b.outputs["BSDF"], out.inputs["Surface"])
    return mat


def _build(bpy, arrays, meta: dict, spp: int, out_dir: Path, bounces: int = BOUNCES) -> dict:
    """Set up the Cycles scene of ``arrays``/``meta`` (:func:`scene_spec`); the compositor writes the passes to
    ``out_dir``. Returns the file output node's slot names."""
    from mathutils import Matrix

    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    cy = sc.cycles
    cy.device = "CPU"
    cy.samples = spp
    cy.seed = 0
    cy.use_denoising = True
    cy.denoiser = "OPENIMAGEDENOISE"
    cy.denoising_input_passes = "RGB_ALBEDO_NORMAL"
    cy.denoising_prefilter = "ACCURATE"
    cy.max_bounces = cy.diffuse_bounces = cy.glossy_bounces = bounces
    cy.pixel_filter_type = "BOX"
    cy.filter_width = 1.0
    sc.render.threads_mode = "FIXED"
    sc.render.threads = THREADS
    sc.render.film_transparent = True
    sc.render.use_persistent_data = True
    sc.render.resolution_percentage = 100
    sc.view_settings.view_transform = "Standard"
    world = bpy.data.worlds.new("black")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    sc.world = world
    room = _mesh(bpy, "room", arrays["room_v"], arrays["room_f"], arrays["room_albedo"], None)
    room.data.materials.append(_material(bpy, "room", principled=False))
    room.is_shadow_catcher = True
    mat = _material(bpy, "object", principled=True)
    for k in range(meta["objects"]):
        ob = _mesh(bpy, f"obj{k}", arrays[f"obj{k}_v"], arrays[f"obj{k}_f"], arrays[f"obj{k}_albedo"],
                   arrays[f"obj{k}_n"])
        ob.data.materials.append(mat)
    for i, e in enumerate(meta["lights"]):
        T, sx, sy = light_frame(np.asarray(e["corners"]), np.asarray(e["normal"]))
        L = np.asarray(e["radiance"], np.float64)
        ld = bpy.data.lights.new(f"light{i}", "AREA")
        ld.shape = "RECTANGLE"
        ld.size, ld.size_y = sx, sy
        peak = float(L.max())
        ld.color = tuple((L / peak).tolist()) if peak > 0 else (0.0, 0.0, 0.0)
        # Cycles: an area light of power P (W) over area A emits radiance P / (pi A) (checked by the test)
        ld.energy = float(np.pi * sx * sy * peak)
        lo = bpy.data.objects.new(f"light{i}", ld)
        lo.matrix_world = Matrix(T.tolist())
        sc.collection.objects.link(lo)
    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    sc.collection.objects.link(cam)
    sc.camera = cam
    vl = sc.view_layers[0]
    vl.cycles.use_pass_shadow_catcher = True
    vl.cycles.denoising_store_passes = True
    sc.use_nodes = True
    nt = sc.node_tree
    nt.nodes.clear()
    rl = nt.nodes.new("CompositorNodeRLayers")
    fo = nt.nodes.new("CompositorNodeOutputFile")
    fo.base_path = str(out_dir)
    fo.format.file_format = "OPEN_EXR"
    fo.format.color_depth = "32"
    fo.format.color_mode = "RGBA"
    fo.file_slots.clear()
    slots = {"combined": "Image", "catcher": "Shadow Catcher", "albedo": "Denoising Albedo",
             "normal": "Denoising Normal"}
    for name, sock in slots.items():
        fo.file_slots.new(name)
        nt.links.new(rl.outputs[sock], fo.inputs[name])
    return slots


def _read_exr(bpy, p: Path) -> np.ndarray:
    """(H, W, 4) float32 top-down pixels of an EXR Blender wrote."""
    img = bpy.data.images.load(str(p))
    img.colorspace_settings.name = "Non-Color"
    w, h = img.size
    buf = np.empty(w * h * 4, np.float32)
    img.pixels.foreach_get(buf)
    bpy.data.images.remove(img)
    return buf.reshape(h, w, 4)[::-1].copy()


def blender_main(spec: Path, out_dir: Path, spp: int, bounces: int = BOUNCES) -> None:
    """Blender's process: render every frame of ``spec`` (:func:`scene_spec`, saved by :func:`render_cycles`)
    at ``spp`` with ``bounces``; per frame ``out_dir/fNNNNNN.npz`` with the passes of the border region and the
    seconds of its render call."""
    import bpy
    from mathutils import Matrix

    meta = json.loads(spec.with_suffix(".json").read_text())
    arrays = dict(np.load(spec))
    _build(bpy, arrays, meta, spp, out_dir / "exr", bounces)
    sc = bpy.context.scene
    cam = sc.camera
    flip = np.diag([1.0, -1.0, -1.0, 1.0])       # OpenCV camera axes -> Blender's (looks down -Z, +Y up)
    for fr in meta["frames"]:
        W, H = fr["width"], fr["height"]
        c = blender_camera(np.asarray(fr["K"]), W, H)
        cam.data.sensor_fit = "HORIZONTAL"
        cam.data.sensor_width = c["sensor_width"]
        cam.data.lens = c["lens"]
        cam.data.shift_x, cam.data.shift_y = c["shift_x"], c["shift_y"]
        cam.data.clip_start, cam.data.clip_end = 0.01, 100.0
        cam.matrix_world = Matrix((np.asarray(fr["T_c2w"]) @ flip).tolist())
        x0, y0, x1, y1 = fr["border"]
        r = sc.render
        r.resolution_x, r.resolution_y = W, H
        r.use_border = r.use_crop_to_border = True
        r.border_min_x, r.border_max_x = x0 / W, x1 / W
        r.border_min_y, r.border_max_y = 1.0 - y1 / H, 1.0 - y0 / H
        sc.frame_set(fr["frame"] + 1)
        shutil.rmtree(out_dir / "exr", ignore_errors=True)
        u0 = resource.getrusage(resource.RUSAGE_SELF)
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=False)
        wall = time.perf_counter() - t0
        u1 = resource.getrusage(resource.RUSAGE_SELF)
        cpu = (u1.ru_utime - u0.ru_utime) + (u1.ru_stime - u0.ru_stime)
        got = {n: _read_exr(bpy, out_dir / "exr" / f"{n}{fr['frame'] + 1:04d}.exr")
               for n in ("combined", "catcher", "albedo", "normal")}
        np.savez(out_dir / f"f{fr['frame']:06d}.npz", **got, wall=wall, cpu=cpu, border=np.asarray(fr["border"]))
        print(f"frame {fr['frame']}: {wall:.2f} s wall, {cpu:.2f} s CPU", flush=True)


# ---------------------------------------------------------------------------------------------------
# Our side: the passes into a run folder, composite, score
# ---------------------------------------------------------------------------------------------------

def render_cycles(spec_arrays: dict, meta: dict, out_dir: Path, spp: int, bounces: int = BOUNCES) -> list[dict]:
    """Render ``meta``'s frames in a Blender process at ``spp``; the per-frame passes (:func:`blender_main`)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    spec = out_dir / "spec.npz"
    np.savez(spec, **spec_arrays)
    spec.with_suffix(".json").write_text(json.dumps(meta))
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.run([sys.executable, "-m", "bench.cycles", "--blender", str(spec), str(out_dir), "--spp", str(spp),
                        "--bounces", str(bounces)],
                       cwd=ROOT, capture_output=True, text=True)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        raise RuntimeError(f"Blender's process failed ({p.returncode}):\n{p.stdout[-2000:]}\n{p.stderr[-3000:]}")
    process_cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    got = [dict(np.load(out_dir / f"f{fr['frame']:06d}.npz")) for fr in meta["frames"]]
    for g in got:     # the whole process (start-up, reading the scene, building it, rendering, reading passes)
        g["process_cpu"] = process_cpu / len(got)
    return got


def trace_passes(got: dict, fr: dict) -> dict:
    """Cycles' border passes as the trace stage's NPZ arrays at the frame's size (see
    :mod:`pipeline.trace.stage`): ``pbr`` premultiplied (Cycles' transparent film is), ``coverage`` = alpha,
    ``shadow_ratio`` = the shadow catcher pass's channel mean (1 outside the border), the guides, ``spp``."""
    W, H = fr["width"], fr["height"]
    x0, y0, x1, y1 = fr["border"]
    R_w2c = np.asarray(fr["T_c2w"])[:3, :3].T
    pbr = np.zeros((H, W, 3), np.float32)
    cov = np.zeros((H, W), np.float32)
    sr = np.ones((H, W), np.float32)
    alb = np.zeros((H, W, 3), np.float32)
    nrm = np.zeros((H, W, 3), np.float32)
    spp = np.zeros((H, W), np.uint16)
    c = got["combined"]
    a = np.clip(c[..., 3], 0.0, 1.0)
    pbr[y0:y1, x0:x1] = np.maximum(c[..., :3], 0.0)
    cov[y0:y1, x0:x1] = a
    s = got["catcher"][..., :3].mean(axis=2)
    sr[y0:y1, x0:x1] = np.where(np.isfinite(s), s, 1.0)
    alb[y0:y1, x0:x1] = got["albedo"][..., :3]
    nrm[y0:y1, x0:x1] = (got["normal"][..., :3].reshape(-1, 3) @ R_w2c.T).reshape(y1 - y0, x1 - x0, 3)
    spp[y0:y1, x0:x1] = 1
    return {"pbr": pbr, "ao": np.ones((H, W), np.float32), "coverage": cov, "shadow_ratio": sr, "albedo": alb,
            "normal": nrm, "spp": spp, "exposure": np.float32(fr["exposure"])}


def cycles_variant(room_dir: Path, work: Path, oracle: Path, spp: int, frames: int, bounces: int = BOUNCES) -> dict:
    """Cycles at ``spp`` on a room whose oracle run is ``oracle``: renders, composites in a copy of the run
    folder (``work/cycles-sSPP``) and leaves the marker :func:`bench.lighting.run_room` reads; returns the
    seconds (wall and CPU per image: render, composite)."""
    from bench.lighting import _cli
    from pipeline.cli import CONFIG_NAME
    from pipeline.io import atomic_save_npz

    arrays, meta = scene_spec(oracle, work / "oracle_lights.json", room_dir / "truth" / "lights.json", frames)
    run = work / f"cycles-s{spp}"
    shutil.rmtree(run, ignore_errors=True)
    shutil.copytree(oracle, run, ignore=shutil.ignore_patterns("composite", "bench_variant.json"))
    got = render_cycles(arrays, meta, work / f"blender-s{spp}", spp, bounces)
    for fr, g in zip(meta["frames"], got):
        tp = trace_passes(g, fr)
        tp["spp"] = tp["spp"] * np.uint16(spp)
        atomic_save_npz(run / "trace" / SCENE / "drop0000" / f"f{fr['frame']:06d}.npz", **tp)
    wall_c, cpu_c, _ = _cli(["run", str(run / CONFIG_NAME), "--out", str(run), "--from", "composite", "--to",
                             "composite", "--progress", "off", "-q"])
    n = len(got)
    render_wall = float(np.sum([g["wall"] for g in got])) / n
    render_cpu = float(np.sum([g["cpu"] for g in got])) / n
    # this folder's trace stage is Cycles' render: run.json says so (bench.lighting.run_room reads its seconds)
    doc = json.loads((run / "run.json").read_text())
    doc["stages"] = [{"stage": "trace", "seconds": round(render_wall * n, 3), "done": n, "total": n,
                      "note": f"Blender Cycles {spp} spp + OIDN (bench.cycles), render calls' wall seconds"}] + [
        st for st in doc["stages"] if st["stage"] != "trace"]
    (run / "run.json").write_text(json.dumps(doc, indent=1))
    return {"render_wall_s_per_image": render_wall, "render_cpu_s_per_image": render_cpu,
            "composite_cpu_s_per_image": cpu_c / n, "composite_wall_s_per_image": wall_c / n,
            "cpu_s_per_image": render_cpu + cpu_c / n, "wall_s_per_image": render_wall + wall_c / n,
            "render_cpu_s_first_frame": float(got[0]["cpu"]),
            "process_cpu_s_per_image": float(got[0]["process_cpu"]) + cpu_c / n,
            "border_px_mean": float(np.mean([(f["border"][2] - f["border"][0]) * (f["border"][3] - f["border"][1])
                                             for f in meta["frames"]]))}


def run_room_all(room_dir: Path, work: Path, frames: int, spps, presets, reuse: bool = False,
                 bounces: int = BOUNCES) -> dict:
    """Our oracle variant at ``presets`` and Cycles at ``spps`` on one room, scored by
    :func:`bench.lighting.run_room` (``reuse``: our variants already run in ``work`` with the same settings are
    read back); the room's figures."""
    import bench.lighting as bl

    n = min(frames, int(json.loads((room_dir / "truth" / "room.json").read_text())["frames"]))
    bl.write_inputs(room_dir, work, n)
    lights = f"trace.lights_file={json.dumps(str(work / 'oracle_lights.json'))}"
    names = []
    for p in presets:
        name = "oracle" if p == "default" else f"oracle-{p}"
        if name != "oracle":
            bl.SETTINGS[name] = list(bl.SETTINGS["oracle"]) + [lights, f"run.preset={p}"]
        names.append(name)
    if "oracle" not in names:      # Cycles reads the default preset's oracle run
        names.append("oracle")
    ours = bl.run_room(room_dir, work, tuple(names), n, reuse=reuse)
    res = {"room": room_dir.name, "frames": n, "ours": {}, "cycles": {}, "photo_band_psnr": ours["photo_band_psnr"],
           "render": ours["render"]}
    for p, name in zip(presets, names):
        v = ours["variants"][name]
        res["ours"][p] = {"psnr_objects": v["psnr_objects"], "psnr_band": v["psnr_band"],
                          "brightness": v["brightness"], "cpu_s_per_image": v["trace_composite_cpu_s_per_frame"],
                          "fit_cpu_s": v["fit_s"], "trace_wall_s": v["trace_wall_s"]}
    for spp in spps:
        secs = cycles_variant(room_dir, work, work / "oracle", spp, n, bounces)
        name = f"cycles-s{spp}"
        bl.SETTINGS[name] = [f"cycles.spp={spp}", f"cycles.bounces={bounces}"]
        (work / name / "bench_variant.json").write_text(json.dumps(
            {"sets": bl.SETTINGS[name], "seconds": [secs["wall_s_per_image"] * n, secs["cpu_s_per_image"] * n, 0.0]}))
        v = bl.run_room(room_dir, work, (name,), n, reuse=True)["variants"][name]
        res["cycles"][str(spp)] = {"psnr_objects": v["psnr_objects"], "psnr_band": v["psnr_band"],
                                   "brightness": v["brightness"], **secs}
        log.info("%s cycles %3d spp: objects %.2f dB band %.2f dB, %.2f s CPU / %.2f s wall per image (render)",
                 room_dir.name, spp, v["psnr_objects"], v["psnr_band"], secs["render_cpu_s_per_image"],
                 secs["render_wall_s_per_image"])
    return res


# ---------------------------------------------------------------------------------------------------
# Summary, chart, command line
# ---------------------------------------------------------------------------------------------------

def ratio_at_equal_psnr(target_db: float, ours_s: float, cycles: list[tuple[float, float]]) -> dict:
    """Cycles' seconds per image at objects PSNR ``target_db`` over ours (``ours_s``), from ``cycles``
    [(seconds, PSNR)] sorted by seconds: PSNR interpolated linearly against log seconds between the two
    sample counts around the target. Where no point reaches it, the ratio against the most expensive point
    (``reached`` False); where the cheapest already reaches it, against the cheapest (Cycles' seconds there
    are an upper bound)."""
    s = np.log([c[0] for c in cycles])
    q = np.asarray([c[1] for c in cycles])
    if not np.any(q >= target_db):
        return {"reached": False, "cycles_s": float(cycles[-1][0]), "ratio": float(cycles[-1][0] / ours_s),
                "note": f"Cycles never reaches {target_db:.2f} dB (best {q.max():.2f} dB); the ratio is against its "
                        f"highest sample count"}
    k = int(np.argmax(q >= target_db))
    if k == 0:
        sec = float(cycles[0][0])
        note = "Cycles' fewest samples already reach it: its seconds are an upper bound"
    else:
        t = (target_db - q[k - 1]) / (q[k] - q[k - 1])
        sec = float(np.exp(s[k - 1] + t * (s[k] - s[k - 1])))
        note = "interpolated against log seconds between the sample counts around it"
    return {"reached": True, "cycles_s": sec, "ratio": sec / ours_s, "note": note}


def summarise(rooms: dict, spps, presets) -> dict:
    """Means over the rooms: ours per preset, Cycles per sample count, and the ratio at our default's PSNR (on
    CPU seconds and on wall seconds of the render calls)."""
    names = list(rooms)

    def mean(vals):
        return round(float(np.mean(vals)), 3)

    ours = {p: {k: mean([rooms[r]["ours"][p][k] for r in names]) for k in ("psnr_objects", "psnr_band",
                                                                             "cpu_s_per_image")}
            for p in presets}
    cyc = {str(s): {k: mean([rooms[r]["cycles"][str(s)][k] for r in names])
                    for k in ("psnr_objects", "psnr_band", "cpu_s_per_image", "wall_s_per_image",
                              "render_cpu_s_per_image", "render_wall_s_per_image", "process_cpu_s_per_image")}
           for s in spps}
    out = {"rooms": names, "ours": ours, "cycles": cyc}
    if "default" in ours and cyc:
        target = ours["default"]["psnr_objects"]
        pts = sorted((cyc[str(s)]["cpu_s_per_image"], cyc[str(s)]["psnr_objects"]) for s in spps)
        out["ratio_cpu"] = {"at_psnr_objects_db": target, "ours_cpu_s_per_image": ours["default"]["cpu_s_per_image"],
                            **ratio_at_equal_psnr(target, ours["default"]["cpu_s_per_image"], pts)}
        out["ratio_cpu_per_room"] = {}
        for r in names:
            o = rooms[r]["ours"]["default"]
            rp = sorted((rooms[r]["cycles"][str(s)]["cpu_s_per_image"], rooms[r]["cycles"][str(s)]["psnr_objects"])
                        for s in spps)
            got = ratio_at_equal_psnr(o["psnr_objects"], o["cpu_s_per_image"], rp)
            out["ratio_cpu_per_room"][r] = {"at_psnr_objects_db": round(o["psnr_objects"], 3),
                                            "ratio": round(got["ratio"], 3), "reached": got["reached"]}
        # Cycles' whole process (Blender's start-up and scene set-up too), as ours includes its stage's start-up
        pts = sorted((cyc[str(s)]["process_cpu_s_per_image"], cyc[str(s)]["psnr_objects"]) for s in spps)
        out["ratio_cpu_whole_process"] = {"at_psnr_objects_db": target,
                                          **ratio_at_equal_psnr(target, ours["default"]["cpu_s_per_image"], pts)}
    return out


def chart(summary: dict, rooms: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, ax = plt.subplots(1, 2, figsize=(13, 5))
    for k, key in enumerate(("psnr_objects", "psnr_band")):
        a = ax[k]
        for r in rooms.values():
            xs = [r["cycles"][s]["cpu_s_per_image"] for s in r["cycles"]]
            a.plot(xs, [r["cycles"][s][key] for s in r["cycles"]], c="tab:red", alpha=0.3, lw=0.8, marker=".")
            xs = [r["ours"][p]["cpu_s_per_image"] for p in r["ours"]]
            a.plot(xs, [r["ours"][p][key] for p in r["ours"]], c="tab:green", alpha=0.3, lw=0.8, marker=".")
        c = summary["cycles"]
        a.plot([c[s]["cpu_s_per_image"] for s in c], [c[s][key] for s in c], c="tab:red", marker="o", lw=2,
               label="Cycles + OIDN (mean)")
        for s in c:
            a.annotate(f"{s} spp", (c[s]["cpu_s_per_image"], c[s][key]), fontsize=8)
        o = summary["ours"]
        a.plot([o[p]["cpu_s_per_image"] for p in o], [o[p][key] for p in o], c="tab:green", marker="s", lw=2,
               label="ours, oracle lights (mean)")
        for p in o:
            a.annotate(p, (o[p]["cpu_s_per_image"], o[p][key]), fontsize=8)
        a.set_xscale("log")
        a.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        a.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        a.set_xlabel("CPU s per image (2 cores; Cycles: render + composite, ours: trace + composite)")
        a.set_ylabel(("objects" if k == 0 else "band") + " PSNR vs Mitsuba truth (dB)")
        a.legend(fontsize=8)
    rc = summary.get("ratio_cpu")
    ax[0].set_title(f"objects; Cycles / ours at {rc['at_psnr_objects_db']:.2f} dB: {rc['ratio']:.1f}x" if rc else
                    "objects")
    ax[1].set_title("band around the objects")
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--suite", default=str(SUITE))
    p.add_argument("--rooms", default=",".join(HELD_OUT))
    p.add_argument("--frames", type=int, default=8, help="the first N frames of each room")
    p.add_argument("--spp", default=",".join(map(str, SPP)), help="Cycles' samples per pixel, comma-separated")
    p.add_argument("--presets", default=",".join(PRESETS), help="our presets (pipeline.presets)")
    p.add_argument("--work", default=str(WORK))
    p.add_argument("--out", default=str(RESULTS / "cycles"), help="output prefix (.json, .png)")
    p.add_argument("--bounces", type=int, default=BOUNCES, help="Cycles' bounces (total, diffuse, glossy)")
    p.add_argument("--reuse", action="store_true", help="read back rooms and our variants already run in --work "
                   "with the same settings")
    p.add_argument("--blender", nargs=2, metavar=("SPEC", "OUT"), help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    spps = [int(x) for x in a.spp.split(",") if x]
    if a.blender:
        blender_main(Path(a.blender[0]), Path(a.blender[1]), spps[0], a.bounces)
        return 0
    try:
        import importlib.util

        if importlib.util.find_spec("bpy") is None:
            raise ImportError
    except ImportError:
        p.error("bpy is not installed: .venv/bin/pip install --no-deps bpy==4.2.0 (a bench-only dependency)")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", stream=sys.stdout)
    presets = tuple(x for x in a.presets.split(",") if x)
    suite = Path(a.suite)
    rooms = [r for r in a.rooms.split(",") if r]
    missing = [r for r in rooms if not (suite / r / "done.json").is_file()]
    if missing:
        p.error(f"rooms {missing} are not rendered in {suite}: python -m bench.lightsuite --out {suite} "
                f"--rooms {','.join(missing)}")
    res = {}
    for r in rooms:
        # a room measured earlier with the same settings on the same render of the suite is read back with --reuse
        work = Path(a.work).resolve() / r
        from bench.lighting import render_fingerprint

        key = {"frames": a.frames, "spp": spps, "presets": list(presets), "bounces": a.bounces,
               "render": render_fingerprint(suite / r)}
        done = work / "cycles_room.json"
        if a.reuse and done.is_file() and json.loads(done.read_text())["key"] == key:
            res[r] = json.loads(done.read_text())["result"]
            log.info("%s: read back from %s", r, done)
            continue
        res[r] = run_room_all(suite / r, work, a.frames, spps, presets, a.reuse, a.bounces)
        done.write_text(json.dumps({"key": key, "result": res[r]}, default=float))
    summary = summarise(res, spps, presets)
    from importlib.metadata import version   # not bpy itself: its Embree clashes with embreex's in one process

    doc = {"summary": summary, "rooms": res,
           "what": "Blender Cycles (CPU, OIDN) vs our oracle variant on the light suite; see bench/cycles.py",
           "cycles": {"version": version("bpy"), "threads": THREADS, "bounces": a.bounces,
                      "denoiser": "OIDN, albedo + normal guides", "pixel_filter": "box 1 px"},
           "suite": str(suite), "machine": os.uname().nodename, "date": time.strftime("%Y-%m-%d %H:%M")}
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from pipeline.io import atomic_write_bytes

    atomic_write_bytes(out.with_suffix(".json"), json.dumps(doc, indent=1, default=float).encode())
    chart(summary, res, out.with_suffix(".png"))
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
