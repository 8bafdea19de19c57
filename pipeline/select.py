"""Frame selection stage: score every frame of a scan for blur, keep a sharp and diverse subset.

One item per scene. Outputs under ``RUN/select/<scene>/``:

``selection.json``
    ``kept`` (frame indices into the :class:`~pipeline.types.Scan` arrays, ascending), per-frame
    ``reason`` and scores, the scan-level flags ``all_blurred`` / ``none_kept`` and ``warnings``.
``scores.csv``
    The same per-frame table for a spreadsheet.
``contact_sheet.png``
    Thumbnails of every frame, framed green (kept), red (blurred), orange (near-duplicate or over
    ``max_frames``) or grey (too dark), with the score that decided.

Methods (``select.method``, scores in :mod:`pipeline.blur`): ``relative`` (default), ``thesis`` (the
published rule) and ``none`` (no blur filter). Decided behaviour of the hard cases, each tested:

* **Few edges** (plain walls): ``relative`` judges a frame against its neighbours, so a sharp
  plain-wall scan keeps its frames; frames with no measurable texture at all (std below
  :data:`pipeline.blur.TEXTURELESS_STD`) cannot show blur: they are kept with reason
  ``textureless`` and do not serve as their neighbours' reference.
* **Very dark scan**: scores are contrast-normalised, so a dim scan is judged like a bright one.
  Frames darker than ``min_brightness`` (black frames, lens covered) are dropped as ``dark``.
* **Everything blurred**: when even the sharpest tenth of the frames has a blur effect above
  ``scan_blur_max``, ``all_blurred`` is true, a warning is logged and written, and the fallback keeps
  the frames that are sharpest relative to their neighbours (never silently all or none); users who
  want none drop the scene. With ``thesis``, a scan with no candidate is flagged the same way and
  keeps nothing (as published). Whenever nothing is kept, ``none_kept`` is true with a warning.
* **Single frame**: its own reference; kept unless dark (and flagged if absolutely blurred).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np

from pipeline import blur
from pipeline.config import SelectConfig
from pipeline.io import atomic_write_bytes, atomic_write_image, atomic_write_json
from pipeline.runfolder import SELECTION_TPATH, list_scenes, load_scan
from pipeline.scanformats.common import read_color
from pipeline.stages import Item, Stage, StageContext

log = logging.getLogger(__name__)

SCORES_FILE = "scores.csv"
SHEET_FILE = "contact_sheet.png"

# reason codes written per frame
KEPT, TEXTURELESS = "kept", "textureless"
BLURRED, DARK, DUPLICATE, LIMIT = "blurred", "dark", "duplicate", "limit"
FEW_EDGES, EDGES_BELOW_MEAN, LAPLACIAN_BELOW_MEAN = "few_edges", "edges_below_mean", "laplacian_below_mean"


@dataclass(frozen=True)
class Selection:
    """Outcome of the selection of one scan (plain arrays; written by :func:`save_selection`)."""

    method: str
    kept: np.ndarray            # (K,) int64, kept frame indices, ascending
    sharp: np.ndarray           # (F,) bool, passed the blur test (before diversity and max_frames)
    reasons: tuple[str, ...]    # (F,) reason code per frame (see the module constants)
    scores: dict[str, np.ndarray]  # name -> (F,) float64 per-frame scores
    all_blurred: bool           # the scan as a whole looks blurred (see the module docstring)
    warnings: tuple[str, ...] = field(default_factory=tuple)

    @property
    def none_kept(self) -> bool:
        return self.kept.size == 0


# ---------------------------------------------------------------------------------------------------
# Decision (arrays in, Selection out)
# ---------------------------------------------------------------------------------------------------

def select_frames(cfg: SelectConfig, T_c2w: np.ndarray, *, features: blur.FrameFeatures | None = None,
                  thesis_edge: np.ndarray | None = None, thesis_lap: np.ndarray | None = None) -> Selection:
    """Decide which frames of one scan to keep.

    Parameters
    ----------
    cfg : SelectConfig
        Method and limits.
    T_c2w : (F, 4, 4) float64
        Camera-to-world poses, metres (for diversity and the speed columns).
    features : FrameFeatures, optional
        Per-frame :func:`pipeline.blur.frame_features` (needed by ``relative``).
    thesis_edge, thesis_lap : (F,) float, optional
        Per-frame :func:`pipeline.blur.thesis_scores` (needed by ``thesis``).

    Returns
    -------
    Selection
    """
    T = np.asarray(T_c2w, dtype=np.float64)
    n = T.shape[0]
    angle, travel = blur.camera_speeds(T)
    scores: dict[str, np.ndarray] = {"angle_deg": angle, "travel_m": travel}
    reasons = np.full(n, KEPT, dtype=object)
    warnings: list[str] = []
    all_blurred = False
    priority = np.zeros(n)

    if features is not None:
        scores.update(contrast=features.contrast, noise=features.noise,
                      brightness=features.brightness, blur_effect=features.blur_effect)
    if thesis_edge is not None and thesis_lap is not None:
        scores.update(thesis_mean_edge=np.asarray(thesis_edge, np.float64),
                      thesis_lap_std=np.asarray(thesis_lap, np.float64))

    if cfg.method == "none":
        sharp = np.ones(n, bool)
    elif cfg.method == "thesis":
        if thesis_edge is None or thesis_lap is None:
            raise ValueError("method 'thesis' needs thesis_edge and thesis_lap")
        sharp, cand = blur.thesis_keep(thesis_edge, thesis_lap)
        e = np.asarray(thesis_edge, np.float64)
        reasons[~cand] = FEW_EDGES
        reasons[cand & ~sharp & (e < e.mean())] = EDGES_BELOW_MEAN
        reasons[cand & ~sharp & (e >= e.mean())] = LAPLACIAN_BELOW_MEAN
        priority = np.asarray(thesis_lap, np.float64)
        if n and not cand.any():
            all_blurred = True
            warnings.append(f"thesis: no frame has a mean edge value >= {blur.THESIS_EDGE_MIN} "
                            f"(max {e.max():.3f}): the scan is blurred or has few edges")
    elif cfg.method == "relative":
        if features is None:
            raise ValueError("method 'relative' needs features")
        dark = features.brightness < cfg.min_brightness
        flat = (features.contrast < blur.TEXTURELESS_STD) & ~dark
        valid = ~dark & ~flat
        detail = blur.signal_detail(features, ~dark, window=cfg.window)
        rel = blur.relative_detail(detail, valid, window=cfg.window)
        scores["detail"] = detail
        scores["relative"] = rel
        sharp = (valid & (rel >= cfg.min_relative)) | flat
        reasons[dark] = DARK
        reasons[flat] = TEXTURELESS
        reasons[valid & ~sharp] = BLURRED
        priority = np.where(valid, rel, 0.0)
        if valid.any():
            best = float(np.percentile(features.blur_effect[valid], 10))
            if best > cfg.scan_blur_max:
                all_blurred = True
                warnings.append(f"all frames look blurred: even the sharpest tenth has a blur effect of "
                                f"{best:.3f} > scan_blur_max {cfg.scan_blur_max}; kept the "
                                f"{int(sharp.sum())} frames sharpest relative to their neighbours "
                                f"(fallback); drop this scene or lower select.min_relative to change that")
        if dark.any():
            warnings.append(f"{int(dark.sum())} of {n} frames are darker than min_brightness "
                            f"{cfg.min_brightness} and were dropped")
    else:  # validated by the config; a new method must be added here
        raise ValueError(f"unknown select.method {cfg.method!r}")

    cand_idx = np.flatnonzero(sharp)
    diverse = blur.diverse_subset(cand_idx, priority, T, min_angle_deg=cfg.min_angle_deg,
                                  min_baseline_m=cfg.min_baseline_m)
    reasons[np.setdiff1d(cand_idx, diverse)] = DUPLICATE
    kept = blur.evenly_spaced(diverse, cfg.max_frames)
    reasons[np.setdiff1d(diverse, kept)] = LIMIT
    if n and kept.size == 0:
        warnings.append(f"no frame of {n} was kept (method {cfg.method})")
    for w in warnings:
        log.warning("select: %s", w)
    return Selection(method=cfg.method, kept=kept.astype(np.int64), sharp=sharp,
                     reasons=tuple(str(r) for r in reasons), scores=scores,
                     all_blurred=all_blurred, warnings=tuple(warnings))


def score_frames(images: Iterable[np.ndarray], *, method: str, thesis_edge_range: str = "0-255"
                 ) -> tuple[blur.FrameFeatures, np.ndarray | None, np.ndarray | None, list[np.ndarray]]:
    """Per-frame scores of an iterable of RGB (H, W, 3) or gray (H, W) uint8 frames, read once.

    Returns
    -------
    features : FrameFeatures
        Always computed (cheap, and shown in scores.csv).
    thesis_edge, thesis_lap : (F,) float64 or None
        Only for ``method == "thesis"``.
    thumbs : list of (h, w, 3) uint8
        Small RGB copies for the contact sheet.
    """
    import cv2

    rows, te, tl, thumbs = [], [], [], []
    for img in images:
        gray = blur.to_gray(img)
        rows.append(blur.frame_features(gray))
        if method == "thesis":
            e, lap = blur.thesis_scores(gray, edge_range=thesis_edge_range)
            te.append(e)
            tl.append(lap)
        rgb = img if img.ndim == 3 else np.repeat(img[..., None], 3, axis=2)
        h, w = rgb.shape[:2]
        tw = 128
        thumbs.append(cv2.resize(rgb, (tw, max(1, round(h * tw / w))), interpolation=cv2.INTER_AREA))
    feats = blur.stack_features(rows)
    if method == "thesis":
        return feats, np.asarray(te), np.asarray(tl), thumbs
    return feats, None, None, thumbs


# ---------------------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------------------

def _r(x: float) -> float:
    return float(round(float(x), 6)) if np.isfinite(x) else None  # type: ignore[return-value]


def selection_doc(sel: Selection, scene: str, frame_ids: np.ndarray, cfg: SelectConfig) -> dict:
    """The JSON document of a selection (deterministic: rounded floats, sorted keys on write)."""
    counts: dict[str, int] = {}
    for r in sel.reasons:
        counts[r] = counts.get(r, 0) + 1
    kept = set(int(i) for i in sel.kept)
    frames = [{"index": i, "frame_id": int(frame_ids[i]), "kept": i in kept, "reason": r,
               "scores": {k: _r(v[i]) for k, v in sel.scores.items()}}
              for i, r in enumerate(sel.reasons)]
    return {"scene": scene, "method": sel.method, "num_frames": len(sel.reasons),
            "kept": [int(i) for i in sel.kept], "kept_frame_ids": [int(frame_ids[i]) for i in sel.kept],
            "all_blurred": sel.all_blurred, "none_kept": sel.none_kept, "warnings": list(sel.warnings),
            "counts": counts, "config": _cfg_dict(cfg), "frames": frames}


def _cfg_dict(cfg: SelectConfig) -> dict:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()}


def scores_csv(doc: dict) -> str:
    """CSV text of the per-frame table of a :func:`selection_doc`."""
    keys = sorted({k for f in doc["frames"] for k in f["scores"]})
    lines = [",".join(["index", "frame_id", "kept", "reason", *keys])]
    for f in doc["frames"]:
        vals = ["" if f["scores"].get(k) is None else f"{f['scores'][k]:.6g}" for k in keys]
        lines.append(",".join([str(f["index"]), str(f["frame_id"]), str(int(f["kept"])), f["reason"], *vals]))
    return "\n".join(lines) + "\n"


_COLOURS = {KEPT: (40, 180, 60), TEXTURELESS: (40, 180, 60), BLURRED: (220, 40, 40), DARK: (128, 128, 128),
            DUPLICATE: (240, 150, 20), LIMIT: (240, 150, 20), FEW_EDGES: (220, 40, 40),
            EDGES_BELOW_MEAN: (220, 40, 40), LAPLACIAN_BELOW_MEAN: (220, 40, 40)}


def contact_sheet(thumbs: list[np.ndarray], doc: dict, *, columns: int = 10) -> np.ndarray:
    """RGB uint8 grid of thumbnails, each framed by its reason's colour and labelled with its score.

    Labels: frame index, reason, and the deciding score (``relative`` for the relative method, the
    Laplacian std for thesis). Scans of more than 300 frames get half-size cells.
    """
    import cv2

    if not thumbs:
        return np.full((40, 200, 3), 255, np.uint8)
    small = len(thumbs) > 300        # long scans: half-size cells, twice the columns, shorter labels
    if small:
        columns *= 2
        thumbs = [cv2.resize(t, (max(1, t.shape[1] // 2), max(1, t.shape[0] // 2)), interpolation=cv2.INTER_AREA)
                  for t in thumbs]
    th = max(t.shape[0] for t in thumbs)
    tw = max(t.shape[1] for t in thumbs)
    pad, text_h = 4, 26
    cw, ch = tw + 2 * pad, th + 2 * pad + text_h
    rows = (len(thumbs) + columns - 1) // columns
    sheet = np.full((rows * ch, min(columns, len(thumbs)) * cw, 3), 255, np.uint8)
    key = {"relative": "relative", "thesis": "thesis_lap_std"}.get(doc["method"], "blur_effect")
    font = cv2.FONT_HERSHEY_SIMPLEX
    for i, (t, f) in enumerate(zip(thumbs, doc["frames"])):
        r, c = divmod(i, columns)
        y0, x0 = r * ch, c * cw
        colour = (40, 180, 60) if f["kept"] else _COLOURS.get(f["reason"], (0, 0, 0))
        sheet[y0:y0 + th + 2 * pad, x0:x0 + tw + 2 * pad] = colour
        sheet[y0 + pad:y0 + pad + t.shape[0], x0 + pad:x0 + pad + t.shape[1]] = t
        v = f["scores"].get(key)
        label1 = f"#{f['index']} {'KEEP' if f['kept'] else f['reason'][:5 if small else 20]}"
        label2 = "" if v is None else f"{v:.2f}" if small else f"{key[:8]} {v:.2f}"
        cv2.putText(sheet, label1, (x0 + 2, y0 + th + 2 * pad + 10), font, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(sheet, label2, (x0 + 2, y0 + th + 2 * pad + 22), font, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
    return sheet


def save_selection(out_dir: str | Path, doc: dict, thumbs: list[np.ndarray] | None = None) -> Path:
    """Write selection.json, scores.csv and (when ``thumbs`` is given) contact_sheet.png atomically."""
    out = Path(out_dir)
    if thumbs is not None:
        atomic_write_image(out / SHEET_FILE, contact_sheet(thumbs, doc))
    atomic_write_bytes(out / SCORES_FILE, scores_csv(doc).encode("utf-8"))
    return atomic_write_json(out / Path(SELECTION_TPATH).name, doc)  # last: its presence means the item is whole


# ---------------------------------------------------------------------------------------------------
# Stage
# ---------------------------------------------------------------------------------------------------

def _plan(ctx: StageContext) -> list[Item]:
    return [Item(key=scene, data={"scene": scene}) for scene in list_scenes(ctx.run_dir)]


def _run_item(ctx: StageContext, item: Item) -> dict:
    scene = item.data["scene"]
    cfg = ctx.cfg.select
    scan = load_scan(ctx.run_dir, scene)
    images = (read_color(scan, i) for i in range(scan.num_frames))
    feats, te, tl, thumbs = score_frames(images, method=cfg.method, thesis_edge_range=cfg.thesis_edge_range)
    sel = select_frames(cfg, scan.T_c2w, features=feats, thesis_edge=te, thesis_lap=tl)
    doc = selection_doc(sel, scene, scan.frame_ids, cfg)
    save_selection(ctx.stage_dir / scene, doc, thumbs if cfg.contact_sheet else None)
    return {"scene": scene, "frames": scan.num_frames, "kept": int(sel.kept.size),
            "all_blurred": sel.all_blurred, "counts": doc["counts"]}


STAGE = Stage("select", plan=_plan, run_item=_run_item)
