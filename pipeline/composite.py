"""The ``composite`` stage: the rendered objects fused into the real photo, and the composite depth.

Two blends (``composite.mode``):

``published``
    The published method, kept as the baseline: inside the occlusion mask (raster labels > 0) the
    PBR colour times the AO, outside it the real pixel. The tracer's PBR pass is premultiplied by
    coverage, so the colour is un-premultiplied first (a hard mask over a premultiplied edge would
    darken the silhouette, a flaw the published method did not have).

``full`` (default)
    * soft, anti-aliased edges: ``out = pbr + (1 - coverage) * background`` with the traced coverage
      (premultiplied alpha), restricted to the raster mask grown by ``trace.edge_band`` pixels so that
      objects the raster hid behind real geometry (real-depth fusion) stay hidden;
    * shadows and contact darkening by differential rendering: ``background = photo x shadow_ratio``
      in linear light;
    * the photo's exposure (``composite.match_exposure``): the trace stage's per-frame ratio of the
      photo to the room mesh colours multiplies the objects' radiance (cameras with auto exposure);
    * the camera's look (:mod:`pipeline.camera_look`): the same tone curve as the tracer's decode of
      the room colours (``linear_to_srgb(radiance x exposure / trace.radiance_scale)``), the photo's
      measured blur level applied to the object layer (and the shadow ratio) in linear light, and the
      photo's measured sensor noise added to the object pixels from the item's seeded generator.
    No AO factor: the path tracer's radiance already holds the objects' self-occlusion.

Pixels the objects change in no way (coverage 0 after blur, shadow ratio 1) are the photo's bytes,
exactly. Every mode writes at the raster frame's resolution, pixel-aligned with its labels and masks;
annotations are the raster stage's and do not depend on the mode.

Outputs per (scene, drop, frame) item, where the export stage reads them:
``RUN/composite/<scene>/drop<NNNN>/f<frame:06d>.png`` (RGB uint8) and ``..._depth.npz`` with ``depth``
(H, W) float32 metres: the raster stage's ``written_depth`` (the real depth with the objects' depth
where they are visible, the room's depth where the room hides an object and the sensor has none, 0 =
invalid; ``composite.depth_fill = "room"`` fills all invalid real depth from the room mesh's depth).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from pipeline import camera_look as cl, color
from pipeline.errors import InputError
from pipeline.runfolder import (COMPOSITE_DEPTH_TPATH, COMPOSITE_TPATH, FrameKey, load_raster_frame, load_scan,
                                load_trace, raster_frames)
from pipeline.scanformats.common import read_color
from pipeline.stages import Item, Stage, StageContext

log = logging.getLogger(__name__)

_COVER_EPS = 1e-3        # coverage below this is "no object" (Monte Carlo coverage is k / spp)
_FILL_RADIUS = 2         # pixels: window radius of the normalised-convolution colour fill
_BLUR_CROP_MARGIN = 24   # pixels around the objects where the photo's blur is measured
_NOISE_BAND = (2, 12)    # pixels: ring around the objects (inner, outer) where photo noise is measured
_SHADOW_RATIO_MAX = 4.0  # shadow ratios above this are clamped (a few noisy rays off a bright object)


# ---------------------------------------------------------------------------------------------------
# Pure blends
# ---------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Composite:
    """What :func:`composite_full` returns."""

    image: np.ndarray      # (H, W, 3) uint8 RGB
    blur_sigma: float      # pixels, Gaussian blur applied to the object layer
    photo_edge_sigma: float  # pixels, edge-width blur measure of the photo near the objects; NaN = not measured
    photo_noise: float     # gray levels (0..255), sensor noise measured in the photo around the objects
    noise_added: float     # gray levels, std of the noise added to fully covered object pixels


def _check_image(name: str, a: np.ndarray, hw: tuple[int, int], channels: int | None) -> None:
    want = hw if channels is None else (*hw, channels)
    if a.shape != want:
        raise ValueError(f"{name} has shape {a.shape}, expected {want}")


def _clean_coverage(coverage: np.ndarray) -> np.ndarray:
    c = np.nan_to_num(np.asarray(coverage, np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    return np.clip(c, 0.0, 1.0)


def _clean_radiance(pbr: np.ndarray) -> np.ndarray:
    p = np.nan_to_num(np.asarray(pbr, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    return np.maximum(p, 0.0)


def unpremultiply(pbr: np.ndarray, coverage: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Object colour (not premultiplied) of every pixel.

    ``pbr / coverage`` where the coverage is above a small epsilon; elsewhere the coverage-weighted mean
    of the pixels within 2 pixels (normalised convolution), and ``fallback`` where none is covered.

    Parameters
    ----------
    pbr : (H, W, 3) float32, linear radiance premultiplied by coverage
    coverage : (H, W) float32 in [0, 1]
    fallback : (H, W, 3) float32, linear colour used where no object sample is near

    Returns
    -------
    (H, W, 3) float32 linear radiance
    """
    cov = _clean_coverage(coverage)
    p = _clean_radiance(pbr)
    k = 2 * _FILL_RADIUS + 1
    num = cv2.boxFilter(p, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)
    den = cv2.boxFilter(cov, -1, (k, k), normalize=False, borderType=cv2.BORDER_CONSTANT)[..., None]
    filled = np.where(den > _COVER_EPS, num / np.maximum(den, _COVER_EPS), fallback)
    direct = p / np.maximum(cov, _COVER_EPS)[..., None]
    return np.where(cov[..., None] > _COVER_EPS, direct, filled).astype(np.float32)


def composite_published(photo: np.ndarray, pbr: np.ndarray, ao: np.ndarray, mask: np.ndarray, *,
                        coverage: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """The published blend: PBR colour x AO inside the mask, the real pixel outside.

    Parameters
    ----------
    photo : (H, W, 3) uint8 sRGB
    pbr : (H, W, 3) float32 linear radiance premultiplied by ``coverage`` (the trace stage's pass)
    ao : (H, W) float32 in [0, 1]
    mask : (H, W) bool, the occlusion mask (raster labels > 0)
    coverage : (H, W) float32 in [0, 1]
    gain : float
        Linear radiance -> photo linear units (``exposure / trace.radiance_scale``).

    Returns
    -------
    (H, W, 3) uint8 sRGB
    """
    photo = np.asarray(photo, np.uint8)
    hw = photo.shape[:2]
    _check_image("photo", photo, hw, 3)
    _check_image("pbr", np.asarray(pbr), hw, 3)
    _check_image("ao", np.asarray(ao), hw, None)
    _check_image("mask", np.asarray(mask), hw, None)
    m = np.asarray(mask, bool)
    out = photo.copy()
    if not m.any():
        return out
    colour = unpremultiply(pbr, coverage, color.decode_u8(photo) / max(gain, 1e-12))
    a = np.clip(np.nan_to_num(np.asarray(ao, np.float32), nan=1.0), 0.0, 1.0)
    obj = color.encode_u8(colour * a[..., None] * np.float32(gain))
    out[m] = obj[m]
    return out


def _bbox(mask: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    h, w = mask.shape
    return (slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, h)),
            slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, w)))


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    if r <= 0:
        return mask.copy()
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0


def _fill_under_objects(sr: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """The shadow ratio with the labelled pixels ``objects`` (where the tracer wrote 1) filled from the room
    around them.

    The room under an object is hidden, but blurring the ratio to the photo's blur level would
    otherwise bleed those 1s into the contact shadow beside the object (a bright rim), and a partly
    covered edge pixel shows the room just beside the object, in its contact line. Filled by normalised
    convolution over growing windows, the nearest first (3 px: the contact line is about a pixel wide;
    a 5 px window reached the unshadowed room and left the light suite's contact lines 25-35 gray levels
    too bright); 1 where no room pixel is near. Unlabelled pixels keep their traced ratio, partly covered
    or not.
    """
    if not objects.any():
        return sr
    w = (~objects).astype(np.float32)
    out = sr.copy()
    todo = objects.copy()
    for k in (3, 5, 11, 23):
        num = cv2.boxFilter(sr * w, -1, (k, k), normalize=False, borderType=cv2.BORDER_REFLECT)
        den = cv2.boxFilter(w, -1, (k, k), normalize=False, borderType=cv2.BORDER_REFLECT)
        ok = todo & (den > 0.5)
        out[ok] = num[ok] / den[ok]
        todo &= ~ok
        if not todo.any():
            break
    out[todo] = 1.0
    return out


def composite_full(photo: np.ndarray, pbr: np.ndarray, coverage: np.ndarray, shadow_ratio: np.ndarray,
                   labels: np.ndarray, *, rng: np.random.Generator, gain: float = 1.0, soft_edges: bool = True,
                   shadows: bool = True, blur_sigma: float | None = None, noise_sigma: float | None = None,
                   edge_band: int = 1) -> Composite:
    """The full blend: soft edges, differential shadows and the photo's camera look.

    Parameters
    ----------
    photo : (H, W, 3) uint8 sRGB
    pbr : (H, W, 3) float32 linear radiance premultiplied by ``coverage``
    coverage : (H, W) float32 in [0, 1], share of each pixel covered by a visible object
    shadow_ratio : (H, W) float32, room light with objects / without (1 = unchanged)
    labels : (H, W) uint16 visible instance labels (0 = none)
    rng : the item's seeded generator (noise)
    gain : float
        Linear radiance -> photo linear units (``exposure / trace.radiance_scale``).
    soft_edges : False = hard label mask instead of the coverage (ablation)
    shadows : False = ignore the shadow ratio (ablation)
    blur_sigma : float or None
        Gaussian blur of the object layer, pixels; None = measured from the photo.
    noise_sigma : float or None
        Sensor noise of the photo, gray levels (0..255); None = measured; 0 = add none.
    edge_band : int
        Pixels around the label mask where coverage is trusted (``trace.edge_band``).

    Returns
    -------
    Composite
    """
    photo = np.asarray(photo, np.uint8)
    hw = photo.shape[:2]
    _check_image("photo", photo, hw, 3)
    _check_image("pbr", np.asarray(pbr), hw, 3)
    _check_image("coverage", np.asarray(coverage), hw, None)
    _check_image("shadow_ratio", np.asarray(shadow_ratio), hw, None)
    _check_image("labels", np.asarray(labels), hw, None)
    mask = np.asarray(labels) > 0
    photo_lin = color.decode_u8(photo)
    alpha, layer = _object_layer(pbr, coverage, mask, photo_lin, np.float32(gain), soft_edges=soft_edges,
                                 edge_band=edge_band)
    sr = _shadow_layer(shadow_ratio, mask) if shadows else np.ones(hw, np.float32)

    objects = alpha > 0
    box = _bbox(objects, _BLUR_CROP_MARGIN)
    photo_edge = float("nan")
    ring = _dilate(objects, _NOISE_BAND[1]) & ~_dilate(objects, _NOISE_BAND[0])
    if ring.sum() < 256:
        ring = ~objects
    if blur_sigma is None:
        if box is None:
            blur_sigma = 0.0
        else:
            blur_sigma, photo_edge = _match_blur(photo, photo_lin, layer, alpha, sr, shadows, box, ring, rng)
    out_lin, al, s = _blend(layer, alpha, sr, photo_lin, shadows, float(blur_sigma))
    out = color.linear_to_srgb(out_lin) * np.float32(255.0)

    noise_added = 0.0
    if noise_sigma is None:
        noise_sigma = 0.0 if box is None else cl.noise_sigma(photo, ring)
    if noise_sigma > 0 and objects.any():
        out, noise_added = _match_noise(out, al, float(noise_sigma), rng)
    image = np.clip(np.round(out), 0, 255).astype(np.uint8)
    changed = (al > 0) | (s != 1.0)
    image = np.where(changed[..., None], image, photo)
    return Composite(image=image, blur_sigma=float(blur_sigma), photo_edge_sigma=photo_edge,
                     photo_noise=float(noise_sigma), noise_added=float(noise_added))


def _object_layer(pbr: np.ndarray, coverage: np.ndarray, mask: np.ndarray, photo_lin: np.ndarray, g: np.float32,
                  *, soft_edges: bool, edge_band: int) -> tuple[np.ndarray, np.ndarray]:
    """The objects' alpha (H, W) float32 and their premultiplied linear layer (H, W, 3) in photo units.

    Coverage is trusted within ``edge_band`` pixels of the label mask; colour is the traced radiance
    unpremultiplied (the photo where nothing was traced) times the gain ``g``.
    """
    cov = _clean_coverage(coverage) * _dilate(mask, edge_band)
    p = _clean_radiance(pbr) * (cov > 0)[..., None]
    colour = unpremultiply(p, cov, photo_lin / max(g, 1e-12)) * g
    if soft_edges:
        # a labelled pixel the tracer found wholly uncovered (meshes of raster and trace differ a little):
        # keep the mask's word for it so the image and the masks stay aligned
        alpha = np.where(mask & (cov <= _COVER_EPS), np.float32(1.0), cov)
    else:
        alpha = mask.astype(np.float32)
    alpha = np.where(alpha > _COVER_EPS, alpha, 0.0).astype(np.float32)
    return alpha, colour * alpha[..., None]


def _shadow_layer(shadow_ratio: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The shadow ratio (H, W) float32 made safe to multiply the photo by: finite, clamped to
    [0, :data:`_SHADOW_RATIO_MAX`], and filled in under the objects (the tracer wrote 1 there)."""
    sr = np.nan_to_num(np.asarray(shadow_ratio, np.float32), nan=1.0, posinf=1.0, neginf=1.0)
    sr = np.clip(sr, 0.0, _SHADOW_RATIO_MAX)
    return _fill_under_objects(sr, mask)   # the tracer wrote 1 on labelled pixels only


def _blend(layer: np.ndarray, alpha: np.ndarray, sr: np.ndarray, photo_lin: np.ndarray, shadows: bool,
           sigma: float, sl: tuple[slice, slice] = (slice(None), slice(None))
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(linear composite, blurred alpha, blurred shadow ratio) of the window ``sl``: the object layer over
    the photo darkened by the shadow ratio, the layer, alpha and ratio blurred by ``sigma`` pixels first."""
    lay, al, s = layer[sl], alpha[sl], sr[sl]
    if sigma > 0:
        lay, al = cl.gaussian_blur(lay, sigma), cl.gaussian_blur(al, sigma)
        s = cl.gaussian_blur(s, sigma) if shadows else s
    al = np.clip(al, 0.0, 1.0)
    out = lay + (1.0 - al)[..., None] * photo_lin[sl] * s[..., None]
    return out, al, s


def _match_blur(photo: np.ndarray, photo_lin: np.ndarray, layer: np.ndarray, alpha: np.ndarray, sr: np.ndarray,
                shadows: bool, box: tuple[slice, slice], ring: np.ndarray, rng: np.random.Generator
                ) -> tuple[float, float]:
    """The blur (sigma, pixels) that makes the objects' silhouettes as sharp as the photo's edges, and the
    photo's edge sigma, measured in the window ``box`` (:func:`pipeline.camera_look.match_blur_sigma`) with
    the photo's gray noise level measured in ``ring``."""
    objects = alpha > 0
    # the objects' silhouettes (not their soft interior shading, not the photo beside them)
    half = alpha >= 0.5
    near = (_dilate(half, 1) & _dilate(~half, 1))[box]
    gray = cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY)
    # the render is measured with the photo's own (gray) noise level: noise makes edges look sharper
    grain = rng.standard_normal(gray[box].shape, dtype=np.float32) * np.float32(cl.noise_sigma(gray, ring))
    return cl.match_blur_sigma(
        gray[box], ~_dilate(objects, 1)[box],
        lambda s: cv2.cvtColor(color.encode_u8(_blend(layer, alpha, sr, photo_lin, shadows, s, box)[0]),
                               cv2.COLOR_RGB2GRAY).astype(np.float32)
        + grain, near)


def _match_noise(out: np.ndarray, al: np.ndarray, noise_sigma: float, rng: np.random.Generator
                 ) -> tuple[np.ndarray, float]:
    """``out`` (H, W, 3) float32 sRGB 0..255 with sensor noise added over the objects (weighted by the
    blurred alpha ``al``) so their noise matches the photo's ``noise_sigma`` (gray levels); and the
    noise added."""
    inner = (al >= 0.99) & ~_dilate(~(al >= 0.99), 1)
    render_sigma = cl.noise_sigma(np.clip(out, 0, 255), inner)
    noise_added = cl.noise_to_add(float(noise_sigma), render_sigma)
    if noise_added > 0:
        n = rng.standard_normal(out.shape, dtype=np.float32) * np.float32(noise_added)
        out = out + n * al[..., None]
    return out, noise_added


def plan(ctx: StageContext) -> list[Item]:
    """One item per raster frame with status ok (the frames the trace stage traced)."""
    frames = raster_frames(ctx.run_dir)
    if not frames:
        log.warning("composite: no raster frame in %s; run the raster and trace stages first",
                    ctx.run_dir / "raster")
    return [Item(key=str(k), data={"scene": k.scene, "drop": k.drop, "frame": k.frame}) for k in frames]


def run_item(ctx: StageContext, item: Item) -> dict:
    from pipeline.io import atomic_save_npz, atomic_write_image

    cfg = ctx.cfg.composite
    fk = FrameKey(item.data["scene"], int(item.data["drop"]), int(item.data["frame"]))
    arr = load_raster_frame(ctx.run_dir, fk).arrays(masks=False)
    labels = arr["labels"]
    h, w = labels.shape
    tr = load_trace(ctx.run_dir, fk)
    for key in ("pbr", "ao", "coverage", "shadow_ratio"):
        if key not in tr:
            raise InputError(f"trace output of {item.key} has no {key!r} pass; re-run 'scansynth trace'")
        if tr[key].shape[:2] != (h, w):
            raise InputError(f"trace pass {key!r} of {item.key} is {tr[key].shape[:2]}, the raster frame is "
                             f"{(h, w)}; re-run trace after raster")
    scan = load_scan(ctx.run_dir, fk.scene)
    photo = read_color(scan, fk.frame)
    if photo.shape[:2] != (h, w):
        photo = cv2.resize(photo, (w, h), interpolation=cv2.INTER_AREA)
    gain = cfg.exposure / ctx.cfg.trace.radiance_scale
    if cfg.mode == "published":
        image = composite_published(photo, tr["pbr"], tr["ao"], labels > 0, coverage=tr["coverage"], gain=gain)
        info = {}
    else:
        exposure = float(tr["exposure"]) if cfg.match_exposure and "exposure" in tr else 1.0
        if not np.isfinite(exposure) or exposure <= 0:
            exposure = 1.0
        res = composite_full(photo, tr["pbr"], tr["coverage"], tr["shadow_ratio"], labels, rng=ctx.rng(item),
                             gain=gain * exposure, soft_edges=cfg.soft_edges, shadows=cfg.shadows,
                             blur_sigma=None if cfg.blur_sigma < 0 else cfg.blur_sigma,
                             noise_sigma=None if cfg.noise_sigma < 0 else cfg.noise_sigma,
                             edge_band=ctx.cfg.trace.edge_band)
        image = res.image
        info = {"exposure": round(exposure, 4), "blur_sigma": res.blur_sigma, "photo_noise": round(res.photo_noise, 3),
                "noise_added": round(res.noise_added, 3),
                "photo_edge_sigma": None if np.isnan(res.photo_edge_sigma) else round(res.photo_edge_sigma, 4)}
    # The raster stage composed the dataset's depth (and judged visibility on it); write the same.
    depth = arr["written_depth"]
    atomic_write_image(fk.path(ctx.run_dir, COMPOSITE_TPATH), image)
    atomic_save_npz(fk.path(ctx.run_dir, COMPOSITE_DEPTH_TPATH), depth=depth)
    return {"mode": cfg.mode, **info}


STAGE = Stage("composite", plan, run_item)
