"""Step 2, the observations: what the photos say about the room's radiance.

Each photo casts a strided pixel grid against the closed room. Photos are linear (sRGB decoded) and divided by
their exposure relative to the mesh colours. A clipped pixel (a channel at or above the threshold) is a lower
bound, never a value: it votes for its mesh vertices being an emitter. The unclipped, lit pixels on the mesh
are the points the fit explains; those through holes give the radiance of the box cell they meet. A clipped
light's own colour shows where its edge covers a pixel in part (:func:`clipped_edge_excess`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.color import LUMINANCE_F64, decode_u8, exposure_ratio, srgb_to_linear
from pipeline.trace.lightfit.closure import Room
from pipeline.trace.lightfit.settings import FitSettings
from pipeline.trace.lightfit.transport import at
from pipeline.trace.photolights import EXPOSURE_RANGE, MIN_EXPOSURE_SAMPLES

MIN_FIT_POINTS = 50           # unclipped room points needed to fit anything
DARK_LEVEL = 0.004            # linear photo level below which a pixel carries no information (sRGB ~ 13)
SIDE_SHARE = 0.9              # share of the camera rays meeting one side of the mesh that makes the other side unseen
EDGE_RING_PX = 1.5            # unclipped pixels this close to a clipped one (their centres) may hold part of it
EDGE_BACK_PX = (3.5, 7.0)     # pixels this far from every clipped one show the surface around it
EDGE_WINDOW_PX = 15           # ... averaged over a window this many pixels across
EDGE_MIN_EXCESS = 0.05        # linear luminance over that surface a pixel needs to count (an 8-bit step: ~0.004)
EDGE_MIN_PIXELS = 30          # such pixels, over all the photos, that measure the colour


@dataclass(frozen=True)
class Observations:
    """The photos' samples of the room, summed per mesh vertex and box cell."""

    mesh_rad: np.ndarray       # (nv, 3) float64 linear radiance per mesh vertex: its colour, or the photos' mean
    seen: np.ndarray           # (nv,) int64 grid rays that met a triangle of the vertex
    clipped_v: np.ndarray      # (nv,) int64 ... of which were clipped
    box_sum: np.ndarray        # (C, 3) float64 summed unclipped radiance seen on each box cell
    box_n: np.ndarray          # (C,) int64 unclipped rays that met the cell
    box_clip: np.ndarray       # (C,) int64 clipped rays that met the cell
    points: np.ndarray         # (m, 3) float64 metres, the lit, unclipped mesh points the photos saw
    normals: np.ndarray        # (m, 3) float64 their unit normals, facing the camera
    radiance: np.ndarray       # (m, 3) float64 their linear radiance (exposure removed)
    exposures: list            # each photo's exposure relative to the mesh colours (1 without colours)
    sides: np.ndarray          # (2,) int64 camera rays that met a mesh triangle's front / back
    seen_side: int             # the side of the mesh the cameras see: +1 front, -1 back, 0 either
    edge_pixels: int | None    # edge pixels of clipped lights that measured their colour (None: not read)
    edge_colour: np.ndarray | None  # (3,) float64 colour (red 1) of the clipped lights, from their edges


@dataclass(frozen=True)
class FitPoints:
    """The room points the fit explains, drawn from the observations."""

    P: np.ndarray              # (n, 3) float64 metres
    N: np.ndarray              # (n, 3) float64 unit normals
    L: np.ndarray              # (n, 3) float64 linear radiance the photos saw

    @property
    def n(self) -> int:
        return len(self.P)


def observe(room: Room, frames: list, colors: np.ndarray | None, st: FitSettings) -> Observations:
    """The :class:`Observations` of ``room`` in ``frames`` (photo (H, W, 3) uint8 sRGB, K, T_c2w), the mesh's
    ``colors`` (V, 3) uint8 sRGB (or None) setting each photo's exposure."""
    F, nv, nt, nb = room.F, room.nv, room.nt, len(room.box_centre)
    scale_r = float(st.radiance_scale)
    mesh_rad = srgb_to_linear(np.asarray(colors)).astype(np.float64) * scale_r if colors is not None else None
    seen, clipped_v = np.zeros(nv, np.int64), np.zeros(nv, np.int64)
    box_sum, box_n, box_clip = np.zeros((nb, 3)), np.zeros(nb, np.int64), np.zeros(nb, np.int64)
    vsum, vn = np.zeros((nv, 3)), np.zeros(nv, np.int64)
    obs_p, obs_n, obs_L = [], [], []
    exposures = []
    sides = np.zeros(2, np.int64)
    edge_excess = []                  # per photo, its clipped lights' edge pixels
    # (not read where the lights handed in are every light: the fit then colours no light of its own)
    read_edges = st.edge_colour and not (room.known_quads and st.known_complete)
    for (photo, _, _), cam in zip(frames, room.cameras):
        photo = np.asarray(photo, np.uint8)
        if read_edges:
            edge_excess.append(clipped_edge_excess(photo, st.threshold))
        o, d, hits, lin, clip = _grid_samples(room, cam, photo, st)
        on_mesh = hits.hit & (hits.prim < nt)
        expo = _exposure(mesh_rad, F, hits, lin, on_mesh & ~clip, scale_r)
        exposures.append(expo)
        lin /= expo
        if on_mesh.any():
            # > 0: the ray met the triangle's back (its normal's side away from the camera)
            facing = np.zeros(len(d))
            facing[on_mesh] = np.sum(room.tri_normal[hits.prim[on_mesh]] * d[on_mesh], axis=1)
            back = facing[on_mesh] > 0
            sides += [int((~back).sum()), int(back.sum())]
            tri = F[hits.prim[on_mesh]]
            np.add.at(seen, tri.ravel(), 1)
            np.add.at(clipped_v, tri[clip[on_mesh]].ravel(), 1)
            okm = np.flatnonzero(on_mesh & ~clip)
            tr = F[hits.prim[okm]]
            for k in range(3):
                np.add.at(vsum, tr[:, k], lin[okm])
                np.add.at(vn, tr[:, k], 1)
            good = okm[(lin[okm] @ LUMINANCE_F64) > DARK_LEVEL * scale_r]
            if good.size:
                prim = hits.prim[good]
                obs_p.append(o[good] + hits.t[good, None] * d[good])
                obs_n.append(room.tri_normal[prim] * -np.sign(facing[good, None] + 1e-30))
                obs_L.append(lin[good])
        on_box = hits.hit & (hits.prim >= nt) & (hits.prim < room.nbt)
        if on_box.any():
            cell = (hits.prim[on_box] - nt) // 2
            np.add.at(box_sum, cell[~clip[on_box]], lin[on_box][~clip[on_box]])
            np.add.at(box_n, cell[~clip[on_box]], 1)
            np.add.at(box_clip, cell[clip[on_box]], 1)
    if mesh_rad is None:   # no colours: each vertex gets the mean of the photo pixels that saw it
        mesh_rad = _photo_colours(vsum, vn)
    # a scan is a shell seen from inside, and a table top or a shelf is one sheet with no underside: the side
    # of the mesh's triangles the cameras see (+1 front, -1 back, 0 either)
    seen_side = (1 if sides[0] >= SIDE_SHARE * sides.sum() else -1 if sides[1] >= SIDE_SHARE * sides.sum() else 0)
    empty = np.zeros((0, 3))
    return Observations(
        mesh_rad=mesh_rad, seen=seen, clipped_v=clipped_v, box_sum=box_sum, box_n=box_n, box_clip=box_clip,
        points=np.concatenate(obs_p) if obs_p else empty, normals=np.concatenate(obs_n) if obs_n else empty,
        radiance=np.concatenate(obs_L) if obs_L else empty, exposures=exposures, sides=sides, seen_side=seen_side,
        edge_pixels=int(sum(len(x) for x in edge_excess)) if edge_excess else None,
        edge_colour=edge_colour(np.concatenate(edge_excess)) if edge_excess else None)


def _grid_samples(room: Room, cam, photo: np.ndarray, st: FitSettings) -> tuple:
    """The strided pixel grid of ``photo`` seen by ``cam``: ray origins and directions, their hits in the room,
    the pixels' linear radiance (x radiance_scale, exposure not removed) and whether each is clipped."""
    h, w = photo.shape[:2]
    ys, xs = np.mgrid[st.stride // 2:h:st.stride, st.stride // 2:w:st.stride]
    pix = (ys * w + xs).ravel()
    o, d = cam.rays(pix, np.full((pix.size, 2), 0.5, np.float32))
    hits = room.isect.intersect(o, d)
    col = photo.reshape(-1, 3)[pix]
    lin = srgb_to_linear(col).astype(np.float64) * float(st.radiance_scale)
    return o, d, hits, lin, col.max(axis=1) >= st.threshold


def _exposure(mesh_rad: np.ndarray | None, F: np.ndarray, hits, lin: np.ndarray, usable: np.ndarray,
              scale_r: float) -> float:
    """A photo's exposure relative to the mesh colours ``mesh_rad`` (1 without them): the median ratio of its
    ``usable`` pixels' luminance to the colours where their rays met the mesh, as the trace stage takes it."""
    if mesh_rad is None:
        return 1.0
    ok = np.flatnonzero(usable)
    ratio = exposure_ratio(lin[ok] @ LUMINANCE_F64,
                           at(mesh_rad, F, hits.prim[ok], hits.u[ok], hits.v[ok]) @ LUMINANCE_F64,
                           floor=DARK_LEVEL * scale_r, min_samples=MIN_EXPOSURE_SAMPLES)
    return 1.0 if ratio is None else float(np.clip(ratio, *EXPOSURE_RANGE))


def _photo_colours(vsum: np.ndarray, vn: np.ndarray) -> np.ndarray:
    """(nv, 3) mean radiance of the photo pixels that saw each vertex (``vsum`` over ``vn``), the mean of all
    where none did."""
    mesh_rad = np.zeros((len(vn), 3))
    have = vn > 0
    mean_obs = (vsum[have].sum(axis=0) / max(vn[have].sum(), 1)) if have.any() else np.zeros(3)
    mesh_rad[have] = vsum[have] / vn[have, None]
    mesh_rad[~have] = mean_obs
    return mesh_rad


def select_points(obs: Observations, count: int, rng: np.random.Generator) -> FitPoints:
    """At most ``count`` of the observed points, drawn without replacement (in their order)."""
    P, N, L = obs.points, obs.normals, obs.radiance
    sel = np.sort(rng.choice(len(P), size=min(len(P), count), replace=False))
    return FitPoints(P=P[sel], N=N[sel], L=L[sel])


def clipped_edge_excess(photo: np.ndarray, threshold: int) -> np.ndarray:
    """(m, 3) linear radiance over the surface around them of the unclipped pixels of ``photo (H, W, 3) uint8``
    next to clipped ones (a channel ``>= threshold``; centres within EDGE_RING_PX), where that excess is at least
    EDGE_MIN_EXCESS in luminance and positive in every channel (its colour has a ratio). The surface is the mean
    of the pixels EDGE_BACK_PX from every clipped one in an EDGE_WINDOW_PX window. Empty where no pixel (or every
    pixel) is clipped.

    Why: a pixel that a clipped light's edge covers in part holds the light's radiance times that part plus
    the surface's for the rest; with the light many times brighter than the surface, the excess has the light's
    colour, which its clipped pixels no longer show."""
    import cv2

    clip = (np.maximum(np.maximum(photo[..., 0], photo[..., 1]), photo[..., 2]) >= threshold).view(np.uint8)
    if not clip.any() or clip.all():
        return np.zeros((0, 3))
    dist = cv2.distanceTransform(1 - clip, cv2.DIST_L2, 3)
    ring = (dist > 0) & (dist <= EDGE_RING_PX)
    back = ((dist >= EDGE_BACK_PX[0]) & (dist <= EDGE_BACK_PX[1])).astype(np.float32)
    lin = decode_u8(photo)
    size = (EDGE_WINDOW_PX, EDGE_WINDOW_PX)
    total = cv2.boxFilter(lin * back[..., None], -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    count = cv2.boxFilter(back, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    m = ring & (count > 0.5)
    excess = lin[m].astype(np.float64) - total[m].astype(np.float64) / count[m][:, None]
    return excess[((excess @ LUMINANCE_F64) > EDGE_MIN_EXCESS) & np.all(excess > 0, axis=1)]


def edge_colour(excess: np.ndarray) -> np.ndarray | None:
    """(3,) colour (red 1) of the clipped lights from the edge pixels :func:`clipped_edge_excess` gives
    (``excess (m, 3)``, positive): their median green / red and blue / red; None with fewer than EDGE_MIN_PIXELS."""
    ex = np.asarray(excess, np.float64).reshape(-1, 3)
    if len(ex) < EDGE_MIN_PIXELS:
        return None
    return np.array([1.0, float(np.median(ex[:, 1] / ex[:, 0])), float(np.median(ex[:, 2] / ex[:, 0]))])
