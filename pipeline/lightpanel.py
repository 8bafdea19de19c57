"""Pictures of a fitted room lighting: a top view of the room with its emitters, and photos with theirs.

The run report (:mod:`pipeline.report_html`) shows them so that a bad light fit is seen at a glance: a lamp
under the floor, the light's power on the wrong side of the room, a colour no lamp has. Everything here works
on arrays (the report reads the run folder):

- :func:`draw_top`: the room seen from above, looking down the scan's up vector (orthographic, not mirrored:
  seen from above), each triangle in the colour of its vertices' albedo (the mesh's colours where the fit
  found none), shaded darker the steeper it stands (walls read as outlines), the highest surface in front,
  the surfaces facing down (ceilings) left out. Over it the emitters as discs whose area follows their share
  of the power and whose colour is their light's colour, numbered brightest first, and the scan's cameras as
  dots with a tick along their view direction.
- :func:`draw_photo`: a photo with each emitter's centre projected into it (a ring); one outside the frame or
  behind the camera is an arrow at the image border pointing toward it.

Drawn with OpenCV on uint8 RGB images; the same inputs give the same pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.camera import Camera
from pipeline.color import LUMINANCE_F64, encode_u8

PANEL_WIDTH = 480             # pixels, every picture of the panel
MAX_HEIGHT = 640              # pixels, the top view's height at most (a long room is scaled down to fit)
MARGIN = 18                   # pixels around the room in the top view
SAMPLE_PX = 0.7               # pixels between the samples a triangle is drawn with (below 1: no holes)
MAX_SUBDIV = 24               # samples along a triangle's edge at most; a larger triangle is filled whole
BACKGROUND = (34, 37, 43)     # outside the room
CAMERA_RGB = (80, 200, 255)
DARKEST_SHOWN = 0.5           # linear: an albedo whose brightest 1 % is darker is shown brighter (vertex_colours)
LABELLED = 9                  # emitters numbered on the pictures (the brightest; the table lists them all)
BORDER_INSET = 8              # pixels between an out-of-view arrow's head and the image border
ARROW_PX = 30                 # length of an out-of-view arrow
STRIP_PX = 22                 # height of the label strip above a photo


@dataclass(frozen=True)
class Emitter:
    """One emitter of a fit's summary (``summary["emitters"]``), as the light it is rendered with."""

    centre: np.ndarray        # (3,) float64 metres, world frame
    area_m2: float
    radiance: np.ndarray      # (3,) float64 linear radiance, photo units
    power_share: float        # of the fitted power, 0..1
    kind: str                 # "lamp" | "box cell" | "clipped region"


def emitters_of(summary: dict) -> list[Emitter]:
    """The emitters a fit's ``summary`` lists (brightest first), with the radiance they are rendered with.
    Entries without a finite centre are skipped."""
    out = []
    for e in summary.get("emitters") or []:
        c = np.asarray(e.get("centre", ()), np.float64)
        rad = np.asarray(e.get("radiance", (0.0, 0.0, 0.0)), np.float64)
        if c.shape != (3,) or rad.shape != (3,) or not np.all(np.isfinite(c)):
            continue
        out.append(Emitter(centre=c, area_m2=float(e.get("area_m2", 0.0)), radiance=rad,
                           power_share=float(e.get("power_share", 0.0)), kind=str(e.get("kind", "?"))))
    return out


def light_rgb(radiance: np.ndarray) -> tuple[int, int, int]:
    """sRGB uint8 colour of a light of linear ``radiance (3,)``, normalised so its largest channel is 1."""
    rad = np.clip(np.nan_to_num(np.asarray(radiance, np.float64)), 0.0, None)
    top = rad.max()
    return tuple(int(x) for x in encode_u8(rad / top if top > 0 else np.ones(3)))


def marker_radius(share: float) -> int:
    """Pixels: a disc's area grows with the emitter's share of the power (the brightest ~18 px across)."""
    return int(round(3 + 14 * np.sqrt(np.clip(share, 0.0, 1.0))))


@dataclass(frozen=True)
class TopView:
    """The orthographic view from above: world point -> pixel ``(u, v) = (p - origin) . (right, -ahead) x
    scale + offset``."""

    right: np.ndarray         # (3,) unit, world direction of the image's +u
    ahead: np.ndarray         # (3,) unit, world direction of the image's -v (up on the picture)
    up: np.ndarray            # (3,) unit, the scan's up (toward the viewer)
    lo: np.ndarray            # (2,) metres, (right, ahead) coordinates at pixel (MARGIN, height - 1 - MARGIN)
    scale: float              # pixels per metre
    width: int
    height: int

    def pixels(self, points_w: np.ndarray) -> np.ndarray:
        """World points (N, 3) -> float64 pixels (N, 2) of the picture (pixel centres at integers)."""
        p = np.asarray(points_w, np.float64).reshape(-1, 3)
        a, b = p @ self.right - self.lo[0], p @ self.ahead - self.lo[1]
        return np.stack([MARGIN + a * self.scale, self.height - 1 - MARGIN - b * self.scale], axis=1)


def top_view(points_w: np.ndarray, up: np.ndarray, *, width: int = PANEL_WIDTH) -> TopView:
    """The :class:`TopView` that holds every point of ``points_w (N, 3)`` seen down ``up (3,)``."""
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    axis = np.eye(3)[int(np.argmin(np.abs(up)))] if abs(up[0]) > 0.9 else np.array([1.0, 0.0, 0.0])
    right = axis - (axis @ up) * up
    right /= np.linalg.norm(right)
    ahead = np.cross(up, right)
    p = np.asarray(points_w, np.float64).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    ab = np.stack([p @ right, p @ ahead], axis=1) if len(p) else np.zeros((1, 2))
    lo, hi = ab.min(axis=0), ab.max(axis=0)
    ext = np.maximum(hi - lo, 0.5)          # metres: a single point still gives a picture
    lo = 0.5 * (lo + hi) - 0.5 * ext
    scale = min((width - 1 - 2 * MARGIN) / ext[0], (MAX_HEIGHT - 1 - 2 * MARGIN) / ext[1])
    height = int(np.ceil(ext[1] * scale)) + 2 * MARGIN + 1
    lo = lo - np.array([((width - 1 - 2 * MARGIN) / scale - ext[0]) / 2, 0.0])   # centred across
    return TopView(right=right, ahead=ahead, up=up, lo=lo, scale=float(scale), width=int(width), height=height)


def vertex_colours(albedo: np.ndarray | None, radiance: np.ndarray) -> tuple[np.ndarray, float]:
    """The colour of each mesh vertex on the top view: ``(colours (V, 3) uint8 sRGB, gain)``.

    A vertex shows its fitted ``albedo (V, 3)`` (linear), or where that is 0 (not fitted) its ``radiance
    (V, 3)`` (linear, the mesh's colours) scaled so the brightest 1 % is white. Where the brightest 1 % of the
    albedo is below DARKEST_SHOWN, all of it is shown ``gain`` times brighter (else gain is 1), so that a room
    the fit made dark can still be seen.
    """
    rad = np.clip(np.nan_to_num(np.asarray(radiance, np.float64)), 0.0, None)
    top = np.percentile(rad @ LUMINANCE_F64, 99) if len(rad) else 1.0
    shown = rad / top if top > 0 else rad
    gain = 1.0
    if albedo is not None and len(albedo) == len(rad) and len(rad):
        alb = np.clip(np.nan_to_num(np.asarray(albedo, np.float64)), 0.0, 1.0)
        fitted = alb.max(axis=1) > 0
        if fitted.any():
            bright = float(np.percentile(alb[fitted] @ LUMINANCE_F64, 99))
            gain = DARKEST_SHOWN / bright if 0 < bright < DARKEST_SHOWN else 1.0
            shown = np.where(fitted[:, None], alb * gain, shown)
    return encode_u8(shown), gain


def _surface(view: TopView, vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray, facing: int,
             image: np.ndarray) -> None:
    """Draw the triangles into ``image``, in place, the highest in front; a triangle facing down
    (``facing`` x normal . up < 0) is left out. A small triangle is sampled every SAMPLE_PX pixels (the
    highest sample of a pixel wins), a large one filled whole at its centroid's height."""
    import cv2

    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    if not len(F):
        return
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    norm = np.linalg.norm(n, axis=1)
    cos_up = (n @ view.up) / np.maximum(norm, 1e-20)
    keep = (norm > 0) & (cos_up * (facing or 1) > -0.2)
    F, cos_up = F[keep], np.abs(cos_up[keep])
    shade = 0.4 + 0.6 * cos_up                       # a wall (seen edge-on) dark, a floor as it is
    rgb = (colours[F].astype(np.float64).mean(axis=1) * shade[:, None]).round().astype(np.uint8)
    px = view.pixels(V)[F]                           # (T, 3, 2)
    height = (V @ view.up)[F].mean(axis=1)
    edge = np.max(np.linalg.norm(px - np.roll(px, 1, axis=1), axis=2), axis=1)
    k = np.ceil(np.nan_to_num(edge) / SAMPLE_PX).clip(1, None).astype(np.int64)
    H, W = image.shape[:2]
    top = np.full((H, W), -np.inf, np.float32)      # height of what the large triangles drew
    for t in sorted(np.flatnonzero(k > MAX_SUBDIV), key=lambda t: (height[t], t)):
        tri = np.round(np.clip(px[t], -1e5, 1e5) * 16).astype(np.int32)
        cv2.fillConvexPoly(image, tri, tuple(int(x) for x in rgb[t]), cv2.LINE_8, 4)
        cv2.fillConvexPoly(top, tri, float(height[t]), cv2.LINE_8, 4)
    flat, hs, ts = [], [], []
    for kk in np.unique(k[k <= MAX_SUBDIV]):
        sel = np.flatnonzero(k == kk)
        i, j = np.meshgrid(np.arange(kk + 1), np.arange(kk + 1), indexing="ij")
        m = i + j <= kk
        bary = np.stack([1 - (i[m] + j[m]) / kk, i[m] / kk, j[m] / kk], axis=1)   # (G, 3)
        bary = np.concatenate([bary, np.full((1, 3), 1 / 3)])                      # and the centroid
        pts = np.einsum("gk,tkd->tgd", bary, px[sel]).round().astype(np.int64)     # (S, G, 2)
        ok = (pts[..., 0] >= 0) & (pts[..., 0] < W) & (pts[..., 1] >= 0) & (pts[..., 1] < H)
        t = np.broadcast_to(sel[:, None], ok.shape)[ok]
        flat.append(pts[..., 1][ok] * W + pts[..., 0][ok])
        hs.append(height[t])
        ts.append(t)
    if not flat:
        return
    flat, hh, tt = np.concatenate(flat), np.concatenate(hs), np.concatenate(ts)
    order = np.lexsort((tt, -hh, flat))              # per pixel: the highest first (ties: lowest triangle)
    pix, first = np.unique(flat[order], return_index=True)
    win = tt[order][first]
    front = height[win] >= top.reshape(-1)[pix]
    image.reshape(-1, 3)[pix[front]] = rgb[win[front]]


def _outlined_text(image: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.5,
                   colour=(255, 255, 255)) -> None:
    import cv2

    cv2.putText(image, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(image, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def _scale_bar(image: np.ndarray, view: TopView) -> None:
    import cv2

    metres = next((m for m in (0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0) if m * view.scale >= 0.15 * view.width), 50.0)
    x0, y = 10, image.shape[0] - 8
    x1 = x0 + int(round(metres * view.scale))
    cv2.line(image, (x0, y), (x1, y), (0, 0, 0), 4)
    cv2.line(image, (x0, y), (x1, y), (255, 255, 255), 2)
    _outlined_text(image, f"{metres:g} m", (x1 + 6, y + 4))


def draw_top(view: TopView, vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray,
             emitters: list[Emitter], cameras: np.ndarray, *, facing: int = 1,
             marked: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """The room from above with its emitters and cameras.

    Parameters
    ----------
    view : the :class:`TopView` (:func:`top_view`)
    vertices, faces : (V, 3) metres world frame and (T, 3) int, the room mesh
    colours : (V, 3) uint8 sRGB, the colour of each vertex
    emitters : drawn largest first, so a small one stays visible; numbered 1.. in the list's order
    cameras : (F, 4, 4) camera-to-world poses, each a dot with a tick along its view direction
    facing : +1 the mesh's front faces the cameras, -1 its back, 0 either (a fit's ``seen_side``; 0 is taken
        as +1): the triangles whose seen side faces down (ceilings, undersides) are left out
    marked : ``{label: T_c2w (4, 4)}`` cameras drawn larger and labelled (the photos beside the top view)

    Returns
    -------
    (view.height, view.width, 3) uint8 RGB
    """
    import cv2

    image = np.empty((view.height, view.width, 3), np.uint8)
    image[:] = BACKGROUND
    _surface(view, vertices, faces, np.asarray(colours, np.uint8), facing, image)
    poses = np.asarray(cameras, np.float64).reshape(-1, 4, 4)
    if len(poses):
        tick = 12.0 / view.scale                       # metres: a 12-px tick
        ends = view.pixels(np.concatenate([poses[:, :3, 3], poses[:, :3, 3] + tick * poses[:, :3, 2]]))
        for a, b in zip(ends[:len(poses)], ends[len(poses):]):
            if np.all(np.isfinite(a)) and np.all(np.isfinite(b)):
                cv2.line(image, _pt(a), _pt(b), CAMERA_RGB, 1, cv2.LINE_AA)
                cv2.circle(image, _pt(a), 2, CAMERA_RGB, -1, cv2.LINE_AA)
    for label, T in (marked or {}).items():
        T = np.asarray(T, np.float64)
        a, b = view.pixels(np.stack([T[:3, 3], T[:3, 3] + 24.0 / view.scale * T[:3, 2]]))
        cv2.arrowedLine(image, _pt(a), _pt(b), (0, 0, 0), 4, cv2.LINE_AA, tipLength=0.35)
        cv2.arrowedLine(image, _pt(a), _pt(b), CAMERA_RGB, 2, cv2.LINE_AA, tipLength=0.35)
        _outlined_text(image, label, (_pt(a)[0] - 14, _pt(a)[1] + 5), 0.5, CAMERA_RGB)
    centres = view.pixels(np.array([e.centre for e in emitters])) if emitters else np.zeros((0, 2))
    for k in sorted(range(len(emitters)), key=lambda k: (-emitters[k].power_share, k)):
        c, r = _pt(centres[k]), marker_radius(emitters[k].power_share)
        cv2.circle(image, c, r + 2, (0, 0, 0), -1, cv2.LINE_AA)
        cv2.circle(image, c, r, light_rgb(emitters[k].radiance), -1, cv2.LINE_AA)
    for k in range(min(LABELLED, len(emitters))):
        c, r = _pt(centres[k]), marker_radius(emitters[k].power_share)
        _outlined_text(image, str(k + 1), (c[0] + r + 3, c[1] + 5))
    _scale_bar(image, view)
    return image


def _pt(p: np.ndarray) -> tuple[int, int]:
    """A pixel point for OpenCV (clamped far outside the picture, where OpenCV's integers would overflow)."""
    q = np.clip(np.nan_to_num(np.asarray(p, np.float64)), -1e5, 1e5)
    return int(round(q[0])), int(round(q[1]))


def border_arrow(camera: Camera, point_w: np.ndarray, *, inset: int = BORDER_INSET) -> tuple | None:
    """Where to draw the arrow toward a world point outside ``camera``'s picture: ``(tail (2,), head (2,))``
    pixels with the head ``inset`` pixels inside the border, or None when the point is in the picture.

    The direction is the point's camera-frame ``(fx x, fy y)``: toward it on the picture for a point in front
    of the camera, and the way to turn toward it for one behind.
    """
    pc = camera.w2c(np.asarray(point_w, np.float64)[None])[0]
    (uv,), _ = camera.project_cam(pc[None])
    W, H = camera.width, camera.height
    if pc[2] > 0 and 0 <= uv[0] <= W - 1 and 0 <= uv[1] <= H - 1:
        return None
    d = np.array([camera.K[0, 0] * pc[0], camera.K[1, 1] * pc[1]])
    d = d / np.linalg.norm(d) if np.linalg.norm(d) > 0 else np.array([0.0, 1.0])
    c = np.array([(W - 1) / 2, (H - 1) / 2])
    half = c - inset
    with np.errstate(divide="ignore"):
        t = np.min(np.where(np.abs(d) > 1e-12, half / np.abs(d), np.inf))
    head = c + t * d
    return head - min(ARROW_PX, t) * d, head


def draw_photo(photo: np.ndarray, camera: Camera, emitters: list[Emitter], *, label: str = "",
               width: int = PANEL_WIDTH) -> np.ndarray:
    """``photo (H, W, 3) uint8 sRGB`` of ``camera``, resized to ``width``, with the emitters' centres: a ring
    where one projects into the picture, and for the LABELLED brightest outside it an arrow at the border
    toward it (numbered as in :func:`draw_top`); ``label`` on a strip above the photo.

    Returns
    -------
    (STRIP_PX + height at ``width``, width, 3) uint8 RGB
    """
    import cv2

    cam = camera.scaled(width / camera.width)
    image = cv2.resize(np.asarray(photo, np.uint8), (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    for k in sorted(range(len(emitters)), key=lambda k: (-emitters[k].power_share, k)):
        e, num = emitters[k], (str(k + 1) if k < LABELLED else "")
        colour = light_rgb(e.radiance)
        arrow = border_arrow(cam, e.centre)
        if arrow is None:
            (uv,), _ = cam.project(e.centre[None])
            c, r = _pt(uv), marker_radius(e.power_share) + 2
            cv2.circle(image, c, r, (0, 0, 0), 4, cv2.LINE_AA)
            cv2.circle(image, c, r, colour, 2, cv2.LINE_AA)
            cv2.circle(image, c, 2, colour, -1, cv2.LINE_AA)
            if num:
                _outlined_text(image, num, (c[0] + r + 3, c[1] + 5))
        elif num:
            tail, head = arrow
            cv2.arrowedLine(image, _pt(tail), _pt(head), (0, 0, 0), 5, cv2.LINE_AA, tipLength=0.4)
            cv2.arrowedLine(image, _pt(tail), _pt(head), colour, 2, cv2.LINE_AA, tipLength=0.4)
            back = tail - 10 * (head - tail) / max(np.linalg.norm(head - tail), 1e-9)
            _outlined_text(image, num, (_pt(back)[0] - 4, _pt(back)[1] + 5))
    strip = np.empty((STRIP_PX, cam.width, 3), np.uint8)
    strip[:] = BACKGROUND
    if label:
        cv2.putText(strip, label, (6, STRIP_PX - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.5, CAMERA_RGB, 1, cv2.LINE_AA)
    return np.concatenate([strip, image])
