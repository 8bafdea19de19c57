"""What a run folder holds so far: rejected drops and frames with their reasons, and images made.

``scansynth run`` adds this to ``run.json`` beside the per-stage timings, so one file answers "how many
images did I get, at what rate, and what was thrown away and why" without reading each stage's files.
Everything here is read from what the stages wrote (their own records stay the reference):

- ``RUN/select/<scene>/selection.json``: frames not kept, counted by reason (blurred, duplicate, ...);
- ``RUN/simulate/<scene>/drop<NNNN>.json``: each drop's verdict; the rejected ones by key;
- ``RUN/raster/summary.json``: frames rejected after the drop (objects out of view, ...) by key;
- ``RUN/export/summary.json``: frames left out of the dataset (no composite image, failed export item);
- ``RUN/export/dataset``: the RGB images of the finished dataset.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from pipeline.bop_layout import RGB_DIR, RGB_EXTS, SPLIT
from pipeline.runfolder import DATASET_DIR, SELECTION_TPATH, SUMMARY_TPATH, path

log = logging.getLogger(__name__)


def _read(path: Path) -> dict | None:
    """A JSON object, or None for a file that is missing, unreadable or not an object (damaged)."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict):
        log.warning("%s: not a JSON object; left out of the run report", path)
        return None
    return doc


def rejected(run_dir: str | Path) -> dict:
    """Rejections recorded in ``run_dir``.

    Returns
    -------
    ``{"select": {scene: {reason: count}}, "drops": {"<scene>/drop<NNNN>": verdict},
    "frames": {"<scene>/drop<NNNN>/f<frame>": reason}, "export": {"<scene>/drop<NNNN>/f<frame>": reason}}``
    (``export``: frames left out of the dataset); a stage that has not run yet gives ``{}``.
    """
    run = Path(run_dir)
    select: dict[str, dict[str, int]] = {}
    for p in sorted(run.glob(SELECTION_TPATH.format(scene="*"))):
        doc = _read(p)
        if doc is None:
            continue
        counts: dict[str, int] = {}
        frames = doc.get("frames")
        for f in frames if isinstance(frames, list) else []:
            if isinstance(f, dict) and not f.get("kept"):
                reason = str(f.get("reason") or "not kept")
                counts[reason] = counts.get(reason, 0) + 1
        select[p.parent.name] = dict(sorted(counts.items()))
    drops = {}
    for p in sorted((run / "simulate").glob("*/drop*.json")):
        doc = _read(p)
        if doc is not None and doc.get("verdict", "accepted") != "accepted":
            drops[f"{p.parent.name}/{p.stem}"] = str(doc["verdict"])
    raster = _read(path(run, SUMMARY_TPATH, stage="raster")) or {}
    export = _read(path(run, SUMMARY_TPATH, stage="export")) or {}
    return {"select": select, "drops": drops, "frames": _mapping(raster.get("rejected_frames")),
            "export": _mapping(export.get("left_out"))}


def _mapping(v) -> dict:
    return dict(v) if isinstance(v, dict) else {}


def images(run_dir: str | Path) -> int:
    """RGB images in the finished dataset (``RUN/export/dataset/train_pbr/<scene>/rgb/``)."""
    root = Path(run_dir) / DATASET_DIR
    if not root.is_dir():
        return 0
    return sum(1 for p in root.glob(f"{SPLIT}/*/{RGB_DIR}/*") if p.suffix[1:] in RGB_EXTS)


def throughput(run_dir: str | Path, stages: list[dict]) -> dict:
    """Images in the dataset and the rate this invocation made them at.

    ``stages`` are run.json's stage entries of this invocation. The rate counts only seconds spent now,
    so it is given only when every item of the listed stages ran now (a resumed run would overstate it).
    """
    n = images(run_dir)
    secs = sum(float(s["seconds"]) for s in stages)
    fresh = all(s["skipped"] == 0 for s in stages)
    out: dict = {"images": n, "seconds": round(secs, 3)}
    if fresh and n and secs > 0 and any(s["stage"] == "export" for s in stages):
        out["images_per_hour"] = round(n * 3600.0 / secs, 1)
    return out
