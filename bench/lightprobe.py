"""The light fit's model of a room's light against Mitsuba's irradiance, in the light suite's rooms.

``bench/lighting.py`` scores what the fitted lights do to the objects; this says where the fit's model of the
room's light is wrong. At points the photos saw, it compares the irradiance the fitted room sends besides its
emitters (the gather of ``trace/{scene}/lights.npz``: the scan's surfaces at their photographed radiance and
the closing box's cells at their fitted radiance) with the indirect irradiance Mitsuba 3 measures there in the
suite's true room (an ``irradiancemeter`` with the emitters hidden from it, the suite's path depth); and it
compares the radiance the fit gives the unseen ceiling with the suite's ceiling albedo times Mitsuba's
irradiance under it. A ratio of 1 is the truth. The reference is Mitsuba, not our tracer, and it measures the
light itself, not through our BSDF or compositor.

It also compares the total irradiance at the objects' places (``OBJECT_RISE_M`` over each object's origin, facing up
and the four horizontal world axes): the fitted room as the trace stage lights an object (the scan's surfaces and
the box cells by the gather, the sampled lights by next-event estimation, :func:`emitter_irradiance`) against
Mitsuba's meter with the emitters in view. ``bench.lighting``'s objects' brightness follows it to within 0.07 per
channel (mean 0.03 over the six rooms' fits at run seeds 0-2 and the oracle), from the fitted lights alone
in seconds, without tracing a frame: a quick check of a change to the fit, not a score.

Run after ``bench.lighting`` (its work folder holds each room's fit run)::

    python -m bench.lightprobe --work runs/bench-lighting --rooms spot,window --variants fit,oracle

What the gather leaves out: a mesh triangle's side no photo saw (the fit replaces its light by
``_sheet_backs``), and the emitters (the fit's own and the known lights), whose light Mitsuba's meter does not
count either. Points: every ``STRIDE``-th pixel of every other photo that meets the scan's mesh.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from bench.lighting import SUITE, WORK
from bench.lightsuite import MAX_DEPTH, room_list, tuning_rooms_need_out

log = logging.getLogger("bench.lightprobe")

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
STRIDE = 40            # photo pixels between probe points
RAYS = 4096            # gather rays per point (the fit's own: 64)
SPP = 8192             # Mitsuba samples per meter
OFFSET_M = 0.004       # a meter stands this far off the surface, along its normal
CEILING_ABOVE_M = 2.3  # box cells facing down above this height (over the floor) are the unseen ceiling
GROUPS = ("floor", "table", "walls", "all")
OBJECT_RISE_M = 0.03   # the objects' meters stand this far over each object's origin (inside its extent)
FACINGS = {"up": (0.0, 0.0, 1.0), "+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0),
           "-y": (0.0, -1.0, 0.0)}   # the suite's world axes (z up)
OBJECT_RAYS = 32768    # gather rays per object meter
NEE_SAMPLES = 16384    # light samples per object meter


def meters(scene, points: np.ndarray, normals: np.ndarray, spp: int, indirect: bool, seed: int = 7) -> np.ndarray:
    """(n, 3) irradiance Mitsuba measures at ``points`` facing ``normals``: on a 2 mm square meter (not part of
    the scene, so it shades nothing) ``OFFSET_M`` off the surface; with ``indirect`` the emitters seen straight
    from the meter are hidden (the light every surface sends, not the lights')."""
    from bench.lightsuite import _mi

    mi = _mi()
    integrator = mi.load_dict({"type": "path", "max_depth": MAX_DEPTH - 1, "hide_emitters": bool(indirect)})
    out = np.zeros((len(points), 3))
    for i, (p, n) in enumerate(zip(np.asarray(points, np.float64), np.asarray(normals, np.float64))):
        n = n / np.linalg.norm(n)
        t = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
        t /= np.linalg.norm(t)
        M = np.eye(4)
        M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = 1e-3 * t, 1e-3 * np.cross(n, t), n, p + OFFSET_M * n
        shape = mi.load_dict({"type": "rectangle", "to_world": mi.ScalarTransform4f(M.tolist()),
                              "sensor": {"type": "irradiancemeter",
                                         "film": {"type": "hdrfilm", "width": 1, "height": 1, "pixel_format": "rgb",
                                                  "rfilter": {"type": "box"}},
                                         "sampler": {"type": "independent", "sample_count": int(spp)}}})
        img = mi.render(scene, sensor=shape.sensor(), integrator=integrator, spp=int(spp), seed=seed)
        out[i] = np.asarray(img, np.float64).reshape(-1)[:3]
    return out


def room_scene(rl) -> tuple:
    """The fitted room ``rl``'s triangles for ray casting: (its Embree intersector, faces (T, 3), unit normals
    (T, 3) as wound)."""
    from pipeline.trace.intersect import EmbreeIntersector

    V, F = np.asarray(rl.vertices, np.float64), np.asarray(rl.faces, np.int64)
    q = V[F]
    tn = np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0])
    tn /= np.maximum(np.linalg.norm(tn, axis=1, keepdims=True), 1e-30)
    return EmbreeIntersector(V.astype(np.float32), F.astype(np.int32)), F, tn


def gather(rl, points: np.ndarray, normals: np.ndarray, rays: int, rng: np.random.Generator,
           scene: tuple | None = None) -> dict:
    """The irradiance the fitted room ``rl`` sends ``points``, by what the cosine-weighted rays meet: ``mesh``
    (the scan's surfaces, the side the photos saw), ``box`` (the closing box's cells), ``lights`` (emitters:
    not counted by the meter), ``unseen_side`` (a mesh triangle's other side: replaced in the fit); each (n, 3),
    and ``box_share`` (n,) the share of rays meeting the box. ``scene``: :func:`room_scene` of ``rl`` if built."""
    from pipeline.trace.lightfit import transport

    isect, F, tn = scene or room_scene(rl)
    n = len(points)
    _, hits, d = transport.gather(isect, np.asarray(points, np.float64), np.asarray(normals, np.float64), rays, rng, OFFSET_M)
    hit = np.flatnonzero(hits.hit)
    rad = np.zeros((hits.hit.size, 3))
    rad[hit] = transport.at(np.asarray(rl.radiance, np.float64), F, hits.prim[hit], hits.u[hit], hits.v[hit])
    prim = np.where(hits.hit, hits.prim, -1)
    safe = np.maximum(prim, 0)
    mesh = (prim >= 0) & (prim < rl.num_mesh_tris)
    back = mesh & (np.sum(tn[safe] * d, axis=1) > 0)
    light = (prim >= 0) & np.asarray(rl.light_tri, bool)[safe]
    kinds = {"mesh": mesh & ~back & ~light, "unseen_side": back & ~light, "box": (prim >= rl.num_mesh_tris) & ~light,
             "lights": light}
    out = {k: np.pi * np.where(m[:, None], rad, 0.0).reshape(n, rays, 3).mean(axis=1) for k, m in kinds.items()}
    out["box_share"] = kinds["box"].reshape(n, rays).mean(axis=1)
    return out


def emitter_irradiance(rl, points: np.ndarray, normals: np.ndarray, samples: int, rng: np.random.Generator,
                       scene: tuple | None = None) -> np.ndarray:
    """(n, 3) irradiance the fitted room ``rl``'s sampled lights (``light_tri``) send ``points`` facing ``normals``,
    with the trace stage's own light sampling (:func:`pipeline.trace.lights.build_area_lights`: a triangle by power,
    then a point by area, its radiance interpolated): ``samples`` points per receiver, emitting from both sides as
    the tracer's next-event estimation takes them, with visibility through the fitted room. A small bright lamp is
    what cosine-weighted gather rays miss most (in the light suite's ceiling room a 32768-ray gather put the
    objects at 0.84x the truth's light, the trace at 1.04x)."""
    from pipeline.trace.lightfit.transport import sampled_irradiance
    from pipeline.trace.lights import build_area_lights, sample_area_lights

    isect, F, tn = scene or room_scene(rl)
    points, normals = np.asarray(points, np.float64), np.asarray(normals, np.float64)
    V, E = np.asarray(rl.vertices, np.float64), np.asarray(rl.radiance, np.float64)
    lights = build_area_lights(V, F, E, np.asarray(rl.light_tri, bool))
    out = np.zeros((len(points), 3))
    if lights.count == 0:
        return out
    for i, (p, n) in enumerate(zip(points, normals)):
        tri, b1, b2, pdf = sample_area_lights(lights, V, F, *rng.random((3, samples)))
        f = F[tri]
        b = np.stack([1 - b1 - b2, b1, b2], axis=1)[:, :, None]
        lp, Le = (b * V[f]).sum(axis=1), (b * E[f]).sum(axis=1)
        g = sampled_irradiance(isect, np.tile(p, (samples, 1)), np.tile(n, (samples, 1)), lp, tn[tri], 1.0,
                                OFFSET_M, two_sided=True)
        out[i] = (g[:, None] * Le / pdf[:, None]).mean(axis=0)
    return out


def photographed_points(rl, scan, every: int = 2, stride: int = STRIDE,
                        scene: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points (n, 3) of the fitted room's scan mesh that every ``every``-th photo of ``scan`` sees at every
    ``stride``-th pixel, and their normals (n, 3) turned to the camera. ``scene``: :func:`room_scene` of ``rl``."""
    isect, _, tn = scene or room_scene(rl)
    P, N = [], []
    w, h = int(scan.width), int(scan.height)
    for i in range(0, scan.num_frames, every):
        cam = scan.camera(i)
        ys, xs = np.mgrid[stride // 2:h:stride, stride // 2:w:stride]
        pix = (ys * w + xs).ravel()
        o, d = cam.rays(pix, np.full((pix.size, 2), 0.5, np.float32))
        hits = isect.intersect(o, d)
        ok = np.flatnonzero(hits.hit & (hits.prim < rl.num_mesh_tris) & ~np.asarray(rl.light_tri, bool)[
            np.maximum(hits.prim, 0)])
        nrm = tn[hits.prim[ok]]
        P.append(o[ok] + hits.t[ok, None] * d[ok])
        N.append(nrm * -np.sign(np.sum(nrm * d[ok], axis=1))[:, None])
    return np.concatenate(P).astype(np.float64), np.concatenate(N).astype(np.float64)


def unseen_ceiling(rl, up: np.ndarray, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres (C, 3) of the closing box's cells that face down more than ``CEILING_ABOVE_M`` above ``floor``,
    and their fitted radiance (C, 3) (four vertices per cell, one radiance)."""
    nm = rl.num_mesh_vertices
    cells = int(rl.summary["box_cells"])
    BV = np.asarray(rl.vertices[nm:nm + 4 * cells], np.float64).reshape(cells, 4, 3)
    BR = np.asarray(rl.radiance[nm:nm + 4 * cells], np.float64).reshape(cells, 4, 3)
    c = BV.mean(axis=1)
    nrm = np.cross(BV[:, 1] - BV[:, 0], BV[:, 2] - BV[:, 0])
    flat = np.abs(nrm @ up) > 0.9 * np.linalg.norm(nrm, axis=1)
    top = flat & (c @ up - floor > CEILING_ABOVE_M)
    return c[top], BR[top].mean(axis=1)


def _ratio(model: np.ndarray, truth: np.ndarray) -> list:
    return [round(float(x), 4) for x in model.sum(axis=0) / np.maximum(truth.sum(axis=0), 1e-30)]


def probe_room(room_dir: Path, run_dir: Path, *, rays: int = RAYS, spp: int = SPP, seed: int = 0) -> dict:
    """The probe's figures for suite room ``room_dir`` and the fitted lights of its run ``run_dir``."""
    from bench.lightsuite import mitsuba_scene, room_spec
    from pipeline.scanformats.detect import read_scan
    from pipeline.trace.lightfit import RoomLights

    t0 = time.perf_counter()
    room = json.loads((room_dir / "truth" / "room.json").read_text())
    lights = sorted(run_dir.glob("trace/*/lights.npz"))
    if not lights:
        raise FileNotFoundError(f"{run_dir}: no trace/*/lights.npz (run bench.lighting's fit variant first)")
    rl = RoomLights.load(lights[0])
    scan = read_scan(room_dir / "scan")
    up = np.asarray(scan.up_w, np.float64)
    up /= np.linalg.norm(up)
    room_rays = room_scene(rl)                    # built once, cast by both
    P, N = photographed_points(rl, scan, scene=room_rays)
    model = gather(rl, P, N, rays, np.random.default_rng(seed), scene=room_rays)
    scene = mitsuba_scene(room_spec(room["room"]), None, room_dir / "mitsuba")
    expo = float(room["exposure"])                 # the photos' (and so the fit's) radiance per Mitsuba's
    truth = expo * meters(scene, P, N, spp, indirect=True)
    floor = float(np.min(P @ up))
    h, nz = P @ up - floor, N @ up
    table = float(room["table"]["top_z"]) - floor
    groups = {"floor": (nz > 0.9) & (h < 0.1), "table": (nz > 0.9) & (np.abs(h - table) < 0.1),
              "walls": np.abs(nz) < 0.2, "all": np.ones(len(P), bool)}
    out: dict = {"room": room["room"], "points": int(len(P)), "lights": str(lights[0].relative_to(run_dir)),
                 "fit_summary": {k: rl.summary.get(k) for k in
                                 ("albedo_level", "known_lights", "own_over_known_power")},
                 "groups": {}}
    for g, m in groups.items():
        if m.sum() < 5:
            continue
        out["groups"][g] = {"points": int(m.sum()),
                            "model_over_mitsuba": _ratio(model["mesh"][m] + model["box"][m], truth[m]),
                            "scan_surfaces_over_mitsuba": _ratio(model["mesh"][m], truth[m]),
                            "box_over_mitsuba": _ratio(model["box"][m], truth[m]),
                            "box_share": round(float(model["box_share"][m].mean()), 4),
                            "unseen_side_over_mitsuba": _ratio(model["unseen_side"][m], truth[m])}
    cen, rad = unseen_ceiling(rl, up, floor)
    level = P - np.outer(P @ up, up)                  # over the floor the photos saw (inside Mitsuba's room)
    cl = cen - np.outer(cen @ up, up)
    inside = np.all((cl >= level.min(axis=0) - 1e-6) & (cl <= level.max(axis=0) + 1e-6), axis=1)
    cen, rad = cen[inside], rad[inside]
    if len(cen):
        # the suite's ceiling (its room's height over the floor), its meters facing down just under it
        probe = cl[inside] + (floor + float(room["room_size_m"][2])) * up
        E = expo * meters(scene, probe, np.tile(-up, (len(probe), 1)), max(spp // 2, 1), indirect=False)
        albedo = np.asarray(room["materials"]["ceiling"]["mean_albedo_linear"], np.float64)
        out["unseen_ceiling"] = {"cells": int(len(cen)), "box_top_m": round(float(np.mean(cen @ up) - floor), 3),
                                 "radiance_over_mitsuba": _ratio(rad, albedo / np.pi * E),
                                 "suite_ceiling_albedo": albedo.round(4).tolist()}
    out["objects"] = objects_light(rl, room_dir, scene, expo, up, spp, np.random.default_rng(seed + 1), room_rays)
    out["seconds"] = round(time.perf_counter() - t0, 1)
    return out


def objects_light(rl, room_dir: Path, scene, expo: float, up: np.ndarray, spp: int, rng: np.random.Generator,
                  room_rays: tuple) -> dict:
    """The total irradiance at the suite room's objects' places, fitted (as the trace stage lights an object: the
    gather of the scan's surfaces and box cells, the sampled lights by :func:`emitter_irradiance`; a mesh
    triangle's unseen side sends nothing there) over Mitsuba's (x the photos' exposure), in all and per facing,
    with each side's direct (the emitters) and indirect share."""
    plan = json.loads((room_dir / "plan.json").read_text())
    centres = np.array([o["t_m2w"] for o in plan["objects"]], np.float64) + OBJECT_RISE_M * up
    face = np.array(list(FACINGS.values()))
    P = np.repeat(centres, len(face), axis=0)
    N = np.tile(face, (len(centres), 1))
    g = gather(rl, P, N, OBJECT_RAYS, rng, scene=room_rays)
    model_ind = g["mesh"] + g["box"]
    model_dir = emitter_irradiance(rl, P, N, NEE_SAMPLES, rng, scene=room_rays)
    total = expo * meters(scene, P, N, spp, indirect=False)
    indirect = expo * meters(scene, P, N, spp, indirect=True)
    facing = np.arange(len(P)) % len(face)
    by = {name: {"model_over_mitsuba": _ratio(model_ind[facing == j] + model_dir[facing == j], total[facing == j]),
                 "mitsuba_direct_share": _ratio(total[facing == j] - indirect[facing == j], total[facing == j])}
          for j, name in enumerate(FACINGS)}
    return {"points": int(len(P)), "model_over_mitsuba": _ratio(model_ind + model_dir, total),
            "direct_over_mitsuba": _ratio(model_dir, total - indirect),
            "indirect_over_mitsuba": _ratio(model_ind, indirect),
            "mitsuba_direct_share": _ratio(total - indirect, total), "by_facing": by}


def chart(results: list[dict], path: Path) -> None:
    """Per room, the model's light besides the emitters over Mitsuba's (per group and the unseen ceiling) and all of
    its light at the objects' places (r g b)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = [*GROUPS, "unseen ceiling", "objects"]
    variants = list(dict.fromkeys(r["variant"] for r in results))
    rooms = list(dict.fromkeys(r["room"] for r in results))
    fig, axes = plt.subplots(len(variants), len(rooms), figsize=(max(6.0, 3.6 * len(rooms)), 3.4 * len(variants)),
                             squeeze=False, sharey=True)
    for r in results:
        ax = axes[variants.index(r["variant"])][rooms.index(r["room"])]
        for j, g in enumerate(cols):
            v = (r["unseen_ceiling"]["radiance_over_mitsuba"] if g == "unseen ceiling" and "unseen_ceiling" in r else
                 r["objects"]["model_over_mitsuba"] if g == "objects" and "objects" in r else
                 r["groups"].get(g, {}).get("model_over_mitsuba"))
            if v is None:
                continue
            for c, (val, colour) in enumerate(zip(v, ("tab:red", "tab:green", "tab:blue"))):
                ax.bar(j + (c - 1) * 0.25, val, 0.25, color=colour)
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_xticks(range(len(cols)), cols, rotation=30)
        ax.set_title(f"{r['room']}, {r['variant']} ({r['seconds']:.0f} s)", fontsize=9)
    for row in axes:
        row[0].set_ylabel("fitted light / Mitsuba's (r g b)")
    fig.suptitle("light besides the emitters: photographed points, unseen ceiling; all light: the objects' places")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.lightprobe", description=__doc__.split("\n\n")[0])
    p.add_argument("--suite", default=str(SUITE))
    p.add_argument("--work", default=str(WORK), help="bench.lighting's work folder (ROOM/fit: the fit run)")
    p.add_argument("--rooms", default="spot,window")
    p.add_argument("--variants", default="fit", help="the run folders under each room (fit, oracle, fit-s1, ...)")
    p.add_argument("--out", default=None, help=f"output prefix (default {RESULTS / 'lightprobe'}; required with a "
                   "tuning-only room, bench.lightsuite.DEV_ROOMS)")
    p.add_argument("--spp", type=int, default=SPP)
    p.add_argument("--rays", type=int, default=RAYS)
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    rooms = room_list(a.rooms, ())
    variants = [v for v in a.variants.split(",") if v]
    if why := tuning_rooms_need_out(rooms, a.out, "/tmp/dev/lightprobe"):
        p.error(f"--rooms {a.rooms}: {why}")
    a.out = a.out or str(RESULTS / "lightprobe")
    missing = [f"{r}/{v}" for r in rooms for v in variants
               if not (Path(a.work) / r / v).is_dir() or not (Path(a.suite) / r).is_dir()]
    if missing:
        print(f"bench.lightprobe: no run or suite room for {', '.join(missing)} (under {a.work} and {a.suite}); run "
              f"bench.lighting on them first", file=sys.stderr)
        return 2
    res = []
    for v in variants:
        for r in rooms:
            res.append({"variant": v, **probe_room(Path(a.suite) / r, Path(a.work) / r / v, rays=a.rays, spp=a.spp)})
            log.info("%s %s: %s; objects %s", r, v, json.dumps(res[-1]["groups"].get("all", {})),
                     res[-1]["objects"]["model_over_mitsuba"])
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"what": __doc__.split("\n\n")[0], "rays": a.rays, "spp": a.spp,
                                                    "rooms": res}, indent=1) + "\n")
    chart(res, out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
