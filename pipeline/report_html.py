"""``RUN/report.html``: one page that shows what a run made and what it threw away, without opening JSON.

Written by ``scansynth report RUN`` and at the end of every ``scansynth run``. Everything on it is read
from the files the stages wrote (nothing is recomputed): ``run.json`` (timings, failures, left-out
inputs, rejections), ``select/<scene>/selection.json`` (frame selection with scores),
``ingest/<scene>/scan.json`` (frames read and kept, registration, up), ``prep``'s object record (what
each model took to become a solid), the BOP dataset (sample images with the visible masks, boxes and
pose axes drawn from the written annotations by :func:`pipeline.preview.draw_annotations`) and each scene's
fitted lights ``trace/<scene>/lights.npz`` (a top view of the room with its emitters and two photos with
theirs, drawn by :mod:`pipeline.lightpanel`, beside what the fit found and assumed).

The page is self-contained: no server, nothing fetched from the network; the chart and the thumbnails
are embedded as ``data:`` URIs, and each thumbnail links to its full-size annotated image in
``RUN/report/`` (a relative link, so the run folder can be moved or copied as a whole); the lighting
pictures are embedded at their full 480 px (the photos as JPEG) and link to their PNG in
``RUN/report/lighting/``. The timings make the page differ from run to run; the images do not.
"""

from __future__ import annotations

import base64
import html
import io
import json
import logging
from pathlib import Path

import numpy as np

from pipeline.bop_layout import SPLIT
from pipeline.errors import UserError
from pipeline.io import atomic_write_bytes, encode_image
from pipeline.runfolder import (DATASET_DIR, ROOM_LIGHTS_TPATH, SCAN_TPATH, SELECTION_TPATH, list_scenes, load_scan,
                                path)

log = logging.getLogger(__name__)

REPORT_NAME = "report.html"
ASSETS_DIR = "report"          # RUN/report/: full-size annotated sample images
LIGHTING_DIR = ASSETS_DIR + "/lighting"   # RUN/report/lighting/: the lighting panel's pictures
MAX_SAMPLES = 12
THUMB_WIDTH = 320
# Frame-selection scores (selection.json) in the order the table shows them; others follow by name.
SCORE_ORDER = ("relative", "blur_effect", "detail", "noise", "brightness", "contrast", "angle_deg", "travel_m")

STYLE = """
body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0;background:#f6f7f9;color:#1d2330}
header{background:#1d2330;color:#fff;padding:18px 28px}header h1{margin:0;font-size:22px}
header p{margin:4px 0 0;color:#b8c0cf;font-size:13px}
main{padding:8px 28px 40px;max-width:1400px}
section{background:#fff;border:1px solid #e1e4ea;border-radius:8px;margin:18px 0;padding:14px 18px}
h2{font-size:17px;margin:2px 0 10px}h3{font-size:15px;margin:14px 0 6px}h4{font-size:13px;margin:10px 0 4px}
.tiles{display:flex;flex-wrap:wrap;gap:12px}
.stat{background:#f0f3f8;border-radius:6px;padding:8px 14px;min-width:120px}
.stat b{display:block;font-size:22px}.stat span{color:#5b6475;font-size:12px}
table{border-collapse:collapse;font-size:13px;margin:4px 0}
td,th{border-bottom:1px solid #e6e8ee;padding:3px 10px 3px 0;text-align:left;vertical-align:top}
th{color:#5b6475;font-weight:600}td.num{text-align:right;font-variant-numeric:tabular-nums}
.grid{display:grid;grid-template-columns:repeat(auto-fill,minmax(300px,1fr));gap:12px}
.grid figure{margin:0}.grid img{width:100%;border-radius:4px;display:block}
figcaption{font-size:12px;color:#5b6475;margin-top:3px}
.ok{color:#1b7f3b}.bad{color:#b3261e}.muted{color:#7a8294}
details summary{cursor:pointer;color:#33507a}
"""


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _read(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _data_uri(data: bytes, mime: str) -> str:
    return f"data:{mime};base64," + base64.b64encode(data).decode("ascii")


def _table(header: list[str], rows: list[list], numeric: set[int] = frozenset()) -> str:
    head = "".join(f"<th>{_e(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td class=num>{_e(c)}</td>" if i in numeric else f"<td>{_e(c)}</td>"
                                    for i, c in enumerate(r)) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


FOLD_ROWS = 10   # longer lists are folded (one click shows them) so the page stays readable


def _folded(header: list[str], rows: list[list]) -> str:
    """A table, folded behind a one-line summary when it has more than FOLD_ROWS rows."""
    if len(rows) <= FOLD_ROWS:
        return _table(header, rows)
    first = ", ".join(str(r[0]) for r in rows[:3])
    return (f"<details><summary>show all {len(rows)} ({_e(first)}, ...)</summary>"
            + _table(header, rows) + "</details>")


def stage_chart(stages: list[dict]) -> bytes | None:
    """PNG bar chart of seconds per stage (``run.json`` stage entries), or None with no stage."""
    if not stages:
        return None
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    names = [s["stage"] for s in stages]
    secs = [float(s.get("seconds", 0.0)) for s in stages]
    fig = Figure(figsize=(7.0, 0.42 * len(names) + 0.9), dpi=100)
    ax = fig.add_subplot(111)
    y = np.arange(len(names))[::-1]
    ax.barh(y, secs, color="#4c78a8")
    ax.set_yticks(y, names)
    for yi, s, st in zip(y, secs, stages):
        n = int(st.get("done", 0)) + int(st.get("skipped", 0))
        ax.text(s, yi, f"  {s:.1f} s ({n} item{'s' if n != 1 else ''})", va="center", fontsize=8)
    ax.set_xlabel("seconds this invocation (wall)")
    ax.set_xlim(0, max(secs + [1e-3]) * 1.35)
    ax.spines[["top", "right"]].set_visible(False)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    return buf.getvalue()


def _samples(run: Path, max_samples: int) -> tuple[str, list[str]]:
    """HTML of the sample grid and the notes on what could not be drawn. Writes the full-size annotated
    images to ``RUN/report/`` and removes the ones an earlier invocation wrote that are not shown now."""
    import cv2

    from pipeline.preview import annotated_samples

    notes: list[str] = []
    dataset = run / DATASET_DIR
    assets = run / ASSETS_DIR
    written: set[str] = set()
    try:
        if not (dataset / SPLIT).is_dir():
            return "<p class=muted>No dataset yet (the export stage has not run).</p>", notes
        n_images, samples = annotated_samples(dataset, max_samples)
        if not n_images:
            return "<p class=muted>The dataset has no images: every frame was rejected (see below).</p>", notes
        figs = []
        for s in samples:
            if s.image is None:
                notes.append(s.problem)
                continue
            # PNG: JPEG's chroma subsampling smears the 1-px coloured outlines the full size is for
            name = f"{s.scene_dir.parent.name}_{s.scene_dir.name}_{s.im_id:06d}.png"
            rel = f"{ASSETS_DIR}/{name}"
            atomic_write_bytes(run / rel, encode_image(run / rel, s.image))
            written.add(name)
            h = int(round(s.image.shape[0] * THUMB_WIDTH / s.image.shape[1]))
            thumb = cv2.resize(s.image, (THUMB_WIDTH, h), interpolation=cv2.INTER_AREA)
            _, jpg = cv2.imencode(".jpg", np.ascontiguousarray(thumb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 85])
            objs = ", ".join(str(g.get("obj_id", "?")) for g in s.gts)
            visib = [float(i.get("visib_fract", 0.0)) for i in s.infos]
            cap = (f"{s.scene_dir.name}/{s.im_id:06d}: {len(s.gts)} objects ({objs})"
                   + (f", visible {min(visib):.0%}-{max(visib):.0%}" if visib else ""))
            figs.append(f'<figure><a href="{_e(rel)}"><img src="{_data_uri(jpg.tobytes(), "image/jpeg")}" '
                        f'alt="{_e(cap)}"></a><figcaption>{_e(cap)}</figcaption></figure>')
        text = (f"<p>{len(figs)} of {n_images} images, evenly spread; outlines: visible masks "
                f"(<code>mask_visib</code>), rectangles: <code>bbox_visib</code>, axes: the pose "
                f"(x red, y green, z blue, half the model's diameter). Click an image for full size.</p>")
        return text + '<div class="grid">' + "".join(figs) + "</div>", notes
    finally:
        for old in [*assets.glob("*.png"), *assets.glob("*.jpg")] if assets.is_dir() else ():
            if old.name not in written:   # an earlier invocation's sample that is not on the page now
                old.unlink(missing_ok=True)


def _rejections(report: dict, run: Path) -> str:
    from pipeline import report as run_report

    rej = report.get("rejected") or run_report.rejected(run)
    parts = []
    fails = [(s["stage"], k, v) for s in report.get("stages", []) for k, v in s.get("failures", {}).items()]
    probs = [(s["stage"], k, line) for s in report.get("stages", [])
             for k, lines in s.get("input_problems", {}).items() for line in lines]
    parts.append("<h3>Failed items</h3>" + (_table(["stage", "item", "error"], [list(f) for f in fails])
                                            if fails else "<p class=ok>None.</p>"))
    parts.append("<h3>Inputs left out</h3>" + (_table(["stage", "item", "what and why"], [list(p) for p in probs])
                                               if probs else "<p class=ok>None.</p>"))
    sel = rej.get("select", {})
    rows = [[scene, reason, n] for scene, d in sel.items() for reason, n in d.items()]
    parts.append("<h3>Frames not selected</h3>" + (_table(["scene", "reason", "frames"], rows, {2}) if rows
                                                   else "<p class=ok>None.</p>"))
    drops = rej.get("drops", {})
    parts.append(f"<h3>Rejected drops ({len(drops)})</h3>" + (
        _folded(["drop", "verdict"], [[k, v] for k, v in drops.items()]) if drops else "<p class=ok>None.</p>"))
    frames = rej.get("frames", {})
    parts.append(f"<h3>Frames rejected after the drop ({len(frames)})</h3>" + (
        _folded(["frame", "reason"], [[k, v] for k, v in frames.items()]) if frames else "<p class=ok>None.</p>"))
    left = rej.get("export", {})
    parts.append(f"<h3>Frames left out of the dataset ({len(left)})</h3>" + (
        _folded(["frame", "reason"], [[k, v] for k, v in left.items()]) if left else "<p class=ok>None.</p>"))
    return "".join(parts)


def _scans(run: Path) -> str:
    out = []
    scenes = sorted(p.parent.name for p in run.glob(SCAN_TPATH.format(scene="*")))
    if not scenes:
        return "<p class=muted>No scan ingested yet.</p>"
    for scene in scenes:
        doc = _read(path(run, SCAN_TPATH, scene=scene)) or {}
        meta = doc.get("meta", {})
        facts = [["format", doc.get("format", "?")],
                 ["frames read / kept after reading", f"{meta.get('frames_read', '?')} / {meta.get('frames_kept', '?')}"],
                 ["image size", f"{doc.get('width', '?')} x {doc.get('height', '?')}"],
                 ["room mesh", f"{meta.get('mesh', '?')} ({meta.get('mesh_faces', '?')} faces)"],
                 ["up", meta.get("up_source", "?")]]
        if meta.get("registration"):
            facts.append(["colour-depth registration", meta["registration"]])
        skipped = {k: v for k, v in (meta.get("skipped") or {}).items() if v}
        if skipped:
            facts.append(["frames skipped on reading", ", ".join(f"{k}: {v}" for k, v in skipped.items())])
        for w in meta.get("warnings", []):
            facts.append(["warning", w])
        block = f"<h3>{_e(scene)}</h3>" + _table(["", ""], facts) + _registration(meta)
        sel = _read(path(run, SELECTION_TPATH, scene=scene))
        if sel:
            frames = sel.get("frames", [])
            kept = sum(1 for f in frames if f.get("kept"))
            # every score the selection recorded, in the order of SCORE_ORDER, then the rest by name
            found = {k for f in frames for k in (f.get("scores") or {})}
            keys = [k for k in SCORE_ORDER if k in found] + sorted(found - set(SCORE_ORDER))
            rows = [[f.get("frame_id"), "kept" if f.get("kept") else "dropped", f.get("reason", "")]
                    + [_num((f.get("scores") or {}).get(k)) for k in keys] for f in frames]
            block += (f"<details><summary>Frame selection: {kept} of {len(frames)} frames kept "
                      f"(method {_e(sel.get('method', '?'))})</summary>"
                      + _table(["frame", "", "reason", *keys], rows, set(range(3, 3 + len(keys))))
                      + "</details>")
        out.append(block)
    return "".join(out)


def _damaged(run: Path, what: str, e: Exception) -> str:
    log.warning("report: %s of %s could not be drawn (%s: %s)", what, run, type(e).__name__, e)
    return (f"<p class=bad>The {_e(what)} could not be drawn: a file of this run folder is damaged or from "
            f"another version ({_e(type(e).__name__)}: {_e(e)}). Re-run the stage that wrote it.</p>")


def _guarded(run: Path, what: str, fn, *args) -> str:
    """A section from files a user may have edited or damaged: its error is shown in its place, and
    the rest of the page is still written."""
    try:
        return fn(*args)
    except (OSError, ValueError, TypeError, AttributeError, KeyError, IndexError) as e:
        return _damaged(run, what, e)


def _num(v) -> str:
    try:
        return f"{float(v):.3f}"
    except (TypeError, ValueError):
        return "" if v is None else str(v)


def _registration(meta: dict) -> str:
    """Colour-depth registration figures of one scan (``scan.json`` meta ``registration_figures``).

    The hook for the registration issue: ingest records no figures yet, so this section is left out;
    once ingest writes ``meta["registration_figures"]`` as ``{name: value}`` (a number or text, e.g.
    the estimated colour focal length and the edge alignment before/after), they appear here as a table.
    """
    figs = meta.get("registration_figures")
    if not isinstance(figs, dict) or not figs:
        return ""
    return "<h4>Colour-depth registration</h4>" + _table(["figure", "value"],
                                                          [[k, _num(v)] for k, v in figs.items()], {1})


def _objects(run: Path) -> str:
    lib = _read(run / "ingest" / "objects" / "library.json")
    prep = (_read(run / "prep" / "_items" / "objects.done.json") or {}).get("objects", {})
    if not lib and not prep:
        return "<p class=muted>No object library ingested yet.</p>"
    entries = lib.get("objects", lib) if isinstance(lib, dict) else (lib or [])
    names = {}
    if isinstance(entries, list):
        names = {str(o.get("obj_id")): o.get("name", "") for o in entries if isinstance(o, dict)}
    rows = [[k, names.get(k, ""), f"{float(v.get('mass', 0.0)) * 1000:.1f}",
             "convex hull (could not be closed)" if v.get("fallback_hull") else "solid",
             v.get("repair", "")] for k, v in sorted(prep.items(), key=lambda kv: int(kv[0]))]
    return _table(["id", "name", "mass g", "mass properties from", "what it took"], rows, {2})


def _lighting(run: Path) -> str:
    """Each scene's fitted lights (``trace/<scene>/lights.npz``): pictures and what the fit found and assumed,
    or one line on why there are none. Writes the pictures to ``RUN/report/lighting/`` and removes the ones
    an earlier invocation wrote that are not shown now."""
    assets = run / LIGHTING_DIR
    written: set[str] = set()
    try:
        scenes = list_scenes(run)
        if not scenes:
            return "<p class=muted>No scan ingested yet.</p>"
        mode = _lighting_mode(run)
        return "".join(f"<h3>{_e(scene)}</h3>" + _guarded(run, f"lighting panel of {scene}", _scene_lighting,
                                                          run, scene, mode, written) for scene in scenes)
    finally:
        for old in sorted(assets.glob("*.png")) if assets.is_dir() else ():
            if old.name not in written:
                old.unlink(missing_ok=True)
        if assets.is_dir() and not any(assets.iterdir()):
            assets.rmdir()


def _lighting_mode(run: Path) -> str:
    """``trace.lighting`` of the run's config.toml (its default where the file does not say)."""
    import tomllib

    from pipeline.config import TraceConfig

    try:
        mode = tomllib.loads((run / "config.toml").read_text(encoding="utf-8")).get("trace", {}).get("lighting")
    except (OSError, ValueError, AttributeError):
        mode = None
    return str(mode) if mode else TraceConfig().lighting


def _scene_lighting(run: Path, scene: str, mode: str, written: set[str]) -> str:
    """The lighting panel of one scene (see :func:`_lighting`); the pictures' names are added to ``written``."""
    import zipfile

    from pipeline.lightpanel import emitters_of
    from pipeline.trace.lightfit import RoomLights

    rel = ROOM_LIGHTS_TPATH.format(scene=scene)
    if not (run / rel).is_file():
        if mode != "fit":
            return (f'<p class=muted>No fitted lights: trace.lighting is "{_e(mode)}" (set it to "fit" to '
                    f"recover the room's lights from its photos).</p>")
        return f"<p class=muted>No fitted lights yet: the trace stage has not fitted them ({_e(rel)} is absent).</p>"
    try:
        rl = RoomLights.load(run / rel)
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as e:
        return (f"<p class=bad>The fitted lights in {_e(rel)} cannot be read ({_e(type(e).__name__)}: {_e(e)}); "
                f"re-run the trace stage.</p>")
    scan = load_scan(run, scene)
    emitters = emitters_of(rl.summary)
    have = [i for i, p in enumerate(scan.color_paths) if p]
    shown = list(zip("AB", sorted({have[0], have[-1]}))) if have else []
    figs, inview = _light_pictures(run, scene, rl, scan, emitters, shown, written)
    stale = (f'<p class=bad>trace.lighting is "{_e(mode)}" now: these lights are from an earlier run that fitted '
             f"them.</p>") if mode != "fit" else ""
    return (stale + '<div class="grid">' + "".join(figs) + "</div>"
            + "<p>Top view: the room from above (down the scan's up), coloured by the albedo the fit found; "
              "discs: the emitters, their area following their share of the power and their colour the "
              "light's, numbered brightest first; blue: the cameras of the scan, A and B those of the photos. "
              "On a photo a ring marks an emitter in view (it may be hidden behind a surface), an arrow at "
              "the border the way to one outside it (or behind the camera).</p>"
            + _light_facts(rl.summary, emitters) + _emitter_table(rl, scan, emitters, shown, inview))


def _light_pictures(run: Path, scene: str, rl, scan, emitters: list, shown: list, written: set[str]) -> tuple:
    """The top view and the photos of the panel as HTML figures (written to ``RUN/report/lighting/``), and
    for each shown photo where each emitter is ("in view", "outside", "behind")."""
    from pipeline.errors import InputError
    from pipeline.lightpanel import border_arrow, draw_photo, draw_top, top_view, vertex_colours
    from pipeline.scanformats.common import read_color

    nv, nt = rl.num_mesh_vertices, rl.num_mesh_tris
    V, F = rl.vertices[:nv], rl.faces[:nt]
    poses = scan.T_c2w
    view = top_view(np.concatenate([V, np.reshape([e.centre for e in emitters], (-1, 3)), poses[:, :3, 3]]),
                    scan.up_w)
    colours, gain = vertex_colours(rl.albedo[:nv] if rl.albedo is not None else None, rl.radiance[:nv])
    top = draw_top(view, V, F, colours, emitters, poses, facing=int(rl.summary.get("seen_side", 1) or 0),
                   marked={label: poses[i] for label, i in shown})
    caption = f"top view, {len(emitters)} emitters" + (f"; the albedo shown {gain:.1f}x brighter" if gain > 1 else "")
    figs = [_light_figure(run, f"{scene}_top.png", top, caption, written)]
    inview: dict[str, list[str]] = {}
    for label, i in shown:
        cam = scan.camera(i)
        inview[label] = ["in view" if border_arrow(cam, e.centre) is None
                         else "behind" if cam.w2c(e.centre[None])[0, 2] <= 0 else "outside" for e in emitters]
        what = f"{label}: frame {int(scan.frame_ids[i])}"
        try:
            photo = read_color(scan, i)
        except InputError as e:
            figs.append(f"<figure><p class=bad>{_e(what)}: {_e(e)}</p></figure>")
            continue
        figs.append(_light_figure(run, f"{scene}_frame{int(scan.frame_ids[i]):06d}.png",
                                  draw_photo(photo, cam, emitters, label=what), what, written, photo=True))
    return figs, inview


def _light_figure(run: Path, name: str, image: np.ndarray, caption: str, written: set[str], *,
                  photo: bool = False) -> str:
    """A figure of the lighting panel: ``image`` written to ``RUN/report/lighting/<name>`` (PNG) and embedded
    in the page (a photo as JPEG, a third of the PNG's size; the top view's flat colours as the PNG)."""
    import cv2

    rel = f"{LIGHTING_DIR}/{name}"
    data = encode_image(run / rel, image)
    atomic_write_bytes(run / rel, data)
    written.add(name)
    if photo:
        _, jpg = cv2.imencode(".jpg", np.ascontiguousarray(image[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 88])
        uri = _data_uri(jpg.tobytes(), "image/jpeg")
    else:
        uri = _data_uri(data, "image/png")
    return (f'<figure><a href="{_e(rel)}"><img src="{uri}" alt="{_e(caption)}"></a>'
            f"<figcaption>{_e(caption)}</figcaption></figure>")


def _rgb_text(rgb) -> str:
    v = np.clip(np.nan_to_num(np.asarray(rgb, np.float64)), 0.0, None)
    return ", ".join(f"{x:.2f}" for x in (v / v.max() if v.max() > 0 else v))


def _light_facts(summary: dict, emitters: list) -> str:
    """What the fit found and what it assumed, in words: only what its summary holds."""
    from pipeline.color import LUMINANCE_F64

    rows = []
    note = summary.get("note") or ""
    if summary.get("fitted") and not note:
        rows.append(["result", "fitted"])
    else:
        rows.append(["result", f"not fitted: {note}" if not summary.get("fitted") else note])
    n = summary.get("num_lights", len(emitters))
    kinds: dict[str, int] = {}
    for e in emitters:
        kinds[e.kind] = kinds.get(e.kind, 0) + 1
    rows.append(["lights", f"{n} sampled as lights" + (f" ({len(emitters)} listed below)" if n != len(emitters)
                                                         else "")
                 + (": " + ", ".join(f"{v} {k}{'s' if v != 1 else ''}" for k, v in sorted(kinds.items()))
                    if kinds else "")])
    if emitters:
        power = np.array([e.area_m2 * float(e.radiance @ LUMINANCE_F64) for e in emitters])
        colour = np.sum([e.area_m2 * e.radiance for e in emitters], axis=0)
        rows.append(["power of the listed lights", f"{power.sum():.4g} (radiance x area: the photos' units x m²); "
                                                   f"the brightest carries {emitters[0].power_share:.0%}"])
        rows.append(["their colour (R, G, B; the largest 1)", _rgb_text(colour)])
    if summary.get("frames") is not None:
        exp = [float(x) for x in summary.get("exposure") or []]
        rows.append(["photos the fit explained", f"{summary['frames']}" + (
            f" (exposure {min(exp):.2f} to {max(exp):.2f})" if len(exp) > 1 else "")])
    if summary.get("albedo_level") is not None:
        rows.append(["albedo level it chose (R, G, B)",
                     ", ".join(f"{float(x):.2f}" for x in summary["albedo_level"])])
    if summary.get("albedo_mean") is not None:
        rows.append(["mean albedo of the points it fitted (R, G, B)",
                     ", ".join(f"{float(x):.2f}" for x in summary["albedo_mean"])])
    if summary.get("residual_median") is not None:
        rows.append(["median error explaining the photos' pixels (relative)",
                     f"{float(summary['residual_median']):.0%}"])
    if summary.get("capture_note"):
        rows.append(["what few views cannot pin", summary["capture_note"]])
    if summary.get("known_lights"):
        own = summary.get("own_over_known_power")
        rows.append(["lights given (trace.lights_file)", f"{summary['known_lights']}" + (
            f"; the fit added light of its own with {float(own):.2f}x their power" if own is not None else "")])
    if summary.get("lights_facing_away"):
        rows.append(["given lights facing away from every camera", _num_list(summary["lights_facing_away"])])
    if summary.get("ceiling_assumed_m") is not None:
        rows.append(["ceiling assumed where no photo saw one", f"{float(summary['ceiling_assumed_m']):.2f} m"])
    return "<h4>What the fit found and what it assumed</h4>" + _table(["", ""], rows)


def _num_list(v) -> str:
    return ", ".join(str(x) for x in v) if isinstance(v, (list, tuple)) else str(v)


def _emitter_table(rl, scan, emitters: list, shown: list, inview: dict) -> str:
    """The listed emitters, brightest first: where (height above the floor: the mesh's lowest 2 %), how large,
    their share and colour, and where each is on the shown photos."""
    if not emitters:
        return ""
    up = np.asarray(scan.up_w, np.float64)
    V = np.asarray(rl.vertices[:rl.num_mesh_vertices], np.float64)
    floor = float(np.percentile(V @ up, 2)) if len(V) else 0.0
    labels = [label for label, _ in shown]
    rows = [[k + 1, e.kind, ", ".join(f"{x:.2f}" for x in e.centre), f"{float(e.centre @ up) - floor:.2f}",
             f"{e.area_m2:.4f}", f"{e.power_share:.1%}", _rgb_text(e.radiance)] + [inview[lb][k] for lb in labels]
            for k, e in enumerate(emitters)]
    header = ["#", "kind", "centre x, y, z (m)", "height above floor (m)", "area m²", "power", "colour"] + \
        [f"photo {lb}" for lb in labels]
    return (f"<details><summary>the {len(emitters)} listed emitters</summary>"
            + _table(header, rows, {0, 3, 4, 5}) + "</details>")


def _no_rate(report: dict) -> str:
    """Why run.json has no images per hour (``pipeline.report.throughput`` gives it only for a fresh run
    through export)."""
    stages = report.get("stages", [])
    if not report:
        return "no run.json yet"
    if any(int(s.get("skipped", 0)) for s in stages):
        return "resumed run: not measured"
    if not any(s.get("stage") == "export" for s in stages):
        return "export did not run in the last invocation"
    return "no image made"


def render(run_dir: str | Path, *, max_samples: int = MAX_SAMPLES) -> str:
    """The report page of ``run_dir`` as HTML text (writes the full-size sample images beside it)."""
    run = Path(run_dir)
    report = _read(run / "run.json")
    if not isinstance(report, dict) or not all(isinstance(report.get(k, {}), dict) for k in ("throughput", "rejected")) \
            or not all(isinstance(s, dict) for s in report.get("stages", [])):
        if report is not None:
            log.warning("%s/run.json is not a scansynth run report; the page leaves it out", run)
        report = {}
    tp = report.get("throughput", {})
    stages = report.get("stages", [])
    from pipeline import report as run_report

    n_images = tp.get("images", run_report.images(run))
    rate = tp.get("images_per_hour")
    stats = [(n_images, "images in the dataset"),
             (f"{rate:.0f}" if rate else "-", "images per hour" if rate else f"images/hour ({_no_rate(report)})"),
             (f"{float(report.get('seconds', 0.0)):.0f} s" if report else "-", "wall time, last invocation"),
             (report.get("failed", "-"), "failed items"),
             (report.get("input_problems", "-"), "inputs left out")]
    tiles = "".join(f'<div class="stat"><b>{_e(v)}</b><span>{_e(k)}</span></div>' for v, k in stats)
    chart = stage_chart(stages)
    chart_html = (f'<img src="{_data_uri(chart, "image/png")}" alt="seconds per stage">' if chart
                  else "<p class=muted>No stage has run yet (run.json is missing).</p>")
    try:
        samples_html, notes = _samples(run, max_samples)
    except (OSError, ValueError, TypeError, AttributeError, KeyError, IndexError, UserError) as e:
        samples_html, notes = _damaged(run, "sample images", e), []
    if notes:
        samples_html += "<p class=bad>" + "<br>".join(_e(n) for n in notes) + "</p>"
    seed = ""
    cfg = run / "config.toml"
    if cfg.is_file():
        import tomllib

        try:
            c = tomllib.loads(cfg.read_text(encoding="utf-8"))
            parts = [f"seed {c.get('run', {}).get('seed', '?')}"]
            for label, table in (("scans", "scan"), ("objects", "objects")):
                paths = c.get(table, {}).get("paths", [])
                if paths:
                    parts.append(f"{label} {', '.join(map(str, paths))}")
            seed = "; ".join(parts)
        except (OSError, ValueError):
            seed = "config.toml could not be read"
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>scansynth run report: {_e(run.name)}</title>
<meta name="viewport" content="width=device-width, initial-scale=1"><style>{STYLE}</style></head>
<body><header><h1>scansynth run report</h1><p>{_e(run.resolve())}<br>{_e(seed)}</p></header><main>
<section><h2>Summary</h2><div class="tiles">{tiles}</div></section>
<section><h2>Seconds per stage</h2>{chart_html}</section>
<section><h2>Sample images</h2>{samples_html}</section>
<section><h2>What was thrown away, and why</h2>{_guarded(run, "rejections", _rejections, report, run)}</section>
<section><h2>Scans</h2>{_guarded(run, "scans", _scans, run)}</section>
<section><h2>Objects</h2>{_guarded(run, "objects", _objects, run)}</section>
<section><h2>Lighting</h2>{_guarded(run, "lighting panel", _lighting, run)}</section>
</main></body></html>
"""


def write_report(run_dir: str | Path, *, max_samples: int = MAX_SAMPLES) -> Path:
    """Write ``RUN/report.html`` (and ``RUN/report/``); returns its path."""
    run = Path(run_dir)
    if not run.is_dir():
        raise UserError(f"{run}: no such run folder; give the --out folder of 'scansynth run'")
    if not (run / "config.toml").is_file():
        raise UserError(f"{run}: not a scansynth run folder (no config.toml); give the --out folder of "
                        f"'scansynth run'")
    out = run / REPORT_NAME
    atomic_write_bytes(out, render(run, max_samples=max_samples).encode("utf-8"))
    return out
