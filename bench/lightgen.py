"""Generated light suite: random rooms from a seed, so that the light fit is tuned on some seeds and reported on
others, never on the rooms it was tuned on.

Each seed draws (:func:`generated_spec`) the room's wall, floor, table and furniture colours (grey paint or a
strong hue per wall), one or two kinds of light (warm to cool ceiling panels, a window, a small spot high over
the table that casts hard shadows, a lamp on the wall behind the table), their places, sizes and colours, the
photos' exposure level, three of the eight LM-O objects, and the capture: a whole room (frames on an arc round
the table) or one view. The camera's grey-world white balance is applied to the photos and the truth, as a real
camera's automatic white balance would. Rendered by :func:`bench.lightsuite.build_room` (Mitsuba 3, the truth
with the objects the same way as the suite's six rooms), small by default (:data:`SMALL`).

The room's box (4 x 5 x 2.6 m), table and furniture places are the suite's: the camera arc and the object
placement are built around them. What varies is what the light fit must tell apart: surface colours, lights,
capture.

Seeds: :data:`TUNE_SEEDS` for choosing the fit's settings, :data:`HELD_OUT_SEEDS` for the figures
(``bench.lighting --generated``).

Run: ``nice .venv/bin/python -m bench.lightgen [--seeds 0-3,100-109] [--set trace.KEY=VALUE]``: renders the
rooms missing from ``bench/cache/lightgen``, runs the pipeline's fit variant on each (:func:`bench.lighting.run_room`:
the objects at their true poses, the real CLI) and writes bench/results/lightgen.json and lightgen.png. Per room,
over its frames' object pixels: PSNR (8-bit sRGB), luminance of ours over the truth's, and the angle between
ours and the truth's mean linear colour. Targets (held-out seeds): PSNR mean >= 28 dB and no room below 22 dB;
luminance within 10 % and colour within 3 degrees in 80 % of the rooms.
"""

from __future__ import annotations

import argparse
import colorsys
import dataclasses
import logging
import sys
import time
from pathlib import Path

import numpy as np

from bench.lightsuite import (COOL, LEVEL, NEUTRAL, ROOM_SIZE, TABLE_CENTRE, TABLE_HEIGHT, WARM, RoomSpec,
                              _panel, build_room, room_spec, square_spp)

log = logging.getLogger("bench.lightgen")

SMALL = {"width": 320, "height": 240, "spp_photo": 16, "spp_crop": 36, "spp_objects": 256, "texture_size": 128}
WHOLE_FRAMES = 4
TUNE_SEEDS = tuple(range(0, 4))
HELD_OUT_SEEDS = tuple(range(100, 110))
LMO_IDS = (1, 5, 6, 8, 9, 10, 11, 12)
GEN_SEED = 7_000_000          # room_seed = GEN_SEED + seed (apart from the suite's rooms' seeds)
LIGHT_KINDS = ("ceiling", "window", "spot", "lamp_in_view")


def room_name(seed: int) -> str:
    return f"gen-{seed:04d}"


def _colour(rng: np.random.Generator, strong: bool) -> tuple[float, float, float]:
    """A linear albedo: a light, slightly tinted grey, or a strong hue."""
    if strong:
        r, g, b = colorsys.hsv_to_rgb(rng.uniform(0, 1), rng.uniform(0.6, 0.9), rng.uniform(0.35, 0.65))
    else:
        r, g, b = colorsys.hsv_to_rgb(rng.uniform(0, 1), rng.uniform(0.0, 0.12), rng.uniform(0.5, 0.8))
    return (round(r, 3), round(g, 3), round(b, 3))


def _tint(rng: np.random.Generator) -> np.ndarray:
    """A light's colour between warm and cool white."""
    t = rng.uniform(0, 1)
    return WARM * (1 - t) + COOL * t if rng.uniform() < 0.8 else NEUTRAL


def _lights(rng: np.random.Generator, kinds: list[str]) -> list:
    X, Y, Z = ROOM_SIZE
    ex, ey, ez = np.eye(3)
    tx, ty = TABLE_CENTRE
    zc = Z - 0.005
    out = []
    for kind in kinds:
        col = _tint(rng)
        if kind == "ceiling":
            for i in range(int(rng.integers(1, 4))):
                s = rng.uniform(0.3, 0.8)
                c = (rng.uniform(0.8, X - 0.8), rng.uniform(0.8, Y - 0.8), zc)
                out.append(_panel(f"ceiling_{i}", c, s * ey, s * ex, rng.uniform(6, 20) * col * (0.6 / s) ** 2,
                                  f"ceiling panel {s:.2f} m"))
        elif kind == "window":
            y = rng.uniform(1.2, Y - 1.2)
            out.append(_panel("window", (X - 0.005, y, 1.6), 1.0 * ez, 1.4 * ey, rng.uniform(15, 40) * COOL,
                              "window on wall x = 4, cool daylight"))
        elif kind == "spot":
            c = (tx + rng.uniform(-0.6, 0.6), ty + rng.uniform(-0.4, 0.6), TABLE_HEIGHT + rng.uniform(1.0, 1.35))
            s = rng.uniform(0.06, 0.15)
            out.append(_panel("spot", c, s * ey, s * ex, rng.uniform(800, 2000) * col * (0.1 / s) ** 2,
                              f"{100 * s:.0f} cm spot over the table: hard shadows"))
        else:
            out.append(_panel("wall_panel", (tx + rng.uniform(-0.8, 0.8), Y - 0.005, rng.uniform(1.2, 1.7)),
                              0.4 * ex, 0.6 * ez, rng.uniform(25, 50) * col, "panel on the wall behind the table"))
    return out


def generated_spec(seed: int) -> tuple[RoomSpec, dict]:
    """The room of ``seed`` and how to capture it: ``{"frames", "obj_ids", "capture", "lights"}``."""
    rng = np.random.default_rng(seed)
    base = room_spec("ceiling")             # geometry and textures kinds of the suite's room
    strong = rng.uniform() < 0.5
    walls = {w: _colour(rng, strong and rng.uniform() < 0.6) for w in ("wall_x0", "wall_x1", "wall_y0", "wall_y1")}
    other = {"floor": _colour(rng, rng.uniform() < 0.2), "table_top": _colour(rng, rng.uniform() < 0.3),
             "shelf": _colour(rng, False), "cabinet": _colour(rng, rng.uniform() < 0.3),
             "box": _colour(rng, False)}
    surfaces = []
    for s in base.surfaces:
        alb = walls.get(s.name) or other.get(s.name)
        if s.name == "floor" or s.name == "table_top":
            alb = tuple(round(0.6 * a, 3) for a in alb)          # floors and tables darker than walls
        surfaces.append(s if alb is None else dataclasses.replace(s, base=alb))
    kinds = sorted(rng.choice(LIGHT_KINDS, size=int(rng.integers(1, 3)), replace=False).tolist())
    level = float(rng.uniform(0.7, 1.15) * LEVEL)
    capture = "one-view" if rng.uniform() < 0.35 else "whole"
    obj_ids = tuple(sorted(int(i) for i in rng.choice(LMO_IDS, size=3, replace=False)))
    spec = RoomSpec(room_name(seed), surfaces, _lights(rng, kinds), level, white_balance=True)
    return spec, {"frames": 1 if capture == "one-view" else WHOLE_FRAMES, "obj_ids": obj_ids,
                  "capture": capture, "lights": kinds, "walls": walls}


def build_generated(out: str | Path, seeds, small: dict = SMALL, rebuild: bool = False) -> dict[str, dict]:
    """Render the rooms of ``seeds`` into ``out`` (complete ones kept); each room's room.json record."""
    res = {}
    for seed in seeds:
        spec, how = generated_spec(seed)
        t0 = time.perf_counter()
        rec = build_room(Path(out), spec.name, frames=how["frames"], width=small["width"], height=small["height"],
                         spp_photo=square_spp(small["spp_photo"]), spp_crop=square_spp(small["spp_crop"]),
                         spp_objects=square_spp(small["spp_objects"]), obj_ids=how["obj_ids"],
                         texture_size=small["texture_size"], rebuild=rebuild, spec=spec,
                         room_seed=GEN_SEED + seed)
        rec["generated"] = how
        res[spec.name] = rec
        log.info("%s (%s, %s) ready in %.0f s", spec.name, how["capture"], "+".join(how["lights"]),
                 time.perf_counter() - t0)
    return res


def seed_list(text: str) -> list[int]:
    """``"0-5,100"`` -> [0, 1, 2, 3, 4, 5, 100]."""
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part:
            a, b = part.split("-")
            out += list(range(int(a), int(b) + 1))
        elif part:
            out.append(int(part))
    return out


def room_figures(res: dict, variant: str = "fit") -> dict:
    """PSNR, luminance ratio and colour angle of one room's ``variant`` (``bench.lighting.run_room``'s record)."""
    from pipeline.color import LUMINANCE_F64

    v = res["variants"][variant]
    fr = [f for f in v["per_frame"] if f]
    truth = np.mean([f["truth_mean"] for f in fr], axis=0)
    ours = np.mean([np.asarray(f["brightness"]) * np.asarray(f["truth_mean"]) for f in fr], axis=0)
    cosang = float(ours @ truth / max(np.linalg.norm(ours) * np.linalg.norm(truth), 1e-12))
    return {"psnr_objects": round(v["psnr_objects"], 2), "psnr_band": round(v["psnr_band"], 2),
            "luminance_ratio": round(float(ours @ LUMINANCE_F64 / max(truth @ LUMINANCE_F64, 1e-12)), 4),
            "colour_deg": round(float(np.degrees(np.arccos(min(1.0, cosang)))), 2),
            "fit_s": round(v.get("fit_s", 0.0), 1), "note": (v.get("fit") or {}).get("note", "")}


def group_figures(rows: dict[str, dict]) -> dict:
    """The targets' figures over rooms ``rows`` (name -> :func:`room_figures`)."""
    if not rows:
        return {}
    ps = np.array([r["psnr_objects"] for r in rows.values()])
    lum = np.array([abs(r["luminance_ratio"] - 1) <= 0.10 + 1e-9 for r in rows.values()])
    col = np.array([r["colour_deg"] <= 3.0 + 1e-9 for r in rows.values()])
    return {"rooms": len(rows), "psnr_objects_mean": round(float(ps.mean()), 2),
            "psnr_objects_min": round(float(ps.min()), 2),
            "luminance_within_10pct_share": round(float(lum.mean()), 3),
            "colour_within_3deg_share": round(float(col.mean()), 3),
            "targets_met": bool(ps.mean() >= 28 and ps.min() >= 22 and lum.mean() >= 0.8 and col.mean() >= 0.8)}


def evaluate(cache: Path, work: Path, seeds, sets: list[str], out: Path | None) -> dict:
    """Render what is missing, run the fit variant on every room and write the results."""
    from bench import lighting
    from bench.common import RESULTS, BenchResult

    recs = build_generated(cache, seeds)
    lighting.SETTINGS["fit"] = ["trace.lighting=fit", *sets]
    rows, groups = {}, {"tuned_on": {}, "held_out": {}}
    for seed in seeds:
        name = room_name(seed)
        res = lighting.run_room(cache / name, work / name, ("fit",))
        rows[name] = {"seed": seed, **recs[name]["generated"], **room_figures(res)}
        rows[name].pop("walls", None)
        groups["held_out" if seed in HELD_OUT_SEEDS else "tuned_on"][name] = rows[name]
        log.info("%s %s %s: objects %.2f dB, luminance %.3f, colour %.1f deg", name, rows[name]["capture"],
                 "+".join(rows[name]["lights"]), rows[name]["psnr_objects"], rows[name]["luminance_ratio"],
                 rows[name]["colour_deg"])
    figures = {g: group_figures(r) for g, r in groups.items()}
    res = BenchResult("lightgen", speed_label="light fit CPU seconds per room",
                      accuracy_label="objects PSNR against Mitsuba's truth, dB")
    for g, r in groups.items():
        for name, row in r.items():
            res.add_point(g, speed=row["fit_s"], accuracy=row["psnr_objects"], label=name[4:])
    res.figures.update({"groups": figures, "rooms": rows, "settings": sets, "small": SMALL})
    res.write(out or RESULTS)
    return figures


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cache", default="bench/cache/lightgen")
    p.add_argument("--work", default="runs/bench-lightgen")
    p.add_argument("--seeds", default=",".join(map(str, TUNE_SEEDS + HELD_OUT_SEEDS)))
    p.add_argument("--set", action="append", default=[], help="extra TABLE.KEY=VALUE for the fit (tuning)")
    p.add_argument("--out", default="", help="results folder (default bench/results)")
    p.add_argument("--render-only", action="store_true", help="render the rooms, run nothing")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", stream=sys.stdout)
    seeds = seed_list(a.seeds)
    if a.render_only:
        build_generated(a.cache, seeds)
        return 0
    figures = evaluate(Path(a.cache), Path(a.work).resolve(), seeds, a.set, Path(a.out) if a.out else None)
    print(figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
