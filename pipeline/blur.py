"""Blur scores of single frames and of frame sequences, and pose-based view diversity.

Plain arrays in, plain arrays out; the stage that reads scans and writes files is
:mod:`pipeline.select`. Two families of scores live here:

``thesis``
    The published reference (seed thesis, section 6.2.1, eq. 6.1): grayscale, Canny edges with
    thresholds 150/250, mean edge value ``mu_e``; frames with ``mu_e >= 0.5`` are candidates; a
    candidate ``c`` is kept when ``mu_c`` is at least the mean of ``mu_e`` over all frames and the
    standard deviation of its Laplacian ``sigma_c`` is at least the mean of ``sigma_L`` over the
    candidates (the thesis writes the two means as sums, which no frame could ever reach; the text and
    the issue say "mean"). The edge map's scale is not stated: OpenCV's Canny returns 0/255, and on
    the 7-Scenes frames the mean of the 0..1 map is 0.009-0.064, so ``mu_e >= 0.5`` on that scale keeps
    no frame of any real scan, while on the 0..255 scale (``>= 0.5`` = 0.2 % edge pixels) it "removes
    most heavily blurred images" as the thesis says. ``edge_range="0-255"`` is therefore the default
    reading; ``"0-1"`` reproduces the literal one.

``relative`` (the default of the stage)
    Blur is relative: a white wall is not blurred, it has no detail to lose. The score of a frame is
    the ratio of its fine-scale detail to its overall contrast, ``r = std(Laplacian) / (std(gray) + 1)``
    on a copy downscaled to 320 pixels wide (a 4-neighbour Laplacian: the finest scale there is), with
    the sensor noise's share of the Laplacian removed (:func:`signal_detail`), and the frame is judged
    against its neighbours in the sequence: ``rel = r / P90(r over the frames within +-window)``.
    Why it works:

    * Motion and defocus blur are low-pass filters: they remove the finest scale first, so ``r``
      drops by a factor of 2-5 for kernels of 9 px and more at 640x480 while the coarse contrast
      ``std(gray)`` barely changes. Dividing by contrast removes exposure and brightness, and removing
      the noise variance keeps a dim, noisy scan from looking sharp everywhere (sensor noise is added
      after the optics blur, so a blurred dim frame still has a noisy fine scale).
    * How much fine detail a *sharp* view has depends on what it shows (a tiled wall versus a plain
      one). Consecutive frames of a scan show nearly the same surfaces, so the sharpest of the nearby
      frames (90th percentile: robust to one oddly noisy frame) is the reference for what this view
      looks like when sharp. Few-edge scenes therefore keep their sharp frames, where an absolute edge
      threshold (the thesis) drops them.
    * Blur in handheld scans comes in short bursts (a fast turn), so a window of +-5 frames nearly
      always holds sharp frames; a scan that is blurred everywhere is caught by a scan-level absolute
      check (below), not by the relative score.

    Textureless frames (contrast below :data:`TEXTURELESS_STD` gray levels) cannot show blur and do not
    take part in the reference of their neighbours.

    Camera speed from the poses (:func:`camera_speeds`) is written beside the scores but not used to
    decide: motion blur depends on the exposure time, which scan formats do not record, and the pose
    step between stored frames (every 10th frame in 7-Scenes) spans many exposures, so a fast step
    does not mean a blurred frame.

``blur_effect``
    The no-reference metric of Crete et al. 2007 ("The blur effect: perception and estimation with a
    new no-reference perceptual blur metric"), as in ``skimage.measure.blur_effect`` (0 = sharp,
    1 = blurred, same values to 1e-5) but with OpenCV filters, measured on a native-resolution centre
    crop (downscaling would shrink the blur). It is content-normalised but, on the benchmark's
    7-Scenes frames, separates blurred from sharp frames less well than ``relative`` (the Kinect v1
    images are soft to begin with); it serves the scan-level "everything is blurred" check: when even
    the sharpest tenth of a scan's frames has a blur effect above ``select.scan_blur_max``, relative
    scores cannot tell and the result says so.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.tolerances import SELECT_TEXTURELESS_STD

log = logging.getLogger(__name__)

WORK_WIDTH = 320            # pixels; frames are scored at this width (a 640x480 frame is halved)
TEXTURELESS_STD = SELECT_TEXTURELESS_STD   # gray levels (0..255) of std at work resolution (see tolerances)
CANNY_LOW, CANNY_HIGH = 150, 250   # thesis thresholds
THESIS_EDGE_MIN = 0.5       # thesis candidate threshold on the mean edge value
BLUR_EFFECT_H = 11          # Crete et al.'s re-blur filter length, pixels (skimage's default)


# ---------------------------------------------------------------------------------------------------
# Single frames
# ---------------------------------------------------------------------------------------------------

def to_gray(image: np.ndarray) -> np.ndarray:
    """Grayscale uint8 copy of an RGB (H, W, 3) or gray (H, W) uint8 image.

    Parameters
    ----------
    image : (H, W, 3) or (H, W) uint8
        RGB colour frame, or already gray.

    Returns
    -------
    (H, W) uint8
    """
    if image.dtype != np.uint8:
        raise ValueError(f"expected a uint8 image, got {image.dtype}")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    raise ValueError(f"expected an (H, W, 3) RGB or (H, W) gray image, got shape {image.shape}")


def thesis_scores(gray: np.ndarray, *, edge_range: str = "0-255") -> tuple[float, float]:
    """The thesis' two per-frame numbers: mean Canny edge value and std of the Laplacian.

    Parameters
    ----------
    gray : (H, W) uint8
        Full-resolution grayscale frame (the thesis works at full resolution).
    edge_range : {"0-255", "0-1"}
        Scale of the edge map whose mean is taken (see the module docstring).

    Returns
    -------
    mean_edge : float
        Mean of the Canny(150, 250) edge map on ``edge_range``.
    lap_std : float
        Standard deviation of the Laplacian (OpenCV ``ksize=1``) of the uint8 image, gray levels.
    """
    edges = cv2.Canny(gray, CANNY_LOW, CANNY_HIGH)
    mean_edge = float(edges.mean())
    if edge_range == "0-1":
        mean_edge /= 255.0
    elif edge_range != "0-255":
        raise ValueError(f"edge_range = {edge_range!r}; valid: '0-255', '0-1'")
    lap_std = float(cv2.Laplacian(gray, cv2.CV_32F).std())
    return mean_edge, lap_std


def _work_copy(gray: np.ndarray) -> np.ndarray:
    h, w = gray.shape
    if w > WORK_WIDTH:
        size = (WORK_WIDTH, max(1, round(h * WORK_WIDTH / w)))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
    return gray.astype(np.float32)


def blur_effect(gray: np.ndarray, *, h_size: int = BLUR_EFFECT_H) -> float:
    """No-reference blur metric of Crete et al. 2007 (0 = sharp, 1 = blurred), OpenCV filters.

    Same definition as ``skimage.measure.blur_effect``: for each axis, ``M1`` sums the absolute Sobel
    derivative along that axis, ``M2`` the part of it that survives a box re-blur of length ``h_size``
    along the same axis, and the result is the max over the axes of ``|M1 - M2| / M1`` (borders
    cropped as skimage does).

    Parameters
    ----------
    gray : (H, W) uint8 or float32
        Grayscale image (the stage passes :func:`center_crop` of the frame).

    Returns
    -------
    float in [0, 1]; 1.0 for an image with no differences at all (nothing sharp in it).
    """
    g = gray.astype(np.float32, copy=False)
    h, w = g.shape
    out = 0.0
    for dx, dy, ksize in ((0, 1, (1, h_size)), (1, 0, (h_size, 1))):
        # axis 0 (rows): derivative in y, re-blur along y (cv2 ksize is (width, height)); OpenCV
        # element-wise ops instead of NumPy: this runs on every frame
        b = cv2.blur(g, ksize, borderType=cv2.BORDER_REFLECT)
        d_f = cv2.absdiff(cv2.Sobel(g, cv2.CV_32F, dx, dy, ksize=3, borderType=cv2.BORDER_REFLECT), 0.0)
        d_b = cv2.absdiff(cv2.Sobel(b, cv2.CV_32F, dx, dy, ksize=3, borderType=cv2.BORDER_REFLECT), 0.0)
        d_f, d_b = d_f[2:h - 1, 2:w - 1], d_b[2:h - 1, 2:w - 1]   # skimage's border crop
        m1 = cv2.sumElems(d_f)[0]
        if m1 <= 1e-6 * max(d_f.size, 1):
            return 1.0
        m2 = cv2.sumElems(cv2.threshold(cv2.subtract(d_f, d_b), 0.0, 0.0, cv2.THRESH_TOZERO)[1])[0]
        out = max(out, abs(m1 - m2) / m1)
    return float(out)


@dataclass(frozen=True)
class FrameFeatures:
    """Per-frame measurements at work resolution (one value per frame, same order as the frames)."""

    lap_var: np.ndarray      # (F,) float64, variance of the 4-neighbour Laplacian, gray levels^2
    noise: np.ndarray        # (F,) float64, Immerkaer noise sigma estimate, gray levels (texture inflates it)
    contrast: np.ndarray     # (F,) float64, std(gray), gray levels 0..255
    brightness: np.ndarray   # (F,) float64, mean(gray) / 255, 0..1
    blur_effect: np.ndarray  # (F,) float64, Crete et al. blur effect of the centre crop, 0 sharp .. 1 blurred


# Immerkaer 1996, "Fast noise variance estimation": a mask that cancels planes and (mostly) edges.
_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
# Gain of the 4-neighbour Laplacian (weights 1, 1, 1, 1, -4) on white noise: 1 + 1 + 1 + 1 + 16.
LAPLACIAN_NOISE_GAIN = 20.0


def frame_features(gray: np.ndarray, *, with_blur_effect: bool = True) -> tuple[float, float, float, float, float]:
    """Measurements of one frame for the ``relative`` method.

    Parameters
    ----------
    gray : (H, W) uint8
        Grayscale frame at any resolution; it is downscaled to :data:`WORK_WIDTH` pixels wide.
    with_blur_effect : bool
        Also compute the blur effect on :func:`center_crop` (the scan-level check needs it; about a
        third of the cost).

    Returns
    -------
    lap_var, noise, contrast, brightness, blur_effect : float
        See :class:`FrameFeatures`; ``blur_effect`` is NaN when not computed.
    """
    g = _work_copy(gray)
    mean, std = cv2.meanStdDev(g)
    lap_std = float(cv2.meanStdDev(cv2.Laplacian(g, cv2.CV_32F, ksize=1))[1][0, 0])
    im = cv2.filter2D(g, cv2.CV_32F, _IMMERKAER, borderType=cv2.BORDER_REFLECT)
    noise = float(np.sqrt(np.pi / 2.0) / 6.0 * cv2.mean(cv2.absdiff(im[1:-1, 1:-1], 0.0))[0]) \
        if min(g.shape) > 2 else 0.0
    be = blur_effect(center_crop(gray)) if with_blur_effect else float("nan")
    return lap_std ** 2, noise, float(std[0, 0]), float(mean[0, 0]) / 255.0, be


def center_crop(gray: np.ndarray) -> np.ndarray:
    """Central (WORK_WIDTH x 3/4 of it) window at native resolution (the whole image when smaller).

    The blur effect is measured here rather than on the downscaled copy: downscaling halves a blur
    kernel's size and hides it, cropping keeps it (blur is a property of the whole frame).
    """
    h, w = gray.shape
    cw, ch = min(w, WORK_WIDTH), min(h, WORK_WIDTH * 3 // 4)
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    return gray[y0:y0 + ch, x0:x0 + cw]


def stack_features(rows: list[tuple[float, ...]]) -> FrameFeatures:
    """Stack :func:`frame_features` results of a sequence into a :class:`FrameFeatures`."""
    a = np.asarray(rows, dtype=np.float64).reshape(-1, 5)
    return FrameFeatures(lap_var=a[:, 0], noise=a[:, 1], contrast=a[:, 2], brightness=a[:, 3],
                         blur_effect=a[:, 4])


def signal_detail(features: FrameFeatures, usable: np.ndarray | None = None, *, window: int = 5) -> np.ndarray:
    """Fine-scale detail of the *scene* in each frame, sensor noise removed, per unit of contrast.

    ``detail = sqrt(max(lap_var - 20 * sigma_n**2, 0)) / (contrast + 1)``. Sensor noise is white, so it
    adds ``20 sigma_n^2`` to the Laplacian's variance whether or not the frame is blurred; in a dim
    scan it hides the loss of detail that blur causes (a blurred frame would score like a sharp one).
    ``sigma_n`` is the smallest Immerkaer estimate among the usable frames within +-``window``:
    neighbouring frames share the exposure and gain, and texture only ever inflates the estimate, so
    the least textured neighbour (often a blurred one) gives the closest value.

    Parameters
    ----------
    features : FrameFeatures
        Per-frame measurements, in sequence order.
    usable : (F,) bool, optional
        Frames whose noise estimate may be used (not the black ones, whose noise is clipped).
    window : int
        Neighbours on each side.

    Returns
    -------
    (F,) float64, dimensionless.
    """
    n = features.lap_var.shape[0]
    ok = np.ones(n, bool) if usable is None else np.asarray(usable, bool)
    sig = np.where(ok, features.noise, np.inf)
    sigma_n = np.empty(n)
    for i in range(n):
        m = sig[max(0, i - window):i + window + 1].min()
        sigma_n[i] = m if np.isfinite(m) else 0.0
    signal = np.maximum(features.lap_var - LAPLACIAN_NOISE_GAIN * sigma_n ** 2, 0.0)
    return np.sqrt(signal) / (features.contrast + 1.0)


# ---------------------------------------------------------------------------------------------------
# Sequences
# ---------------------------------------------------------------------------------------------------

def thesis_keep(mean_edge: np.ndarray, lap_std: np.ndarray, *,
                edge_min: float = THESIS_EDGE_MIN) -> tuple[np.ndarray, np.ndarray]:
    """The thesis' selection rule (eq. 6.1) over one image set.

    Parameters
    ----------
    mean_edge, lap_std : (F,) float
        :func:`thesis_scores` of every frame of the set.
    edge_min : float
        Candidate threshold on ``mean_edge`` (0.5 as published).

    Returns
    -------
    keep : (F,) bool
        Kept frames.
    candidate : (F,) bool
        Frames that passed the first step (``mean_edge >= edge_min``).
    """
    mean_edge = np.asarray(mean_edge, dtype=np.float64)
    lap_std = np.asarray(lap_std, dtype=np.float64)
    candidate = mean_edge >= edge_min
    if not candidate.any():
        return np.zeros_like(candidate), candidate
    keep = candidate & (mean_edge >= mean_edge.mean()) & (lap_std >= lap_std[candidate].mean())
    return keep, candidate


def relative_detail(detail: np.ndarray, valid: np.ndarray | None = None, *, window: int = 5,
                    percentile: float = 90.0) -> np.ndarray:
    """Each frame's detail divided by the sharp level of its neighbourhood in the sequence.

    Parameters
    ----------
    detail : (F,) float
        Per-frame detail (:func:`signal_detail`), in sequence order.
    valid : (F,) bool, optional
        Frames allowed to serve as reference (textureless and too-dark frames are not); a frame
        whose window holds no valid frame is compared with all valid frames of the scan, and when no
        frame is valid at all the result is all ones.
    window : int
        Neighbours on each side that form the reference (the frame itself included).
    percentile : float
        Percentile of the neighbours' detail taken as the "sharp" reference, 0..100.

    Returns
    -------
    (F,) float64
        ``detail / reference``: about 1 for a frame as sharp as its sharp neighbours, lower when blurred.
    """
    d = np.asarray(detail, dtype=np.float64)
    n = d.shape[0]
    ok = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    if n == 0:
        return np.zeros(0)
    if not ok.any():
        return np.ones(n)
    global_ref = float(np.percentile(d[ok], percentile))
    out = np.empty(n)
    for i in range(n):
        lo, hi = max(0, i - window), min(n, i + window + 1)
        w = d[lo:hi][ok[lo:hi]]
        ref = float(np.percentile(w, percentile)) if w.size else global_ref
        out[i] = d[i] / ref if ref > 0 else 1.0
    return out


def camera_speeds(T_c2w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and travel of the camera from the previous frame (0 for the first).

    Parameters
    ----------
    T_c2w : (F, 4, 4) float64
        Camera-to-world poses, metres.

    Returns
    -------
    angle_deg : (F,) float64
        Rotation angle between consecutive camera orientations, degrees per frame step.
    travel_m : (F,) float64
        Distance between consecutive camera centres, metres per frame step.
    """
    T = np.asarray(T_c2w, dtype=np.float64)
    n = T.shape[0]
    ang = np.zeros(n)
    trav = np.zeros(n)
    if n > 1:
        ang[1:] = rotation_angles_deg(T[:-1, :3, :3], T[1:, :3, :3])
        trav[1:] = np.linalg.norm(T[1:, :3, 3] - T[:-1, :3, 3], axis=1)
    return ang, trav


def rotation_angles_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Geodesic angle between rotation matrices, degrees; (..., 3, 3) each, broadcast."""
    Rrel = np.einsum("...ji,...jk->...ik", Ra, Rb)
    c = (np.trace(Rrel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def diverse_subset(candidates: np.ndarray, priority: np.ndarray, T_c2w: np.ndarray, *,
                   min_angle_deg: float, min_baseline_m: float) -> np.ndarray:
    """Greedy pick of views that are not near-duplicates of a view already picked.

    A view is a near-duplicate of a picked one when it is both within ``min_angle_deg`` of rotation
    AND within ``min_baseline_m`` of camera travel of it. Views are visited from the highest
    ``priority`` (the sharpest) down, so of a cluster of near-identical views the sharpest is kept.
    With both limits at 0 nothing is a duplicate and every candidate is returned.

    Parameters
    ----------
    candidates : (K,) int
        Frame indices to choose from (the sharp frames).
    priority : (F,) float
        Per-frame priority over all frames; higher first, ties by frame index.
    T_c2w : (F, 4, 4) float64
        Camera-to-world poses of all frames, metres.

    Returns
    -------
    (M,) int64
        Picked frame indices, ascending.
    """
    cand = np.asarray(candidates, dtype=np.int64)
    if min_angle_deg <= 0.0 and min_baseline_m <= 0.0:
        return np.sort(cand)
    pr = np.asarray(priority, dtype=np.float64)[cand]
    order = cand[np.lexsort((cand, -pr))]
    R = T_c2w[:, :3, :3]
    C = T_c2w[:, :3, 3]
    picked: list[int] = []
    for i in order:
        if picked:
            p = np.asarray(picked)
            dup = (rotation_angles_deg(R[p], R[i][None]) < min_angle_deg) & \
                  (np.linalg.norm(C[p] - C[i], axis=1) < min_baseline_m)
            if dup.any():
                continue
        picked.append(int(i))
    return np.sort(np.asarray(picked, dtype=np.int64))


def evenly_spaced(indices: np.ndarray, k: int) -> np.ndarray:
    """At most ``k`` of ``indices`` (sorted), spread evenly over the list; all when k <= 0."""
    idx = np.asarray(indices, dtype=np.int64)
    if k <= 0 or idx.size <= k:
        return idx
    pos = np.unique(np.round(np.linspace(0, idx.size - 1, k)).astype(np.int64))
    return idx[pos]
