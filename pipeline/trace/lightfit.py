"""The room's light sources recovered from its photos by inverse rendering (``trace.lighting = "fit"``).

A scan's photos show the room's surfaces, not its lamps: the lamps hang above every photo's field of
view, a window is a hole the depth sensor never saw, a lamp in view is clipped at sensor white. Lighting
the objects with the room mesh's colours alone (the "scan" mode) therefore misses the main light, and the
objects come out too dark, with the colour of the walls and no directional shadow. This module finds
what emits light and how much, so that rendering the room with it reproduces the photos, in the spirit of
Yu et al., "Inverse Global Illumination" (SIGGRAPH 1999), reduced to what a CPU does in seconds:

1. **Closure.** The room mesh is closed by a box (the mesh's and the cameras' extent about ``up``, the
   wall behind each camera half a metre behind it, :func:`box_extent`, plus a margin) cut into cells of
   about ``cell`` metres: every ray that leaves the mesh through a hole, or past the top of the scanned
   walls, meets a cell, so unseen light gets a place in the room, not only a direction. A cell the mesh
   hides from every camera (behind a wall) is not part of the room: it stays dark (:func:`_behind_the_mesh`).
2. **Observations.** Each used photo casts a strided pixel grid against mesh + box. Photos are linear
   (sRGB decoded) and divided by their exposure relative to the mesh colours (median ratio, as the
   trace stage measures it per frame). Rays through holes give the radiance of the box cell they meet;
   a clipped pixel (a channel ``>= threshold``) is a lower bound, never a value. Mesh regions the photos
   see clipped (voted per vertex, as :mod:`pipeline.trace.photolights` does; where the strided grid met a
   vertex fewer than twice, its clipped colour votes) are emitters of unknown radiance, bounded below by
   sensor white. Without the colour's vote the suite's window came out as scattered pieces of half its
   area in the mesh, the rest taken as a known radiance of sensor white.
3. **Unknowns.** The radiance of every box cell no photo saw unclipped, and of every clipped mesh
   region: non-negative RGB, bounded below where clipped.
4. **Fit.** At up to ``points`` room points the photos saw unclipped, a diffuse surface of albedo
   ``rho`` shows ``L = rho / pi * (E_known + A e)``: ``E_known`` is the irradiance from the room's known
   radiance (cosine-weighted hemisphere rays against mesh + box, the mesh's colours where they hit it; from
   the side of a triangle no camera saw, not its colour: a table top is one sheet, and its unseen back
   reflects the low surfaces' light with the sheet's own albedo, :func:`_sheet_backs`), ``A e`` the
   irradiance from the unknown emitters
   (their area sampled explicitly, with visibility through the room's own geometry, so the shadows
   furniture casts in the photos say where light comes from). Albedo is one RGB value per patch of the
   mesh, clamped to ``ALBEDO_RANGE``: a patch joins the cells of ``albedo_cell`` metres facing one of six
   directions whose photo chromaticity falls in one bin of ``albedo_group`` (one material seen under
   different light, :func:`_chromaticity_groups`). The fit alternates non-negative least squares for
   ``e`` (relative error, weighed by the photo's level around each point, :func:`_relative_weights`; an
   L1 prior on emitted power: few, bright emitters) with the albedo, over a search of the albedo's
   overall level, the one thing a diffuse image cannot tell from the light's strength on its own: the
   light the known surfaces send each other (``E_known``) pins it.
   Stage 2 lets only the cells that carry most of that light emit (the rest reflect) and takes each
   channel's level at the residual's minimum. Patch albedos may be pulled toward the level
   (``albedo_shrink`` pseudo-points per patch; 0 by default). With an albedo per cell, each cell explains
   its own light with its albedo: without the pull the suite's dark table top came out 1.3-1.5x too
   bright (the light reaching it too weak, the objects standing on it too dark); with a pull of 2-4 its
   bright walls came out 0.8x too dark. The patches by material pin the contrast instead.
   The unseen walls above the scan reflect with the albedo of the upper walls the photos saw
   (:func:`_wall_ratio`, under stage 1's light), not with the level, which the floor and the furniture pull
   down and warm: with the true lights handed in, the suite's window room's objects came out 0.93/0.88/0.86
   of the truth's brightness with the level, 0.95/0.93/0.91 with the walls'. The unseen ceiling reflects as
   white paint (``ceiling_albedo``, :data:`CEILING_ALBEDO`): what comes back down from it is the known light
   that most sets the level (the fit's power over the truth's moved 0.82-1.09x in the suite's dim room with
   the albedo assumed for the unseen cells), and with the walls' albedo there the window room, whose light
   reaches the table mostly off the ceiling, came out at 1.5-1.9x the truth's power in four seeds of five.
   Stage 3 (``refine``): each emitting cell is cut into lamps of ``refine`` metres, at the box and, under a
   ceiling cell, hanging up to ``REFINE_DEPTHS[-1]`` below it in free space no photo saw; the sparsity
   prior picks among them, the level is searched again with the lamps pinned (a parabola through the
   lowest residuals), and the chosen lamps are refitted without the prior. A 10 cm spot 1.2 m above a
   table is then found there, not smeared over a 0.4 m ceiling cell 0.65 m higher. But the squares' grid
   (``refine`` metres, depths 0.25 m apart) cut that spot into four squares 7 cm too high, about twice its
   size: the objects under it came out 0.95 / 0.88 / 0.80 of the truth's brightness. Where a light is,
   and how big, is what the objects see most (the true rectangle handed in as the only candidate: 27.8 dB
   against 25.5; the true size 7 cm higher: 24.3), and the same objective tells it: over a grid of heights
   and sizes it is lowest at the truth's height. So stage 3's lamps are polished (``polish``,
   :func:`_coordinate_search`): each cluster of touching lamps hung below the ceiling becomes one
   rectangle, started as one square where the cluster's light is, its height searched on a grid five times
   finer, then its height, place and size one at a time, with the other lamps held. The spot room's objects
   then came out 27.3 / 27.3 / 27.7 dB at run seeds 0-2 (25.5 / 26.4 / 25.9), blue 0.86-0.91 (0.80-0.86), its
   lamp 3 cm from the truth's (8 cm); rooms without hanging lamps are unchanged, the others moved by -0.54 to
   +0.06 dB; about 2 s more per fit (60 evaluations of a cluster, each one lamp's columns and a refit).
   Stage 1 (the search over all unknowns) uses every other point, stage 3's choice among its ~900 lamps
   every fourth (half their shadow rays, the fit's largest single cost: the 7-Scenes kitchen's fit 28 -> 24
   CPU s, the suite's objects PSNR within run-seed noise); stage 2's and 3's levels and the chosen emitters'
   power use all of them. Each level search evaluates every other level of the grid, then the levels next
   to what it picks (:func:`_level_search`: the whole grid's answer where the objective falls and then
   rises, from 11-13 of its 19 levels). The level is
   the noisiest thing the fit finds: on the suite, 8000 points this way held each room's objects PSNR
   within 1.3 dB across run seeds at about the cost of 4000 everywhere (within up to 1.5 dB; 2000: 7 dB);
   16000 (the default) raised the tuned rooms' objects PSNR by 0.5 dB over three run seeds (lamp_in_view
   +0.9, window +0.7, ceiling 0.0) for about twice the fit's seconds.
5. **Result.** :class:`RoomLights`: the mesh plus the box with a linear radiance per vertex (the mesh's
   colours, fitted radiance on emitters and unseen cells) and the triangles to sample as lights
   (emitters with a visible share of the power; the lamps join the mesh as small one-sided rectangles),
   and the albedo the fit found per vertex (a mesh vertex takes its nearest fit point's, on a surface
   facing the same way; the rest the level; the box's sides the upper walls', its top the ceiling's). The
   trace stage lights and shadows the objects with it, and takes the objects' shadows out of the room's
   light they see with the albedo.

White balance comes from the same fit: each channel has its own albedo level, and the emitters found share one
colour, fitted over the three channels together (``shared_colour``, :func:`_shared_colour`), so they get the
colour that explains several surfaces under one light, and the objects' own colours are lit in the photo's
colour space; no grey-world assumption is made. One colour per kind of emitter: the ones the photos saw clipped
(a lamp or a window in view, a lower bound on their radiance) share one, the ones no photo saw (the box's cells,
the lamps hung below them) another. A warm lamp in view and a neutral ceiling fill above the views are two
fixtures, and the fill lights the tops of the objects on a table: with one colour for both, the suite's
lamp-in-view room's fill came out as warm as the lamp (blue/red 0.60, the truth's 0.92); per kind, its objects'
blue is 0.80-0.94x the truth's at run seeds 0-2 (0.77-0.91x with one colour and the same supports; the fill
itself still comes out warmer than the truth's, blue/red 0.68-0.78). Solved channel by channel, each channel put
its light wherever it explained its own surfaces best: the suite's coloured room came out lit by a pure-red and
a pure-green lamp, each on the wall of the other colour. The light's colour itself follows from the three
channels' albedo levels, and each channel's objective is nearly flat about its minimum (the true light sits
within 0.1-2.6 % of it on the suite) while the light's power goes about as the inverse square of the level: with
each channel at its own minimum, the coloured room's deep red walls came out lit red (power 1.21 / 0.58 / 0.58
of the truth's). The last stage therefore takes the levels with a prior pulling the light's colour toward the
photos' white (``white_prior``, :func:`_white_levels`): a prior on the light, not on the surfaces' average (grey
world would make those walls' light redder still), that gives way where a channel's objective is steep.
Projecting the shared colour onto the Planckian locus at fixed levels instead (tried before,
lighting_seeds.json: not kept) left the levels, and with them the room's albedo, where they were. Where stage 3
found lamps, the prior is on the room's brightest surfaces instead (``white_patch``, :func:`_grey_levels`): the
largest albedo patches of the brightest tenth of the points are pulled toward grey, as white paint, a ceiling or
a cabinet is. With the suite's true albedos handed to the fit, its lights come out the truth's colour (power
0.89-0.93x in every channel, ceiling and coloured rooms), and the median residual is the fit's own to within
4 %: the colour error is the albedo's, and the photos barely tell it. The light's prior took a warm lamp over
white walls for a white one (the suite's ceiling room, blue 1.3x); the brightest surfaces, not the light, are
what a room most often keeps near grey.

A light the photos saw clipped (a lamp or a window in view) shows its own colour where it is not clipped: a pixel
its edge covers in part holds its radiance times that part plus the surface around it for the rest, so the
excess of such pixels over that surface has the light's colour less the surface's, the light's where it is many
times brighter (:func:`_clipped_edge_excess`; the suite's lamp in view, about 70x its wall: green / red 0.87 and
blue / red 0.66, the truth's 0.86 / 0.70; its window 1.19 / 1.41, the truth's 1.18 / 1.39). Where at least
EDGE_MIN_PIXELS such pixels show it (``edge_colour``), the fit's clipped emitters take that colour at the
luminance the fit found for them (brighter where a channel would fall under sensor white); the fit's own colour
for them follows the albedo's (the lamp in view: blue / red 0.60 at run seeds 0-2). The albedo stays the fit's.
On the suite that moved the lamp room's objects' blue from 0.89 / 0.83 / 0.82 of the truth's to 0.91 / 0.84 /
0.83 (seeds 0-2) and the window room's from 0.93 / 0.93 / 0.92 to 0.94 / 0.94 / 0.95, each room's objects PSNR
by -0.12 to +0.12 dB; the other rooms have no clipped pixel. Pulling the albedo levels toward the edges' colour
instead (as ``white_patch`` does toward grey) over-lit the window room in blue (the light at the objects' places
1.29x the truth's at seed 1, by the light probe's measure), and both pulls at once brought neither room nearer
(lighting_seeds.json, session 29).

Cost (640x480, 8 photos, 16000 points): 10-20 CPU seconds on the light suite; computed once per scan and kept in
``RUN/trace/<scene>/lights.npz``.
"""

from __future__ import annotations

import collections
import functools
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from pipeline.color import LUMINANCE_F64, decode_u8, exposure_ratio, srgb_to_linear
from pipeline.geometry import up_frame
from pipeline.trace.photolights import EXPOSURE_RANGE, MIN_EXPOSURE_SAMPLES

log = logging.getLogger(__name__)

ALBEDO_RANGE = (0.02, 0.95)   # plausible diffuse albedo of room surfaces (linear, per channel)
# the room's albedo level (per channel, the geometric mean over the photographed patches) is searched over these;
# a room with deep red or green walls or a dark floor has a channel well below 0.15 (the suite's coloured room,
# walls 0.06-0.09 in blue: the fit sat at 0.15, the old grid's end, and lit the objects 0.78x too little in blue)
ALBEDO_LEVELS = (0.05, 0.075, 0.1, 0.125, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7, 0.75,
                 0.8, 0.85)
MIN_FIT_POINTS = 50           # unclipped room points needed to fit anything
DARK_LEVEL = 0.004            # linear photo level below which a pixel carries no information (sRGB ~ 13)
MARGIN = 0.02                 # metres between the mesh's extent and the closing box
LOW_FILL_M = 0.8              # box cells lower than this above the scan's lowest point are filled, not fitted
ASSUMED_CEILING_M = 2.5       # a scan shorter than this (floor to top) is closed at this height above its lowest point
BEHIND_CAMERA_M = 0.5         # the unseen wall behind a camera is at least this far behind it (horizontally)
PRIOR_ALBEDO = 0.5            # albedo at which the sparsity prior's weight is measured against the data term
REFINE_DEPTHS = (0.0, 0.25, 0.5, 0.75)  # stage 3: metres below an emitting ceiling cell a lamp may hang
# stage 3's polish (polish): each cluster of touching lamps holding at least POLISH_SHARE of their power becomes
# one rectangle, moved along its normal and in its plane and resized by a coordinate search from these first
# steps (metres along the normal, along its two edges; log of its two half sizes), halving POLISH_HALVINGS times
POLISH_SHARE = 0.1
POLISH_STEPS = (0.05, 0.04, 0.04, 0.3, 0.3)
POLISH_DEPTH_STEP_M = 0.05    # the search starts at the best of the depths this far apart
POLISH_HALVINGS = 3
POLISH_MIN_HALF_M = 0.01      # the smallest lamp the polish makes: 2 cm across
LAMP_MIN_M = 1.5              # stage 3: a hanging lamp is at least this far above the scan's lowest point
COLUMN_CHUNK = 8              # columns whose shadow rays are traced together (on the fit's threads)
WALL_COS = 0.3                # a fit point whose normal is this close to horizontal (cosine to up) is on a wall
WEIGHT_NEIGHBOURS = 16        # points whose median photo luminance sets a point's least-squares weight
NORMAL_METRES = 2.0           # ... in a space where a unit normal counts as this many metres
SIDE_SHARE = 0.9              # share of the camera rays meeting one side of the mesh that makes the other side unseen
# the room's brightest surfaces (white_patch): the albedo patches holding at least BRIGHT_MIN_SHARE of the fit
# points each, brightest first, until they hold BRIGHT_SHARE of them (a patch of a few points, a lamp's edge or a
# sliver the light misses, is no surface to balance on)
BRIGHT_SHARE = 0.1
BRIGHT_MIN_SHARE = 0.01
# the colour of the lights the photos saw clipped, from the unclipped pixels their edges cover in part
# (edge_colour, :func:`_clipped_edge_excess`)
EDGE_RING_PX = 1.5            # unclipped pixels this close to a clipped one (their centres) may hold part of it
EDGE_BACK_PX = (3.5, 7.0)     # pixels this far from every clipped one show the surface around it
EDGE_WINDOW_PX = 15           # ... averaged over a window this many pixels across
EDGE_MIN_EXCESS = 0.05        # linear luminance over that surface a pixel needs to count (an 8-bit step: ~0.004)
EDGE_MIN_PIXELS = 30          # such pixels, over all the photos, that measure the colour
EDGE_RAISE_WARN = 1.5         # the edges' colour raising a clipped light's brightness more than this is said
LIGHT_SHARE = 0.002           # emitters with at least this share of the fitted power are sampled as lights
# albedo of a ceiling no photo saw: white paint (EN 12464-1 recommends 0.7-0.9 for a ceiling; it is the surface
# a room most often leaves white)
CEILING_ALBEDO = 0.8
CEILING_COS = 0.7             # a closing box cell whose normal is this close to down is the ceiling
# a mesh vertex this close to a known light (trace.lights_file) is that light's surface: the light suite's oracle
# hands its lamps in 2 cm off their wall, and a scan's wall around a lamp is a voxel or two rough
KNOWN_LIGHT_REACH_M = 0.05
# with lights handed in, the fit says so when the light it adds of its own has more than this share of their power
OWN_OVER_KNOWN_SAID = 0.5
REGION_SAMPLES = 16           # area samples per (unseen cell, clipped region) pair


@dataclass(frozen=True)
class FitSettings:
    """Knobs of :func:`fit_room_lights` (the trace stage fills them from TraceConfig)."""

    points: int = 16000         # room points the fit uses at most (every other one to find where the light is)
    gather_rays: int = 64       # hemisphere rays per point for the known irradiance
    emitter_samples: int = 2    # area samples per (point, unknown) pair
    cell: float = 0.4           # metres, size of the closing box's cells
    albedo_cell: float = 0.5    # metres, size of an albedo patch
    albedo_shrink: float = 0.0  # prior pulling each patch's albedo to the room's level, in mean points per patch
    albedo_group: float = 0.03  # cells whose photo chromaticity falls in one bin this wide share an albedo (0 = off)
    stride: int = 8             # photo pixels between grid rays
    threshold: int = 250        # 8-bit level at which a channel counts as clipped
    min_share: float = 0.5      # share of clipped observations that makes a mesh vertex an emitter
    sparsity: float = 0.4       # L1 weight on emission (columns normalised; relative to the data term's scale)
    level_tolerance: float = 0.05  # the highest albedo level whose objective is within this share of the best
    # stage 2: the cells carrying this share of stage 1's power emit, the rest reflect (and stage 3 keeps the lamps
    # carrying this share of its power). 0.99 dropped the suite's weak ceiling fills: stage 1, at the least light
    # that explains the photos, gives a fill 6-10 % of the true power 0.4-1.5 % of its own; the objects on the
    # table under it then lost the neutral light from above (lamp in view, true fill handed in: blue 0.81 -> 0.91)
    support_share: float = 0.999
    max_emitters: int = 24      # stage 2: at most this many unknown cells emit (0 = no second stage)
    refine: float = 0.1         # stage 3: metres, size of the lamps the emitting cells are refined into (0 = off)
    polish: int = 60            # stage 3: objective evaluations placing and sizing each cluster of lamps (0 = off)
    radiance_scale: float = 1.0  # the trace stage's: radiance = this x linear colour
    shared_colour: bool = True  # every emitter found is one colour (fitted); False: each channel on its own
    white_prior: float = 0.1    # last stage without white_patch: pull of the emitters' colour toward white (0 = off)
    white_patch: float = 1.0    # last stage: pull of the brightest surfaces' albedo toward grey (0 = white_prior's)
    ceiling_albedo: float = CEILING_ALBEDO  # the unseen ceiling's albedo, white (0 = the upper walls', as the sides)
    known_complete: bool = False  # the known lights are every light: the fit adds none (trace.lights_complete)
    edge_colour: bool = True    # the lights the photos saw clipped take the colour of the pixels their edges cover


@dataclass(frozen=True)
class RoomLights:
    """The room mesh closed by a box, with a fitted linear radiance per vertex."""

    vertices: np.ndarray       # (V, 3) float32: the mesh's vertices, then the box's
    faces: np.ndarray          # (T, 3) int32: the mesh's triangles, then the box's
    radiance: np.ndarray       # (V, 3) float32 linear radiance (x radiance_scale)
    light_tri: np.ndarray      # (T,) bool: triangles sampled explicitly as lights
    num_mesh_vertices: int
    num_mesh_tris: int
    summary: dict = field(default_factory=dict)   # what was fitted and assumed (JSON-able)
    albedo: np.ndarray | None = None   # (V, 3) float32 linear albedo the fit found (None: not fitted)

    def save(self, path) -> None:
        from pipeline.io import atomic_save_npz
        import json

        keep = {k: v for k, v in self.summary.items() if k != "seconds"}   # same seed, same bytes: no timings
        atomic_save_npz(path, vertices=self.vertices, faces=self.faces, radiance=self.radiance,
                        albedo=(np.zeros_like(self.radiance) if self.albedo is None else self.albedo),
                        light_tri=self.light_tri, num_mesh_vertices=np.int64(self.num_mesh_vertices),
                        num_mesh_tris=np.int64(self.num_mesh_tris),
                        summary=np.frombuffer(json.dumps(keep, sort_keys=True).encode(), np.uint8))

    @staticmethod
    def load(path) -> "RoomLights":
        import json

        from pipeline.io import load_npz

        z = load_npz(path)
        return RoomLights(vertices=z["vertices"], faces=z["faces"], radiance=z["radiance"],
                          light_tri=z["light_tri"].astype(bool), num_mesh_vertices=int(z["num_mesh_vertices"]),
                          num_mesh_tris=int(z["num_mesh_tris"]),
                          summary=json.loads(bytes(z["summary"]).decode()),
                          albedo=z["albedo"])   # a file without (an earlier version's): KeyError, fitted again


# ---------------------------------------------------------------------------------------------------
# Geometry: the closing box
# ---------------------------------------------------------------------------------------------------

def closing_box(points: np.ndarray, up: np.ndarray, cell: float, margin: float = MARGIN
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An inward-facing box around ``points`` (aligned with ``up``), cut into cells of about ``cell`` m.

    Returns
    -------
    vertices : (4C, 3) float64, four of its own per cell (so a cell's radiance is constant)
    faces : (2C, 3) int64, two triangles per cell, wound so their normal points into the box
    centres : (C, 3) float64 cell centres
    normals : (C, 3) float64 inward unit normals
    """
    e1, e2, u = up_frame(up)
    B = np.stack([e1, e2, u])                     # rows: box axes in world
    c = np.asarray(points, np.float64) @ B.T
    lo, hi = c.min(axis=0) - margin, c.max(axis=0) + margin
    verts, faces, cen, nrm = [], [], [], []
    for axis in range(3):
        a1, a2 = [k for k in range(3) if k != axis]
        for side, val in ((+1, lo[axis]), (-1, hi[axis])):   # inward normal: + at lo, - at hi
            n1 = max(1, int(np.ceil((hi[a1] - lo[a1]) / cell)))
            n2 = max(1, int(np.ceil((hi[a2] - lo[a2]) / cell)))
            g1 = np.linspace(lo[a1], hi[a1], n1 + 1)
            g2 = np.linspace(lo[a2], hi[a2], n2 + 1)
            for i in range(n1):
                for j in range(n2):
                    q = np.zeros((4, 3))
                    q[:, axis] = val
                    q[:, a1] = [g1[i], g1[i + 1], g1[i + 1], g1[i]]
                    q[:, a2] = [g2[j], g2[j], g2[j + 1], g2[j + 1]]
                    base = 4 * len(cen)
                    nn = np.zeros(3)
                    nn[axis] = side
                    f = np.array([[base, base + 1, base + 2], [base, base + 2, base + 3]])
                    tn = np.cross(q[1] - q[0], q[2] - q[0])
                    if tn @ nn < 0:
                        f = f[:, ::-1]
                    verts.append(q)
                    faces.append(f)
                    cen.append(q.mean(axis=0))
                    nrm.append(nn)
    V = np.concatenate(verts) @ B                  # back to world
    return V, np.concatenate(faces), np.asarray(cen) @ B, np.asarray(nrm) @ B


def box_extent(vertices: np.ndarray, cameras, known_quads, up: np.ndarray) -> np.ndarray:
    """The points the closing box must enclose: the mesh, the cameras, the known lights' corners, and a
    point :data:`BEHIND_CAMERA_M` behind each camera (against its optical axis, projected level).

    Whoever held a camera stood in front of the wall behind it, which no photo saw. A box closing the room
    at the cameras themselves stands nearer the lamps than any real wall there: on the light suite its side
    shone 1.15-1.47x Mitsuba's wall with the true lights handed in, and lit the objects with light the room
    does not have. A scanned wall farther away still sets the box (it encloses the mesh).

    ``up`` is a unit vector; a camera looking straight up or down adds no point behind it.
    """
    pts = [np.asarray(vertices, np.float64).reshape(-1, 3)]
    for cam in cameras:
        axis = cam.T_c2w[:3, 2]
        level = axis - (axis @ up) * up
        n = float(np.linalg.norm(level))
        pts.append(cam.center[None])
        if n > 1e-6:
            pts.append((cam.center - BEHIND_CAMERA_M * level / n)[None])
    return np.concatenate(pts + [np.asarray(q, np.float64).reshape(-1, 3) for q in known_quads])


# ---------------------------------------------------------------------------------------------------
# The fit
# ---------------------------------------------------------------------------------------------------

def _at(values: np.ndarray, faces: np.ndarray, prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Per-vertex ``values`` interpolated at barycentric points ``(u, v)`` of triangles ``prim``."""
    f = faces[prim]
    u, v = u[:, None], v[:, None]
    return (1 - u - v) * values[f[:, 0]] + u * values[f[:, 1]] + v * values[f[:, 2]]


def _gather(isect, points: np.ndarray, normals: np.ndarray, rays: int, rng: np.random.Generator, eps: float,
            pool=None):
    """``rays`` cosine-weighted hemisphere rays from each point: (owner (R,) point index, hits, directions);
    cast in parts on ``pool``'s threads if given (the same hits)."""
    from pipeline.trace.intersect import Hits, offset_origins
    from pipeline.trace.sampling import cosine_hemisphere, to_world

    owner = np.repeat(np.arange(len(points)), rays)
    u = rng.random((2, owner.size))
    dl, _ = cosine_hemisphere(u[0], u[1])
    n = normals[owner]
    d = to_world(dl, n).astype(np.float32)
    o = offset_origins(points[owner].astype(np.float32), n.astype(np.float32), d, eps)
    if pool is None:
        return owner, isect.intersect(o, d), d
    cuts = np.linspace(0, len(o), 5).astype(int)   # four parts: two threads each cast two
    parts = _in_order([functools.partial(isect.intersect, o[a:b], d[a:b]) for a, b in zip(cuts[:-1], cuts[1:])], pool)
    return owner, Hits(*(np.concatenate([getattr(h, f) for h in parts]) for f in ("t", "prim", "u", "v"))), d


def _unseen_side(prim: np.ndarray, d: np.ndarray, tn: np.ndarray, nt: int, seen_side: int) -> np.ndarray:
    """(R,) bool: the rays of directions ``d`` met mesh triangle ``prim`` (one of the first ``nt``; normals
    ``tn``) on the side no camera saw (``seen_side``: +1 the cameras see the front, -1 the back, 0 both)."""
    out = np.zeros(prim.shape, bool)
    if seen_side == 0:
        return out
    m = np.flatnonzero(prim < nt)
    out[m] = seen_side * np.sum(d[m] * tn[prim[m]], axis=1) > 0
    return out


def _sheet_backs(P: np.ndarray, N: np.ndarray, patch: np.ndarray, npatch: int, owner: np.ndarray,
                 hit_pos: np.ndarray, seen_normal: np.ndarray, reach: float, weight: float, near: int = 8):
    """(len(P), npatch + 1) sparse: the irradiance each point ``P`` (normals ``N``) receives from the unseen
    sides of sheets, per unit albedo of each patch (the last column: per unit of the room's level) and unit
    radiance of what those sides face. ``owner (R,)`` / ``hit_pos (R, 3)`` / ``seen_normal (R, 3)``: the
    gather rays that met an unseen side (the point they left, where they met it, the normal of the side the
    cameras saw there), each worth ``weight`` (pi / rays per point). A hit takes the patch of the nearest of
    its ``near`` nearest points within ``reach`` metres that faces the way the seen side does (the sheet's
    photographed top, not the wall beside it: a scan's table top is one sheet), the level where none does.

    Why: the underside of a table top is lit by the floor below and reflects it with the table's albedo. The
    top's colour there doubled the floor's irradiance under the suite's table; nothing there (as before) left
    it short, and the fit, explaining the floor's shadow with a higher albedo, lit the suite's rooms whose
    lamps no photo sees with too little light (spot and dim: 0.80-1.00 of the true power over five run
    seeds; 0.87-1.03 with the sheets' backs)."""
    import scipy.sparse

    n = len(P)
    if owner.size == 0 or n == 0:
        return scipy.sparse.csr_matrix((n, npatch + 1))
    idx = _nearest_facing(P, N, hit_pos, seen_normal, reach, near)
    col = np.where(idx >= 0, patch[idx], npatch)
    return scipy.sparse.csr_matrix((np.full(owner.size, float(weight)), (owner, col)), shape=(n, npatch + 1))


def _nnls(Q: np.ndarray, g: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """``argmin_x>=0 0.5 x'Qx - g'x + lam'x`` (``Q`` symmetric positive semi-definite), solved exactly.

    With ``Q = R'R`` (Cholesky of the unit-diagonal rescaling plus a ridge of 1e-10, more where rounding
    leaves it indefinite) it is the non-negative least squares ``min ||R x - R'^-1 (g - lam)||``, solved by
    Lawson and Hanson's active set (``scipy.optimize.nnls``) on a unit right-hand side (scipy 1.12-1.14 stop
    on an absolute tolerance). The projected-gradient iteration (FISTA, 400 steps) used before stopped short
    of the minimum in 3 solves of 4 on 7-Scenes (objective 0.04 % higher at the median, 11 % at the 90th
    percentile): the level searches compared objectives that were not minima. Where there is no answer
    (non-finite input, no factor, no convergence) it says so and leaves the emission at zero.
    """
    from scipy.linalg import solve_triangular
    from scipy.optimize import nnls

    x = np.zeros(g.shape[0])
    dq = np.diag(Q)
    use = np.flatnonzero(dq > 1e-300)      # a column that sends no light stays at zero (lam >= 0)
    if use.size == 0:
        return x

    def none(why: str) -> np.ndarray:
        log.warning("light fit: no emission solve for %d unknowns (%s); left at zero", use.size, why)
        return x

    if not (np.all(np.isfinite(Q)) and np.all(np.isfinite(g)) and np.all(np.isfinite(lam))):
        return none("non-finite input")
    d = np.sqrt(dq[use])
    Qs = Q[np.ix_(use, use)] / d[:, None] / d[None, :]
    for ridge in (1e-10, 1e-8, 1e-6, 1e-4):
        try:
            R = np.linalg.cholesky(Qs + ridge * np.eye(use.size)).T
            break
        except np.linalg.LinAlgError:
            continue
    else:
        return none("no Cholesky factor")
    b = solve_triangular(R.T, (g[use] - lam[use]) / d, lower=True)
    bn = float(np.linalg.norm(b))
    if bn == 0:
        return x
    try:
        z, _ = nnls(R, b / bn, maxiter=50 * use.size)
    except RuntimeError:
        return none("the active set did not settle")
    x[use] = z * bn / d
    return x


def _prior_scale(A: np.ndarray, w: np.ndarray) -> float:
    """The sparsity prior's scale for columns ``A (n, K)`` at points of weights ``w``: the data term's mean
    column norm squared at ``PRIOR_ALBEDO`` (1 without columns)."""
    return float(np.mean(np.sum((A * (w * PRIOR_ALBEDO / np.pi)[:, None]) ** 2, axis=0))) if A.shape[1] else 1.0


def _solve_emission(rho_pt: np.ndarray, Ek: np.ndarray, A_ch, L: np.ndarray, w: np.ndarray,
                    lb: np.ndarray, lam_k: np.ndarray, sparsity: float, scale: float | list | None = None,
                    shared_colour: bool = False, pool=None) -> tuple[np.ndarray, float]:
    """Emission (K, 3) >= lb minimising the weighted residual of ``L = rho/pi (Ek + A e)`` plus an L1 prior
    on emitted power (``sparsity x scale x lam_k``; ``scale`` one for all channels, one per channel, or by
    default each channel's :func:`_prior_scale`, not computed where ``sparsity`` is 0); returns it and the
    prior's value per channel (3,). ``shared_colour``: the emission above the lower bound is one colour for
    every unknown (:func:`_shared_colour`), else each channel is solved on its own. The channels' products
    and solves run on ``pool``'s threads if given (the caller's own thread must not be one of them)."""
    K = A_ch[0].shape[1]
    e = np.zeros((K, 3))
    cost = np.zeros(3)

    def gram(ch: int) -> tuple:
        s = w * rho_pt[:, ch] / np.pi                   # row scale
        B = A_ch[ch] * s[:, None]
        return s, B, B.T @ B

    # channels with the same columns and albedo (stage 1's searches start each level grey) share one product,
    # the solve's largest: the same bytes, once
    lead = [next(c for c in range(ch + 1) if A_ch[c] is A_ch[ch] and np.array_equal(rho_pt[:, c], rho_pt[:, ch]))
            for ch in range(3)]
    shared = {c: gram(c) for c in set(lead) if lead.count(c) > 1}

    def channel(ch: int) -> tuple:
        A = A_ch[ch]
        s, B, Q = shared[lead[ch]] if lead[ch] in shared else gram(ch)
        y = w * L[:, ch] - s * (Ek[:, ch] + A @ lb[:, ch])
        g = B.T @ y
        # the prior's weight is the data term's scale at a fixed albedo, not at the level being tried:
        # scaled with the level (as rho^2) it priced the light a low level needs less than a high level's,
        # and the least-light level search drifted to the darkest albedo
        sc = (1.0 if sparsity == 0 else scale[ch] if isinstance(scale, (list, tuple)) else
              scale if scale is not None else _prior_scale(A, w))
        lam = sparsity * sc * lam_k
        return (B, y, Q, g, lam), _nnls(Q, g, lam)

    parts = []
    for ch, (part, x) in enumerate(_in_order([functools.partial(channel, ch) for ch in range(3)], pool)):
        e[:, ch] = lb[:, ch] + x
        cost[ch] = float(part[4] @ x)      # the prior's part of the objective (the data part: the caller's)
        parts.append(part)
    if shared_colour and K:
        # one colour per kind: the unknowns the photos saw clipped (a lower bound) and those no photo saw
        x, col = _shared_colour(parts, e - lb, (lb.max(axis=1) > 0).astype(np.int64))
        e = lb + x[:, None] * col
        cost = np.array([float(parts[c][4] @ (x * col[:, c])) for c in range(3)])
    return e, cost


def _shared_colour(parts: list, x0: np.ndarray, kind: np.ndarray, iters: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Emission ``x (K,) >= 0`` times one colour ``col_g (3,) >= 0`` (mean 1) per kind ``g`` of unknown
    (``kind (K,)`` in 0..G-1), minimising the three channels' objectives together: ``parts`` holds each channel's
    (B, y, Q = B'B, g = B'y, prior weights), ``x0 (K, 3)`` each channel's own solution (its totals per kind start
    the colours). Alternates the emission (one non-negative least squares over the channels' stacked rows at the
    colours) and the colours (per channel, the best non-negative scales of each kind's ``B x``). Returns ``x``
    and each unknown's colour, (K, 3).

    The channels solved on their own are each free to put their light anywhere: in the light suite's
    coloured room they lit the red wall with a pure-red lamp on the green wall opposite and the green
    wall with a pure-green one on the red wall, and the objects between came out 1.3x too green. A room's
    lamps, windows and panels are one colour far more often than they are the colours of its walls."""
    K = x0.shape[0]
    G = int(kind.max()) + 1 if K else 1
    members = [kind == g for g in range(G)]
    col = np.ones((G, 3))
    for g, m in enumerate(members):
        tot = x0[m].sum(axis=0)
        if tot.mean() > 0:
            col[g] = tot / tot.mean()
    x = np.zeros(K)
    for _ in range(iters):
        d = [col[kind, c] for c in range(3)]            # each unknown's scale in channel c
        x = _nnls(sum(d[c][:, None] * parts[c][2] * d[c][None, :] for c in range(3)),
                  sum(d[c] * parts[c][3] for c in range(3)), sum(d[c] * parts[c][4] for c in range(3)))
        X = np.zeros((K, G))                              # x on each kind's rows
        X[np.arange(K), kind] = x
        for c, (B, y, _, _, lam) in enumerate(parts):
            U = B @ X                                     # each kind's light at unit colour
            col[:, c] = _nnls(U.T @ U, U.T @ y, lam @ X)
        for g, m in enumerate(members):
            mean = float(col[g].mean())
            if mean <= 0:                                 # a kind that explains nothing in any channel: dark
                x[m], col[g] = 0.0, 1.0
            else:
                col[g] /= mean
                x[m] *= mean
        if not x.any():
            break
    return x, col[kind]


def _curve_minimum(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per column of ``y (len(x), C)``, where a parabola through the lowest sample and its two neighbours
    has its minimum (the lowest sample itself at either end of ``x``)."""
    out = np.empty(y.shape[1])
    for c in range(y.shape[1]):
        i = int(np.argmin(y[:, c]))
        out[c] = x[i]
        if 0 < i < len(x) - 1:
            (x0, x1, x2), (y0, y1, y2) = x[i - 1:i + 2], y[i - 1:i + 2, c]
            den = (x0 - x1) * (x0 - x2) * (x1 - x2)
            a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
            b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / den
            if a > 0:
                out[c] = float(np.clip(-b / (2 * a), x0, x2))
    return out


def _clipped_edge_excess(photo: np.ndarray, threshold: int) -> np.ndarray:
    """(m, 3) linear radiance over the surface around them of the unclipped pixels of ``photo (H, W, 3) uint8``
    next to clipped ones (a channel ``>= threshold``; centres within EDGE_RING_PX), where that excess is at least
    EDGE_MIN_EXCESS in luminance and positive in every channel (its colour has a ratio). The surface is the mean of the pixels EDGE_BACK_PX from every clipped one in an
    EDGE_WINDOW_PX window. Empty where no pixel (or every pixel) is clipped.

    Why: a pixel that a clipped light's edge covers in part holds the light's radiance times that part plus
    the surface's for the rest; with the light many times brighter than the surface, the excess has the light's
    colour, which its clipped pixels no longer show (the light suite's lamp in view: green / red 0.874, blue / red
    0.657 at its edges, the truth's 0.860 / 0.700; its window 1.19 / 1.41, the truth's 1.18 / 1.39)."""
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


def _edge_colour(excess: np.ndarray) -> np.ndarray | None:
    """(3,) colour (red 1) of the clipped lights from the edge pixels :func:`_clipped_edge_excess` gives
    (``excess (m, 3)``, positive): their median green / red and blue / red; None with fewer than EDGE_MIN_PIXELS."""
    ex = np.asarray(excess, np.float64).reshape(-1, 3)
    if len(ex) < EDGE_MIN_PIXELS:
        return None
    return np.array([1.0, float(np.median(ex[:, 1] / ex[:, 0])), float(np.median(ex[:, 2] / ex[:, 0]))])


def _edge_coloured(e: np.ndarray, lb: np.ndarray, colour: np.ndarray) -> tuple[np.ndarray, float]:
    """Emission ``e (k, 3)`` of lights seen clipped, in ``colour (3,)`` (positive) at its luminance, or brighter
    where that leaves a channel under its lower bound ``lb (k, 3)`` (clipped: at least sensor white there), and
    the most the luminance of a light the fit lit above that bound was raised for it (1: none; a light held at
    its bound had no luminance of its own to keep)."""
    e, lb = np.asarray(e, np.float64), np.asarray(lb, np.float64)
    c = np.asarray(colour, np.float64)
    keep = (e @ LUMINANCE_F64) / float(c @ LUMINANCE_F64)
    scale = np.maximum(keep, np.max(lb / c[None], axis=1))
    lit = (e @ LUMINANCE_F64) > 1.001 * (lb @ LUMINANCE_F64)
    return scale[:, None] * c[None], float(np.max(scale[lit] / keep[lit])) if lit.any() else 1.0


def _say_edge_raise(name: str, colour: np.ndarray, raised: float) -> None:
    """One warning where the edges' ``colour`` raised a clipped light's brightness over EDGE_RAISE_WARN times
    (``raised``): a clipped light's lower bound is sensor white in every channel (the fit's throughout), so one
    clipped in one channel only, and deeply coloured, would come out that much too bright. Said, with the fix."""
    if raised > EDGE_RAISE_WARN:
        log.warning("light fit of %s: the clipped lights take the colour at their edges (green / red %.2f, blue / red "
                    "%.2f), %.1fx brighter than the fit found so that every channel stays at least sensor white, as "
                    "in a light clipped in every channel; one clipped in fewer channels comes out too bright: "
                    "trace.fit_edge_colour = false keeps the fit's colour", name, colour[1], colour[2], raised)


def _white_levels(res: np.ndarray, power: np.ndarray, prior: float, fine: int = 400) -> np.ndarray:
    """(3,) albedo level per channel minimising ``sum_c res_c(l_c) / min res_c + prior x sum_c (log P_c(l_c) -
    mean_c log P_c(l_c))^2``: each channel's objective ``res (len(ALBEDO_LEVELS), 3)`` relative to its lowest,
    plus a pull of the light's colour (the emitted power ``power`` per channel at each level) toward the
    photos' white. Both are interpolated in log level through the levels evaluated (finite ``res``, positive
    ``power``) by cubic splines (a monotone one would put each minimum on a level evaluated, losing what the
    parabola of :func:`_curve_minimum` finds between them); the channels couple only through the mean, which
    is searched on a grid. Each channel's own minimum (:func:`_curve_minimum`) where ``prior`` is 0 or a
    channel has fewer than three such levels.

    Why: each channel's objective is nearly flat about its minimum (on the light suite the true light sits
    within 0.1-2.6 % of it), while the light's power goes about as the inverse square of the level, so
    each channel's own minimum left the light's colour to a few per cent of residual: in the coloured room
    the red walls' light came out red (power 1.21 / 0.58 / 0.58 of the truth's). A room's light is far more
    often near the white the camera was balanced for than the colour of its walls, and where a channel's
    objective is steep (a warm lamp under white walls) the data still decides."""
    from scipy.interpolate import CubicSpline

    lv = np.asarray(ALBEDO_LEVELS, np.float64)
    res = np.asarray(res, np.float64)
    power = np.asarray(power, np.float64)
    ok = np.isfinite(res) & np.isfinite(power) & (power > 0)
    if prior <= 0 or (ok.sum(axis=0) < 3).any():
        return _curve_minimum(lv, res)
    lo = max(float(np.log(lv[ok[:, c]]).min()) for c in range(3))
    hi = min(float(np.log(lv[ok[:, c]]).max()) for c in range(3))
    if hi <= lo:
        return _curve_minimum(lv, res)
    xf = np.linspace(lo, hi, fine)
    g = np.empty((fine, 3))
    y = np.empty((fine, 3))
    for c in range(3):
        x = np.log(lv[ok[:, c]])
        g[:, c] = CubicSpline(x, res[ok[:, c], c] / res[ok[:, c], c].min())(xf)
        y[:, c] = CubicSpline(x, np.log(power[ok[:, c], c]))(xf)
    ms = np.linspace(y.min(), y.max(), fine)
    f = g[None] + prior * (y[None] - ms[:, None, None]) ** 2        # (means, fine, 3)
    i = f.argmin(axis=1)                                           # (means, 3)
    tot = np.take_along_axis(f, i[:, None, :], axis=1)[:, 0].sum(axis=1)
    return np.exp(xf[i[int(np.argmin(tot))]])


def _brightest_colour(rho: np.ndarray, patch: np.ndarray) -> np.ndarray | None:
    """(3,) mean albedo of the room's brightest surfaces: of the patches (albedo ``rho (npatch, 3)``, the points'
    patch ``patch (n,)``) holding at least BRIGHT_MIN_SHARE of the points each, the brightest (luminance) until
    they hold BRIGHT_SHARE of the points, weighted by their points. None without such a patch."""
    n = patch.size
    count = np.bincount(patch, minlength=len(rho))
    big = np.flatnonzero(count >= max(BRIGHT_MIN_SHARE * n, 1))
    if big.size == 0:
        return None
    big = big[np.argsort(-(rho[big] @ LUMINANCE_F64), kind="stable")]
    top = big[:int(np.searchsorted(np.cumsum(count[big]), BRIGHT_SHARE * n)) + 1]
    return (count[top, None] * rho[top]).sum(axis=0) / count[top].sum()


def _grey_levels(res: np.ndarray, bright: np.ndarray, level: np.ndarray, prior: float) -> np.ndarray:
    """(3,) albedo level per channel minimising ``sum_c res_c(l_c) / min res_c + prior x sum_c (log T_c(l_c) -
    mean_c log T_c(l_c))^2``, ``T_c(l) = bright_c x l / level_c``: the room's brightest surfaces, of albedo
    ``bright (3,)`` at the levels ``level (3,)``, pulled toward grey (their pattern relative to each channel's level
    does not change with it). :func:`_white_levels` with the brightest surfaces' albedo in the place of the
    light's power: the photo is fixed, so a channel's light goes as the inverse of its albedo.

    Why: a room's brightest surfaces (a ceiling, white walls, cabinets, doors) are far more often near grey
    than its light is near the camera's white. Under a warm lamp with the light's prior the suite's ceiling room
    came out lit white, its albedo warm (blue 1.31 / 1.03 / 1.08x the truth's power at run seeds 0-2), and its
    coloured room lit red (green 0.83 / 0.76 / 0.70x); both come nearer grey walls and white cabinets this way."""
    # both positive: levels come off ALBEDO_LEVELS, albedos are clipped to ALBEDO_RANGE
    scale = np.asarray(bright, np.float64) / np.asarray(level, np.float64)
    return _white_levels(res, 1.0 / (np.asarray(ALBEDO_LEVELS, np.float64)[:, None] * scale), prior)


def _within(y: np.ndarray, tolerance: float) -> np.ndarray:
    """(levels, C) bool: the levels whose objective ``y (levels, C)`` is within ``tolerance`` of each column's
    lowest (stage 1 takes the highest of them)."""
    return y <= y.min(axis=0) * (1 + tolerance)


def _level_search(evaluate, pool, tolerance: float | None = None) -> np.ndarray:
    """(len(ALBEDO_LEVELS), 3) objective ``evaluate(level)`` (3,) of each channel on the level grid, inf where
    it was not needed: every other level first, then the levels next to what the search picks from them, until
    each channel's pick (its lowest level and, with ``tolerance``, its highest level within that share of the
    lowest objective) has both neighbours evaluated. Where each channel's objective falls and then rises over
    the grid, the picks are those of the whole grid (a parabola through the lowest level and its neighbours
    too), from 11-13 of the 19 levels. The levels of a round run on ``pool``'s threads."""
    m = len(ALBEDO_LEVELS)
    y = np.full((m, 3), np.inf)
    done = np.zeros(m, bool)
    todo = list(range(0, m, 2)) + ([m - 1] if (m - 1) % 2 else [])
    while todo:
        for i, v in zip(todo, _in_order([functools.partial(evaluate, ALBEDO_LEVELS[i]) for i in todo], pool)):
            y[i], done[i] = v, True
        need = set()
        ok = _within(y, tolerance) if tolerance is not None else None
        for c in range(3):
            picks = [int(np.argmin(y[:, c]))] + ([int(np.flatnonzero(ok[:, c]).max())] if ok is not None else [])
            need.update(j for i in picks for j in (i - 1, i + 1) if 0 <= j < m and not done[j])
        todo = sorted(need)
    return y


def _level_search_with_power(evaluate, pool) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_level_search` of ``evaluate(level) -> (objective (3,), emitted power (3,))``: the objective and
    the power per channel at each level, (len(ALBEDO_LEVELS), 3) each (inf / NaN where not evaluated), for
    :func:`_white_levels`."""
    power = np.full((len(ALBEDO_LEVELS), 3), np.nan)

    def objective(lv: float) -> np.ndarray:
        obj, power[ALBEDO_LEVELS.index(lv)] = evaluate(lv)
        return obj

    return _level_search(objective, pool), power


def _finite(values, digits: int = 4) -> list:
    """A list of ``values`` rounded to ``digits``, None where not finite (a level the search did not need)."""
    return [round(float(v), digits) if np.isfinite(v) else None for v in np.asarray(values, np.float64).ravel()]


def _sliver_rule(norms: np.ndarray, expected: np.ndarray, med: float) -> tuple[np.ndarray, np.ndarray]:
    """The sparsity prior's guard against unknowns the points see only through slivers (a gap between the
    mesh and the box, a grazing angle, a box square behind a wall): their columns ``norms`` are tiny, so
    they would explain anything with implausible radiance at no cost. Each is priced (weight relative to
    the median cell's column ``med``) at least as if it were seen as well as ``expected`` (the median cell,
    or for a lamp the median cell per unit area times its own area), and those under 2 % of that are not
    fitted at all. Returns (fitted?, price)."""
    expected = np.asarray(expected, np.float64)
    return norms >= 0.02 * expected, np.maximum(norms, expected) / max(med, 1e-12)


def _wall_ratio(L: np.ndarray, E: np.ndarray, w: np.ndarray, cos_up: np.ndarray, height: np.ndarray,
                level: np.ndarray) -> np.ndarray:
    """(3,) albedo of the room's upper walls over its albedo level ``level (3,)``. The upper walls are the
    fit points whose normal is within WALL_COS of horizontal (``cos_up``: its cosine to up) at least
    LOW_FILL_M above the scan's lowest point (``height``); their albedo is the one that explains their
    photographed radiance ``L (n, 3)`` under the fitted irradiance ``E (n, 3)`` best (weights ``w``), as
    one patch, not shrunk toward the level. The unseen walls above the scan (and the ceiling, where
    ``ceiling_albedo`` is 0) reflect with it: the level also counts the floor and the furniture, darker and
    warmer than walls. 1 with fewer than MIN_FIT_POINTS such points."""
    wall = (np.abs(cos_up) < WALL_COS) & (height >= LOW_FILL_M)
    if int(wall.sum()) < MIN_FIT_POINTS:
        return np.ones(3)
    ww = (w[wall] ** 2)[:, None]
    num = np.sum(ww * L[wall] * E[wall], axis=0)
    den = np.sum(ww * E[wall] ** 2, axis=0)
    walls = np.where(den > 0, np.pi * num / np.maximum(den, 1e-30), np.asarray(level, np.float64))
    return walls / np.maximum(np.asarray(level, np.float64), 1e-6)


def _patch_keys(P: np.ndarray, N: np.ndarray, cell: float) -> np.ndarray:
    """(n, 4) int64 albedo patch of points ``P`` with normals ``N``: their cell of ``cell`` metres and their
    normal's dominant axis and sign."""
    ax = np.argmax(np.abs(N), axis=1)
    side = N[np.arange(len(N)), ax] > 0
    return np.concatenate([np.floor(P / cell).astype(np.int64), (ax * 2 + side)[:, None]], axis=1)


def _chromaticity_groups(cell: np.ndarray, keyp: np.ndarray, L: np.ndarray, bin_size: float) -> tuple[np.ndarray, int]:
    """Albedo patches that join the albedo cells ``cell (n,)`` (of keys ``keyp``, :func:`_patch_keys`) whose
    photo chromaticity (r and g of the cell's summed ``L``) falls in one bin of ``bin_size`` and whose
    normal has one axis and sign: (patch per point (n,), patches).

    A room is a few materials (one wood, one paint, one floor), each lit unevenly. With an albedo of its
    own, a cell explains its light with its albedo: the suite's dark table top came out 1.2-2.3x too
    bright and the bright walls 0.8-0.95x too dark, and the fitted light reached the table, where the
    objects stand, 0.76-0.82x too weakly. One albedo per material, seen across cells under different
    light, makes the light explain the difference instead."""
    nc = int(cell.max()) + 1
    tot = np.stack([np.bincount(cell, L[:, c], minlength=nc) for c in range(3)], axis=1)
    chroma = tot[:, :2] / np.maximum(tot.sum(axis=1, keepdims=True), 1e-12)
    axis = np.zeros(nc, np.int64)
    axis[cell] = keyp[:, 3]
    key = np.concatenate([np.floor(chroma / bin_size).astype(np.int64), axis[:, None]], axis=1)
    _, group = np.unique(key, axis=0, return_inverse=True)
    group = group.ravel()
    return group[cell], int(group.max()) + 1


def _relative_weights(P: np.ndarray, N: np.ndarray, lum: np.ndarray, k: int = WEIGHT_NEIGHBOURS) -> np.ndarray:
    """(n,) weights that make the fit's least squares relative: one over the median photo luminance of each
    point's ``k`` nearest points (in position and normal, a unit normal counting as ``NORMAL_METRES``:
    the neighbours are on the same surface, not across a crease), plus a floor of 5 % of the median
    luminance.

    One over each point's own luminance is biased: texture makes the photo vary at one light, and the
    bright texels get less say, so the fitted albedo x light comes out low (the suite's rooms, with the
    true albedo handed in: 0.69-0.86x the photos, emitted power 0.73x the truth). The neighbours' median
    is the light's level there without the texture (the floor's prediction then 0.95-0.98x the photo)."""
    from scipy.spatial import cKDTree

    floor = 0.05 * float(np.median(lum)) + 1e-9
    if len(lum) <= k:
        return 1.0 / (lum + floor)
    X = np.concatenate([P, NORMAL_METRES * N], axis=1)
    _, nb = cKDTree(X).query(X, k=k)
    return 1.0 / (np.median(lum[nb.reshape(len(X), -1)], axis=1) + floor)


def _behind_the_mesh(isect, cells: np.ndarray, cams: list, eps: float, grid: int = 3) -> np.ndarray:
    """(C,) bool: the closing box's cells ``cells (C, 4, 3)`` (corners in order) the room's mesh hides from
    every camera centre ``cams``: from each of ``grid`` x ``grid`` points spread over the cell, the segment
    to every camera meets the mesh (``isect`` holds it with the box, which the segments do not cross). A
    cell seen in part, through a hole or past a wall's end, is not hidden. False for all without cameras."""
    cells = np.asarray(cells, np.float64).reshape(-1, 4, 3)
    t = (np.arange(grid) + 0.5) / grid
    a, b = (x.ravel() for x in np.meshgrid(t, t))
    o, u, v = cells[:, 0], cells[:, 1] - cells[:, 0], cells[:, 3] - cells[:, 0]
    pts = (o[:, None] + a[None, :, None] * u[:, None] + b[None, :, None] * v[:, None]).reshape(-1, 3)
    hidden = np.full(len(pts), bool(cams))
    for c in cams:
        if not hidden.any():
            break
        idx = np.flatnonzero(hidden)
        d = np.asarray(c, np.float64)[None] - pts[idx]
        dist = np.linalg.norm(d, axis=1)
        d /= np.maximum(dist, 1e-12)[:, None]
        hidden[idx] = isect.occluded(pts[idx] + eps * d, d, np.maximum(dist - 2 * eps, 0))
    return hidden.reshape(len(cells), grid * grid).all(axis=1)


def _nearest_facing(P: np.ndarray, N: np.ndarray, Q: np.ndarray, QN: np.ndarray, reach: float, k: int = 8,
                    either_way: bool = False) -> np.ndarray:
    """(len(Q),) index of the nearest of each query ``Q``'s ``k`` nearest points ``P`` within ``reach``
    metres whose normal ``N`` is within 60 degrees of the query's ``QN`` (``either_way``: of it or its
    opposite), -1 where none is."""
    from scipy.spatial import cKDTree

    out = np.full(len(Q), -1, np.int64)
    if len(Q) == 0 or len(P) == 0:
        return out
    k = min(k, len(P))
    dist, nb = cKDTree(P).query(Q, k=k, distance_upper_bound=reach)
    dist, nb = dist.reshape(len(Q), k), np.minimum(nb.reshape(len(Q), k), len(P) - 1)
    cos = np.einsum("qkj,qj->qk", N[nb], QN)
    ok = np.isfinite(dist) & ((np.abs(cos) if either_way else cos) > 0.5)
    first = np.argmax(ok, axis=1)                                  # the nearest that qualifies
    has = ok[np.arange(len(Q)), first]
    out[has] = nb[has, first[has]]
    return out


def _vertex_albedo(V: np.ndarray, F: np.ndarray, P: np.ndarray, N: np.ndarray, rho_p: np.ndarray,
                   level: np.ndarray, reach: float, k: int = 8) -> np.ndarray:
    """(V, 3) albedo of the mesh's vertices: that of the nearest fit point ``P`` (normals ``N``, albedo
    ``rho_p (n, 3)``) within ``reach`` metres on a surface facing the same way (the vertex's area-weighted
    normal within 60 degrees, either way round: a mesh's winding need not face the cameras); ``level (3,)``
    where there is none (no photo saw it). Nearest, not by patch key: a vertex on a patch's boundary plane
    (a wall's own plane) falls in the next cell, which its surface's points do not."""
    from pipeline.trace.scene import vertex_normals

    out = np.tile(np.asarray(level, np.float64), (len(V), 1))
    if len(V) == 0 or len(F) == 0 or len(P) == 0:
        return out
    near = _nearest_facing(P, N, V, vertex_normals(V, F).astype(np.float64), reach, k, either_way=True)
    out[near >= 0] = rho_p[near[near >= 0]]
    return out


def _unit_normal(quad: np.ndarray) -> np.ndarray:
    """(3,) unit normal of rectangle ``quad (4, 3)``: the side its corners turn counter-clockwise around."""
    q = np.asarray(quad, np.float64)
    n = np.cross(q[1] - q[0], q[2] - q[0])
    return n / max(float(np.linalg.norm(n)), 1e-30)


def _near_quads(points: np.ndarray, quads: np.ndarray, reach: float) -> np.ndarray:
    """(n,) bool: ``points (n, 3)`` within ``reach`` metres of any parallelogram ``quads (C, 4, 3)`` (corners in
    order)."""
    P = np.asarray(points, np.float64).reshape(-1, 3)
    near = np.zeros(len(P), bool)
    for q in np.asarray(quads, np.float64).reshape(-1, 4, 3):
        a, b = q[1] - q[0], q[3] - q[0]
        d = P - q[0]
        u = np.clip(d @ a / max(float(a @ a), 1e-30), 0.0, 1.0)
        v = np.clip(d @ b / max(float(b @ b), 1e-30), 0.0, 1.0)
        near |= np.linalg.norm(d - u[:, None] * a - v[:, None] * b, axis=1) <= reach
    return near


def _quad_area(quads: np.ndarray) -> np.ndarray:
    """(C,) areas of parallelograms ``quads (C, 4, 3)`` (corners in order)."""
    q = np.asarray(quads, np.float64).reshape(-1, 4, 3)
    return np.linalg.norm(np.cross(q[:, 1] - q[:, 0], q[:, 3] - q[:, 0]), axis=1)


def _sampled_irradiance(isect, Pi: np.ndarray, Ni: np.ndarray, lp: np.ndarray, nl: np.ndarray, area: float,
                        eps: float, two_sided: bool = False) -> np.ndarray:
    """(R,) one-sample estimates of the irradiance at receivers ``Pi`` (normals ``Ni``) per unit radiance
    of a light of total ``area``, from points ``lp`` drawn uniformly on it (normals ``nl``), with visibility
    through ``isect``; a one-sided light emits along ``nl``."""
    from pipeline.trace.intersect import offset_origins

    dv = lp - Pi
    dist = np.linalg.norm(dv, axis=1)
    wl = dv / np.maximum(dist, 1e-12)[:, None]
    cos_i = np.einsum("ij,ij->i", wl, Ni)
    cos_l = -np.einsum("ij,ij->i", wl, nl)
    if two_sided:
        cos_l = np.abs(cos_l)
    g = np.zeros(len(Pi))
    ok = np.flatnonzero((cos_i > 0) & (cos_l > 0) & (dist > 4 * eps))
    if ok.size == 0:
        return g
    o2 = offset_origins(Pi[ok].astype(np.float32), Ni[ok].astype(np.float32), wl[ok].astype(np.float32), eps)
    occ = isect.occluded(o2, wl[ok].astype(np.float32), (dist[ok] - 3 * eps).astype(np.float32))
    vis = ok[~occ]
    g[vis] = cos_i[vis] * cos_l[vis] / dist[vis] ** 2 * area
    return g


def _in_order(jobs: list, pool) -> list:
    """``[job() for job in jobs]``, on ``pool``'s threads when there is one (Embree traces without holding
    the GIL). Callers draw their random numbers before, in order: the result does not depend on the pool."""
    if pool is None:
        return [job() for job in jobs]
    return list(pool.map(lambda job: job(), jobs))


def _fill_columns(out: np.ndarray, samples: int, jobs, pool) -> np.ndarray:
    """``out[:, c]``: the mean over ``samples`` of each ``(c, job)`` that ``jobs`` yields (a generator that
    draws its random numbers as it goes, so in order). On ``pool``'s threads, at most ``COLUMN_CHUNK`` jobs
    ahead of the oldest unfinished one: this thread draws the next jobs' samples while the pool traces
    (drawn between chunks, with the pool idle meanwhile, the kitchen fit's columns took 6.7 s, now 5.7)."""
    def put(c: int, g: np.ndarray) -> None:
        out[:, c] = g.reshape(out.shape[0], samples).mean(axis=1)

    if pool is None:
        for c, job in jobs:
            put(c, job())
        return out
    ahead: collections.deque = collections.deque()
    for c, job in jobs:
        ahead.append((c, pool.submit(job)))
        if len(ahead) > COLUMN_CHUNK:
            c0, fut = ahead.popleft()
            put(c0, fut.result())
    for c0, fut in ahead:
        put(c0, fut.result())
    return out


def _quad_columns(isect, P: np.ndarray, N: np.ndarray, quads: np.ndarray, normals: np.ndarray, samples: int,
                  rng: np.random.Generator, eps: float, pool=None) -> np.ndarray:
    """(n, C) irradiance at points ``P`` (normals ``N``) per unit radiance of each one-sided rectangle
    ``quads (C, 4, 3)`` emitting along ``normals (C, 3)``: ``samples`` area samples per pair, with visibility
    through ``isect``; the shadow rays on ``pool``'s threads if given."""
    n = len(P)
    Pi = np.repeat(P, samples, axis=0)
    Ni = np.repeat(N, samples, axis=0)

    def jobs():
        for c, q in enumerate(quads):
            a, b = q[1] - q[0], q[3] - q[0]
            r = rng.random((2, n * samples))
            lp = q[0] + r[0][:, None] * a + r[1][:, None] * b
            yield c, functools.partial(_sampled_irradiance, isect, Pi, Ni, lp,
                                       np.broadcast_to(normals[c], lp.shape), float(_quad_area(q)[0]), eps)

    return _fill_columns(np.zeros((n, len(quads))), samples, jobs(), pool)


def _area_points(tris: np.ndarray, count: int, corners: np.ndarray, normals: np.ndarray, areas: np.ndarray,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, float] | None:
    """``count`` points drawn uniformly over the area of triangles ``tris`` (indices into ``corners (T, 3, 3)``,
    ``normals (T, 3)``, ``areas (T,)``): the points (count, 3), their triangles' normals (count, 3) and the
    triangles' total area; None where that is 0."""
    ar = areas[tris]
    tot = float(ar.sum())
    if tot <= 0:
        return None
    pick = tris[np.minimum(np.searchsorted(np.cumsum(ar) / tot, rng.random(count)), len(tris) - 1)]
    r1, r2 = rng.random(count), rng.random(count)
    s1 = np.sqrt(r1)
    q = corners[pick]
    lp = (1 - s1)[:, None] * q[:, 0] + (s1 * (1 - r2))[:, None] * q[:, 1] + (s1 * r2)[:, None] * q[:, 2]
    return lp, normals[pick], tot


def _region_columns(isect, P: np.ndarray, N: np.ndarray, regions: list, corners: np.ndarray, normals: np.ndarray,
                    areas: np.ndarray, samples: int, side: int, rng: np.random.Generator, eps: float,
                    pool=None) -> np.ndarray:
    """(n, R) irradiance at points ``P`` (normals ``N``) per unit radiance of each region of ``regions`` (arrays
    of triangle indices, as :func:`_area_points` takes them): ``samples`` area samples per pair, with visibility
    through ``isect``. A region emits from its triangles' normal side (``side`` +1), the other side (-1) or
    both (0)."""
    Pi, Ni = np.repeat(P, samples, axis=0), np.repeat(N, samples, axis=0)

    def jobs():
        for r, tris in enumerate(regions):
            drawn = _area_points(tris, len(Pi), corners, normals, areas, rng)
            if drawn is not None:
                yield r, functools.partial(_sampled_irradiance, isect, Pi, Ni, drawn[0], drawn[1] * (side or 1),
                                           drawn[2], eps, two_sided=side == 0)

    return _fill_columns(np.zeros((len(P), len(regions))), samples, jobs(), pool)


def _lamp_clusters(quads: np.ndarray, nrm: np.ndarray, size: float) -> list[np.ndarray]:
    """The lamps (corners ``quads (C, 4, 3)``, normals ``nrm (C, 3)``) that touch, as index arrays: facing one way,
    centres within 1.5 x ``size`` of one another across the normal (diagonal neighbours too), at any height along
    it (squares hung one above another light the room as one lamp, and a lamp under another would shade it).
    Each cluster's lamps in order, the clusters by their first lamp."""
    cen = np.asarray(quads, np.float64).mean(axis=1)
    root = np.arange(len(cen))

    def find(i: int) -> int:
        while root[i] != i:
            i = root[i]
        return i

    for i in range(len(cen)):
        d = cen[i + 1:] - cen[i]
        d = d - np.outer(d @ nrm[i], nrm[i])
        near = (nrm[i + 1:] @ nrm[i] > 0.999) & (np.linalg.norm(d, axis=1) <= 1.5 * size)
        for j in i + 1 + np.flatnonzero(near):
            root[find(int(j))] = find(i)
    labels = np.array([find(i) for i in range(len(cen))], np.int64)
    return [np.flatnonzero(labels == r) for r in sorted(set(labels.tolist()))]


def _rectangle(centre: np.ndarray, u: np.ndarray, v: np.ndarray, hu: float, hv: float) -> np.ndarray:
    """(4, 3) corners of the rectangle about ``centre`` with unit edges ``u``, ``v`` and half sizes ``hu``, ``hv``,
    in the order of the squares :func:`_lamp_candidates` cuts (corner, + u, + u + v, + v)."""
    o = centre - hu * u - hv * v
    return np.stack([o, o + 2 * hu * u, o + 2 * hu * u + 2 * hv * v, o + 2 * hv * v])


def _cluster_start(quads: np.ndarray, power: np.ndarray, at: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the polish starts a cluster of lamps ``quads (m, 4, 3)`` (parallel, facing one way; emitted power
    ``power (m,)``): the power-weighted centre of their centres seen along the normal, in the plane of lamp
    ``at``; and the unit edges u, v of the first."""
    q = np.asarray(quads, np.float64)
    u = q[0, 1] - q[0, 0]
    v = q[0, 3] - q[0, 0]
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    cen = q.mean(axis=1)
    pw = np.maximum(np.asarray(power, np.float64), 0.0)
    wt = pw / pw.sum() if pw.sum() > 0 else np.full(len(q), 1.0 / len(q))
    d = wt @ (cen - cen[at])
    return cen[at] + (d @ u) * u + (d @ v) * v, u, v


def _coordinate_search(evaluate, x0: np.ndarray, steps: np.ndarray, lo: np.ndarray, hi: np.ndarray, valid,
                       budget: int, halvings: int = POLISH_HALVINGS) -> tuple[np.ndarray, float, int]:
    """Minimise ``evaluate(x)`` from ``x0`` one coordinate at a time: steps one way while they lower it, else
    the other way (within ``lo``, ``hi`` and where ``valid(x)``); when a sweep over the coordinates lowers
    nothing, every step halves, ``halvings`` times. Stops early where a whole sweep changes nothing at all (the
    value does not depend on x) and after ``budget`` evaluations. Returns the best x, its value and the
    evaluations made."""
    x = np.asarray(x0, np.float64).copy()
    best = float(evaluate(x))
    n = 1
    step = np.asarray(steps, np.float64).copy()
    h = 0
    while h <= halvings and n < budget:
        better, moved = False, False
        for k in np.flatnonzero(step > 0):
            for sign in (1.0, -1.0):
                went = False
                while n < budget:
                    y = x.copy()
                    y[k] = np.clip(x[k] + sign * step[k], lo[k], hi[k])
                    if y[k] == x[k] or not valid(y):
                        break
                    f = float(evaluate(y))
                    n += 1
                    moved |= f != best
                    if f >= best:
                        break
                    best, x, better, went = f, y, True, True
                if went:
                    break
        if not moved:
            break
        if not better:
            step /= 2
            h += 1
    return x, best, n


def _hang_ok(isect, cen: np.ndarray, nrm: np.ndarray, depth: np.ndarray, cams: list, eps: float) -> np.ndarray:
    """(C,) bool: a lamp centred at ``cen (C, 3)``, hanging ``depth (C,)`` metres along its normal ``nrm (C, 3)``
    below its ceiling cell, has free space up to that cell and no photo (``cams``) saw where it hangs."""
    ok = np.ones(len(cen), bool)
    if not len(cen):
        return ok
    dn = -np.asarray(nrm, np.float64)
    ok &= ~isect.occluded((cen + eps * dn).astype(np.float32), dn.astype(np.float32),
                          (np.asarray(depth, np.float64) - 2 * eps).astype(np.float32))
    for cam in cams:
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            break
        uv, z = cam.project(cen[idx])
        inside = (z > 1e-6) & np.all((uv >= 0) & (uv < [cam.width, cam.height]), axis=1)
        j = idx[inside]
        if j.size == 0:
            continue
        t = np.asarray(cam.center, np.float64)
        dv = cen[j] - t
        dist = np.linalg.norm(dv, axis=1)
        seen = ~isect.occluded(np.repeat(t[None], j.size, axis=0).astype(np.float32),
                               (dv / dist[:, None]).astype(np.float32), (dist - eps).astype(np.float32))
        ok[j[seen]] = False
    return ok


def _lamp_candidates(isect, cells: np.ndarray, BV: np.ndarray, bnrm: np.ndarray, upv: np.ndarray, size: float,
                     h_min: float, cams: list, eps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Small lamps an emitting box cell may stand for: the cell cut into squares of about ``size`` metres, and
    for a ceiling cell the same squares hung ``REFINE_DEPTHS`` below it, in free space no photo saw
    (``cams``: the photos' :class:`~pipeline.camera.Camera`) and at least ``h_min`` high. Returns corners (C, 4, 3), normals
    (C, 3) and the cell each came from (C,)."""
    quads, nrm, parent, depth = [], [], [], []
    for c in cells:
        q = BV[4 * c: 4 * c + 4]
        a, b = q[1] - q[0], q[3] - q[0]
        na = max(1, int(round(np.linalg.norm(a) / size)))
        nb_ = max(1, int(round(np.linalg.norm(b) / size)))
        ceiling = float(bnrm[c] @ upv) < -0.5
        for d in (REFINE_DEPTHS if ceiling else (0.0,)):
            for i in range(na):
                for j in range(nb_):
                    o = q[0] + (i / na) * a + (j / nb_) * b + d * bnrm[c]
                    quads.append(np.stack([o, o + a / na, o + a / na + b / nb_, o + b / nb_]))
                    nrm.append(bnrm[c])
                    parent.append(c)
                    depth.append(d)
    if not quads:
        return np.zeros((0, 4, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    quads, nrm, parent, depth = np.asarray(quads), np.asarray(nrm), np.asarray(parent), np.asarray(depth)
    cen = quads.mean(axis=1)
    hung = depth > 0
    keep = ~hung | (cen @ upv >= h_min)
    idx = np.flatnonzero(hung & keep)
    keep[idx] = _hang_ok(isect, cen[idx], nrm[idx], depth[idx], cams, eps)
    return quads[keep], nrm[keep], parent[keep]


def read_lights_file(file: str, radiance_scale: float = 1.0) -> list[tuple[np.ndarray, np.ndarray]]:
    """The emitters of ``trace.lights_file``: ``[(corners (4, 3), radiance (3,) x radiance_scale)]``.

    Raises InputError naming the file and the entry for anything that is not a list of
    ``{"corners": 4 x 3 numbers, "radiance": 3 numbers >= 0}`` with a non-degenerate rectangle.
    """
    import json
    from pathlib import Path

    from pipeline.errors import InputError

    p = Path(file)
    try:
        doc = json.loads(p.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{p}: cannot read trace.lights_file ({e}); give a JSON list of "
                         f"{{\"corners\": [[x, y, z] x 4], \"radiance\": [r, g, b]}}") from None
    if not isinstance(doc, list):
        raise InputError(f"{p}: trace.lights_file must be a JSON list of emitters, got {type(doc).__name__}")
    out = []
    for k, e in enumerate(doc):
        try:
            c = np.asarray(e["corners"], np.float64)
            r = np.asarray(e["radiance"], np.float64)
        except (TypeError, KeyError, ValueError):
            raise InputError(f"{p}: emitter {k} needs \"corners\" (4 x [x, y, z] metres) and \"radiance\" "
                             f"([r, g, b])") from None
        if c.shape != (4, 3) or r.shape != (3,) or not (np.all(np.isfinite(c)) and np.all(np.isfinite(r))):
            raise InputError(f"{p}: emitter {k}: corners {c.shape} / radiance {r.shape} must be 4 x 3 and 3 "
                             f"finite numbers")
        if np.any(r < 0) or _quad_area(c)[0] < 1e-8:
            raise InputError(f"{p}: emitter {k}: radiance {r.tolist()} must be >= 0 and the rectangle must "
                             f"have an area")
        out.append((c, r * radiance_scale))
    return out


def fit_room_lights(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None, frames, *,
                    up: np.ndarray, rng: np.random.Generator, settings: FitSettings = FitSettings(),
                    name: str = "scan", known_lights=(), threads: int = 1) -> RoomLights:
    """Recover the room's emitters from its photos (see the module docstring).

    Parameters
    ----------
    vertices, faces : (V, 3) float metres and (T, 3) int, the room mesh
    colors : (V, 3) uint8 sRGB vertex colours (the radiance of what the scan saw), or None (then the
        photos' own observations give each vertex its radiance)
    frames : list of ``(photo (H, W, 3) uint8 sRGB, K (3, 3), T_c2w (4, 4))``
    up : (3,) world up
    rng : seeded generator (the fit is deterministic for a generator state)
    name : the scan's name, for messages
    known_lights : ``(corners (4, 3) metres, radiance (3,) linear, photo units)`` rectangles that are
        known to emit (``trace.lights_file``): added to the room as lights of that radiance; the fit
        then explains only what they leave unexplained
    threads : threads for the fit's shadow rays and its independent level searches (the result does not
        depend on it; BLAS is left as the caller set it): more than one where nothing else runs beside the
        fit (the trace stage's plan)

    Returns
    -------
    RoomLights; its ``summary["note"]`` says in one line what was assumed when the fit fell back
    """
    if threads <= 1:
        return _fit_room_lights(vertices, faces, colors, frames, up=up, rng=rng, settings=settings, name=name,
                                known_lights=known_lights, pool=None)
    with ThreadPoolExecutor(max_workers=threads) as pool:
        return _fit_room_lights(vertices, faces, colors, frames, up=up, rng=rng, settings=settings, name=name,
                                known_lights=known_lights, pool=pool)


def _fit_room_lights(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None, frames, *,
                     up: np.ndarray, rng: np.random.Generator, settings: FitSettings, name: str, known_lights,
                     pool: ThreadPoolExecutor | None) -> RoomLights:
    """:func:`fit_room_lights`, its shadow rays and level searches on ``pool``'s threads (None: this one)."""
    from pipeline.camera import Camera
    from pipeline.trace.intersect import EmbreeIntersector

    t0 = time.process_time()
    st = settings
    V = np.asarray(vertices, np.float64).reshape(-1, 3)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    nv, nt = len(V), len(F)
    frames = list(frames)
    cameras = [Camera(K=np.asarray(Kc, np.float64), T_c2w=np.asarray(T, np.float64), width=np.shape(ph)[1],
                      height=np.shape(ph)[0]) for ph, Kc, T in frames]
    cams = [c.center for c in cameras]
    kq = [np.asarray(c, np.float64).reshape(4, 3) for c, _ in known_lights]
    # a known light emits on the side its corners turn counter-clockwise around (as the trace samples it)
    kq_n = [_unit_normal(q) for q in kq]
    upv = np.asarray(up, np.float64) / np.linalg.norm(up)
    pts_box = box_extent(V, cameras, kq, upv) if nv or cams else np.zeros((1, 3))
    hgt = pts_box @ upv
    h_low = float(hgt.min())
    ceiling_assumed = float(hgt.max()) - h_low < ASSUMED_CEILING_M
    if ceiling_assumed:   # a scan that did not reach the ceiling: put the box's top where a ceiling would be
        pts_box = np.concatenate([pts_box, (pts_box[np.argmin(hgt)] + ASSUMED_CEILING_M * upv)[None]])
    BV, BF, bcen, bnrm = closing_box(pts_box, up, st.cell)
    nb = len(bcen)
    hb = bcen @ upv
    # the box's bottom (under the floor) and the low band of its sides (furniture height): never a light
    floor_cell = ((bnrm @ upv) > 0.5) | (hb < h_low + LOW_FILL_M)
    ceiling_cell = (bnrm @ upv) < -CEILING_COS   # the box's top (white paint where st.ceiling_albedo > 0)
    KV = np.concatenate(kq) if kq else np.zeros((0, 3))
    KF = np.array([[4 * i, 4 * i + 1, 4 * i + 2] for i in range(len(kq))] +
                  [[4 * i, 4 * i + 2, 4 * i + 3] for i in range(len(kq))], np.int64).reshape(-1, 3)
    k_rad = np.asarray([r for _, r in known_lights], np.float64).reshape(-1, 3)   # (len(kq), 3)
    Krad = np.repeat(k_rad, 4, axis=0)
    AV = np.concatenate([V, BV, KV]).astype(np.float32)
    AF = np.concatenate([F, BF + nv, KF + nv + len(BV)]).astype(np.int32)
    nbt = nt + len(BF)                       # triangles before the known lights
    isect = EmbreeIntersector(AV, AF)
    eps = 1e-3 * max(float(np.ptp(AV, axis=0).max()), 1e-3)
    p_ = AV[AF].astype(np.float64)
    tn = np.cross(p_[:, 1] - p_[:, 0], p_[:, 2] - p_[:, 0])
    tarea = 0.5 * np.linalg.norm(tn, axis=1)
    tn /= np.maximum(2 * tarea, 1e-30)[:, None]
    scale_r = float(st.radiance_scale)
    mesh_rad = (srgb_to_linear(np.asarray(colors)).astype(np.float64) * scale_r if colors is not None
                else None)

    # --- observations ------------------------------------------------------------------------------
    thr_lin = float(srgb_to_linear(np.array([st.threshold], np.uint8))[0]) * scale_r
    seen = np.zeros(nv, np.int64)
    clipped_v = np.zeros(nv, np.int64)
    box_sum = np.zeros((nb, 3))
    box_n = np.zeros(nb, np.int64)
    box_clip = np.zeros(nb, np.int64)
    vsum = np.zeros((nv, 3))
    vn = np.zeros(nv, np.int64)
    obs_p, obs_n, obs_L = [], [], []
    exposures = []
    sides = np.zeros(2, np.int64)     # camera rays that met a mesh triangle's front / back
    edge_excess = []                  # per photo, its clipped lights' edge pixels (_clipped_edge_excess)
    # (not read where the lights handed in are every light: the fit then colours no light of its own)
    read_edges = st.edge_colour and not (kq and st.known_complete)
    for (photo, _, _), cam in zip(frames, cameras):
        photo = np.asarray(photo, np.uint8)
        h, w = photo.shape[:2]
        if read_edges:
            edge_excess.append(_clipped_edge_excess(photo, st.threshold))
        ys, xs = np.mgrid[st.stride // 2:h:st.stride, st.stride // 2:w:st.stride]
        pix = (ys * w + xs).ravel()
        o, d = cam.rays(pix, np.full((pix.size, 2), 0.5, np.float32))
        hits = isect.intersect(o, d)
        col = photo.reshape(-1, 3)[pix]
        lin = srgb_to_linear(col).astype(np.float64) * scale_r
        clip = col.max(axis=1) >= st.threshold
        on_mesh = hits.hit & (hits.prim < nt)
        # exposure of this photo relative to the mesh colours (1 without colours)
        expo = 1.0
        if mesh_rad is not None:
            ok = np.flatnonzero(on_mesh & ~clip)
            ratio = exposure_ratio(lin[ok] @ LUMINANCE_F64,
                                   _at(mesh_rad, F, hits.prim[ok], hits.u[ok], hits.v[ok]) @ LUMINANCE_F64,
                                   floor=DARK_LEVEL * scale_r, min_samples=MIN_EXPOSURE_SAMPLES)
            if ratio is not None:
                expo = float(np.clip(ratio, *EXPOSURE_RANGE))
        exposures.append(expo)
        lin /= expo
        if on_mesh.any():
            # > 0: the ray met the triangle's back (its normal's side away from the camera)
            facing = np.zeros(pix.size)
            facing[on_mesh] = np.sum(tn[hits.prim[on_mesh]] * d[on_mesh], axis=1)
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
                n = tn[prim] * -np.sign(facing[good, None] + 1e-30)
                obs_p.append(o[good] + hits.t[good, None] * d[good])
                obs_n.append(n)
                obs_L.append(lin[good])
        on_box = hits.hit & (hits.prim >= nt) & (hits.prim < nbt)
        if on_box.any():
            cell = (hits.prim[on_box] - nt) // 2
            np.add.at(box_sum, cell[~clip[on_box]], lin[on_box][~clip[on_box]])
            np.add.at(box_n, cell[~clip[on_box]], 1)
            np.add.at(box_clip, cell[clip[on_box]], 1)

    edge_colour = _edge_colour(np.concatenate(edge_excess)) if edge_excess else None
    edge_raised = [None]              # the most the edges' colour raised a clipped light's luminance (_edge_coloured)
    if mesh_rad is None:   # no colours: each vertex gets the mean of the photo pixels that saw it
        mesh_rad = np.zeros((nv, 3))
        have = vn > 0
        mean_obs = (vsum[have].sum(axis=0) / max(vn[have].sum(), 1)) if have.any() else np.zeros(3)
        mesh_rad[have] = vsum[have] / vn[have, None]
        mesh_rad[~have] = mean_obs
    summary: dict = {"frames": len(frames), "exposure": [round(e, 4) for e in exposures],
                     "box_cells": int(nb), "mesh_triangles": int(nt), "known_lights": len(kq),
                     "camera_sides": sides.tolist()}
    if edge_excess:
        summary["clipped_edge_pixels"] = int(sum(len(x) for x in edge_excess))
        summary["clipped_edge_colour"] = None if edge_colour is None else _finite(edge_colour)
    # the side of the mesh's triangles the cameras see (+1 front, -1 back, 0 either): a scan is a shell
    # seen from inside, and a table top or a shelf is one sheet with no underside. A ray from the floor
    # below that meets the sheet's unseen side must not take the lit top's colour (the gathers below)
    seen_side = (1 if sides[0] >= SIDE_SHARE * sides.sum() else -1 if sides[1] >= SIDE_SHARE * sides.sum() else 0)
    summary["seen_side"] = seen_side
    # a known light emits on one side only (as the trace stage samples it): one that turns its back on every
    # camera is most likely wound the wrong way, which would light the room in no image. Said, not changed.
    backwards = [k for k, (q, qn_) in enumerate(zip(kq, kq_n)) if cams and all(
        float(qn_ @ (c - q.mean(axis=0))) < 0 for c in cams)]
    if backwards:
        summary["lights_facing_away"] = backwards
        log.warning("light fit of %s: trace.lights_file emitter(s) %s face away from every camera (they emit on the "
                    "side their corners turn counter-clockwise around); if they should light the room, reverse "
                    "their corners' order", name, backwards)

    def fallback(note: str) -> RoomLights:
        """The mesh's colours alone (the "scan" lighting) closed by a box of their mean radiance."""
        mean = (mesh_rad.mean(axis=0) if nv else np.zeros(3))
        rad = np.concatenate([mesh_rad, np.tile(mean, (len(BV), 1)), Krad]).astype(np.float32)
        summary.update(note=note, fitted=False, seconds=round(time.process_time() - t0, 2), emitters=[])
        log.warning("light fit of %s: %s", name, note)
        lt = np.zeros(len(AF), bool)
        lt[nbt:] = True
        return RoomLights(vertices=AV, faces=AF, radiance=rad, light_tri=lt,
                          num_mesh_vertices=nv, num_mesh_tris=nt, summary=summary)

    if not frames:
        return fallback("no colour photos: lit by the mesh colours alone, holes at their mean radiance")
    if nt == 0:
        return fallback("no room mesh: nothing to fit")

    # --- unknowns: unseen / clipped box cells, clipped mesh regions ---------------------------------
    light_v = (seen >= 2) & (clipped_v >= st.min_share * np.maximum(seen, 1))
    if colors is not None:   # where the grid rays barely met a vertex, its colour (from every photo) says
        light_v |= (seen < 2) & (np.asarray(colors).reshape(-1, 3).max(axis=1) >= st.threshold)
    if kq:
        # the mesh's surface where a known light is (a lamp or window in view, also in the depth maps) is that
        # light: not a second emitter (clipped, at least sensor white) nor a bright surface in the gathers. As
        # one, it lit the light suite's lamp-in-view room 1.4x the wall panel handed in
        on_known = _near_quads(V, np.asarray(kq), KNOWN_LIGHT_REACH_M)
        summary["vertices_on_known_lights"] = int(on_known.sum())
        light_v &= ~on_known
        mesh_rad[on_known] = 0.0
    box_known = box_n > 0
    box_rad = np.zeros((nb, 3))
    box_rad[box_known] = box_sum[box_known] / box_n[box_known, None]
    box_unknown = np.flatnonzero((~box_known | (box_clip > box_n)) & ~floor_cell)
    # a cell the mesh hides from every camera is behind the scan's surfaces (a wall's far side): nothing there
    # lights the room but through the gap between the mesh and the box, and a lamp behind a wall lighting the
    # room through the white ceiling (CEILING_ALBEDO) explained photos of walls brighter near the top better
    # than the ceiling's own cells did. Such cells stay dark, and do not reflect
    unmet = box_unknown[(box_n + box_clip)[box_unknown] == 0]     # cells no photo's ray met
    behind = unmet[_behind_the_mesh(isect, BV.reshape(-1, 4, 3)[unmet], cams, eps)]
    box_unknown = np.setdiff1d(box_unknown, behind)
    summary["cells_behind_the_mesh"] = int(behind.size)
    # low cells no photo saw: the mean radiance of the mesh's surfaces below the same height
    fill = ~box_known & floor_cell
    low = V[F].mean(axis=1) @ upv < h_low + LOW_FILL_M
    low_rad = mesh_rad[F[low]].mean(axis=(0, 1)) if low.any() else mesh_rad.mean(axis=0)
    box_rad[fill] = low_rad
    # clipped mesh triangles grouped into cells of st.cell metres
    light_t = np.flatnonzero(light_v[F].all(axis=1))
    groups: list[np.ndarray] = []
    if light_t.size:
        cen_t = V[F[light_t]].mean(axis=1)
        key = np.floor(cen_t / st.cell).astype(np.int64)
        _, inv = np.unique(key, axis=0, return_inverse=True)
        groups = [light_t[inv.ravel() == g] for g in range(inv.max() + 1)]
    K = box_unknown.size + len(groups)
    summary.update(unknown_cells=int(box_unknown.size), clipped_regions=len(groups),
                   ceiling_assumed_m=ASSUMED_CEILING_M if ceiling_assumed else None,
                   clipped_vertices=int(light_v.sum()), observed_cells=int(box_known.sum()))

    if not obs_p:
        return fallback("no unclipped, lit room pixel in the photos (all dark or all clipped): lit by the "
                        "mesh colours alone")
    P = np.concatenate(obs_p)
    N = np.concatenate(obs_n)
    L = np.concatenate(obs_L)
    if len(P) < MIN_FIT_POINTS:
        return fallback(f"only {len(P)} unclipped lit room pixels in the photos (need {MIN_FIT_POINTS}): lit by "
                        f"the mesh colours alone")
    sel = np.sort(rng.choice(len(P), size=min(len(P), st.points), replace=False))
    P, N, L = P[sel], N[sel], L[sel]
    n = len(P)

    # per-element radiance used by the gather: mesh colours (emitters: 0, they are unknowns), known cells
    unknown_tri = np.zeros(len(AF), np.int64) - 1       # triangle -> unknown index
    for k, c in enumerate(box_unknown):
        unknown_tri[nt + 2 * c: nt + 2 * c + 2] = k
    for g, tris in enumerate(groups):
        unknown_tri[tris] = box_unknown.size + g
    vrad = np.concatenate([mesh_rad, np.repeat(box_rad, 4, axis=0), Krad])
    # lower bounds: clipped observations are at least sensor white
    lb = np.zeros((K, 3))
    for k, c in enumerate(box_unknown):
        if box_clip[c] > 0:
            lb[k] = thr_lin
    lb[box_unknown.size:] = thr_lin

    def edge_coloured(e: np.ndarray) -> None:
        """The fit's answer ``e (K, 3)``, in place: the unknowns the photos saw clipped (a lower bound) take their
        edges' colour where the photos show it. The colour of a light seen clipped is the photos' own there; the
        fit's comes from the albedo's colour, which the photos barely tell (the suite's lamp in view: blue / red
        0.60, the edges' 0.66, the truth's 0.70). Its luminance stays the fit's unless a channel would fall under
        sensor white; the albedo and the residuals stay the fit's, under its own colour."""
        if edge_colour is not None:
            seen = np.flatnonzero(lb.max(axis=1) > 0)
            e[seen], edge_raised[0] = _edge_coloured(e[seen], lb[seen], edge_colour)

    # known irradiance: cosine-weighted rays against mesh + box
    M = st.gather_rays
    pr, hh, dg = _gather(isect, P, N, M, rng, eps, pool)
    Lg = np.zeros((pr.size, 3))
    hit = np.flatnonzero(hh.hit)
    Lg[hit] = _at(vrad, AF, hh.prim[hit], hh.u[hit], hh.v[hit])
    # a mesh triangle's unseen side does not send the seen side's colour: with the top's colour there, the
    # floor under the suite's table got 2.0x its true irradiance (75th percentile; 3.6x at the 95th), and the
    # fit a darker albedo. What it sends instead depends on the albedo (see _sheet_backs below)
    back = hit[_unseen_side(hh.prim[hit], dg[hit], tn, nt, seen_side)]
    Lg[back] = 0.0
    # (a clipped region's back is not a sheet: the region is an unknown, sampled two-sided below)
    sheet = back[unknown_tri[hh.prim[back]] < 0]
    back_owner = pr[sheet]
    back_pos = P[back_owner] + hh.t[sheet, None].astype(np.float64) * dg[sheet].astype(np.float64)
    back_normal = tn[hh.prim[sheet]] * float(seen_side)    # the side the cameras saw (seen_side is +-1 here)
    summary["gather_unseen_side"] = round(float(back.size / max(hit.size, 1)), 4)
    Lg[hit[(unknown_tri[hh.prim[hit]] >= 0) | (hh.prim[hit] >= nbt)]] = 0.0   # sampled explicitly below
    Ek = np.pi * Lg.reshape(n, M, 3).mean(axis=1)

    # irradiance per unit radiance of each unknown: its area sampled explicitly, with visibility
    el_tris = [np.arange(nt + 2 * c, nt + 2 * c + 2) for c in box_unknown] + list(groups)
    known_tris = [np.array([nbt + i, nbt + len(kq) + i]) for i in range(len(kq))]
    A = np.zeros((n, K + len(kq)))
    S = st.emitter_samples
    Pi = np.repeat(P, S, axis=0)
    Ni = np.repeat(N, S, axis=0)

    def jobs():
        for k, tris in enumerate(el_tris + known_tris):
            drawn = _area_points(tris, n * S, p_, tn, tarea, rng)
            if drawn is not None:
                # a clipped mesh region (or a known light) lights both ways
                yield k, functools.partial(_sampled_irradiance, isect, Pi, Ni, drawn[0], drawn[1], drawn[2], eps,
                                           two_sided=box_unknown.size <= k < K)

    _fill_columns(A, S, jobs(), pool)
    if kq:   # the known lights' irradiance joins the known part
        Ek = Ek + A[:, K:] @ k_rad
    A = np.ascontiguousarray(A[:, :K])
    active = np.flatnonzero(A.max(axis=0) > 0)
    # where the light comes from (stage 1, and stage 3's choice among lamps) is found on every other point;
    # the chosen emitters' power and the albedo level are fitted to all of them (see FitSettings.points)
    srows = np.arange(0, n, 2) if n >= 2 * MIN_FIT_POINTS else np.arange(n)
    A1 = np.ascontiguousarray(A[srows])

    # The unseen cells reflect as well as emit: a cell's radiance is e + rho_u / pi (Eu_known + G L_u),
    # with G (K x K) the irradiance one cell receives per unit radiance of another and Eu_known what it
    # receives from the known room (hemisphere rays from its centre). So the fill light of unseen walls and
    # ceiling follows from the room's light at the albedo level being tried, and only emission pays the
    # sparsity prior: L_u = (I - rho_u / pi G)^-1 (e + rho_u / pi Eu_known).
    G = np.zeros((K, K))
    Eu = np.zeros((K, 3))
    nbu = box_unknown.size
    if nbu:
        Mu = max(16, M // 2)
        ku, hu, du = _gather(isect, bcen[box_unknown], bnrm[box_unknown], Mu, rng, eps, pool)
        hit = np.flatnonzero(hu.hit)
        hit = hit[~_unseen_side(hu.prim[hit], du[hit], tn, nt, seen_side)]
        tri = hu.prim[hit]
        j = unknown_tri[tri]
        un = (j >= 0) & (j < nbu)             # unseen cells (clipped regions: sampled below)
        np.add.at(G, (ku[hit[un]], j[un]), np.pi / Mu)
        kn = hit[(j < 0) & (tri < nbt)]
        np.add.at(Eu, ku[kn], np.pi / Mu * _at(vrad, AF, hu.prim[kn], hu.u[kn], hu.v[kn]))
        if groups:
            # what the clipped regions send the unseen cells, sampled over their area (from the side the cameras
            # saw, as the gather takes it): the cells' hemisphere rays meet a small bright region seldom, and the
            # lamp-in-view room's unseen ceiling got 0.70-1.33x its mean light from the wall panel over four run
            # seeds (area samples: within 0.5 %)
            G[:nbu, nbu:] = _region_columns(isect, bcen[box_unknown], bnrm[box_unknown], groups, p_, tn, tarea,
                                            REGION_SAMPLES, seen_side, rng, eps, pool)
        if kq:   # and what the known lights send them (sampled by area, as the trace stage's lights are)
            Eu[:nbu] += _quad_columns(isect, bcen[box_unknown], bnrm[box_unknown], np.asarray(kq), np.asarray(kq_n),
                                      16, rng, eps, pool) @ k_rad
    reflect = np.zeros(K)
    reflect[:nbu] = 1.0                      # clipped mesh regions are lamps: they do not reflect here
    # the ceiling's cells reflect as white paint, whatever the walls' albedo (see CEILING_ALBEDO)
    ceiling = np.zeros(K)
    if st.ceiling_albedo > 0:
        ceiling[:nbu] = ceiling_cell[box_unknown]
        reflect -= ceiling
    summary["ceiling_cells"] = int(ceiling.sum())

    # the unseen cells' albedo relative to the room's level, per channel: 1 until stage 1 has found the
    # walls' (see _wall_ratio)
    unseen_ratio = np.ones(3)

    def unseen(level: np.ndarray) -> np.ndarray:
        """(3,) albedo of the unseen cells at the room's albedo levels ``level (3,)``."""
        return np.clip(np.asarray(level, np.float64) * unseen_ratio, *ALBEDO_RANGE)

    def rho_u(albedo_c: float) -> np.ndarray:
        """(K,) albedo over pi of the unknowns when the unseen side cells' albedo is ``albedo_c`` (the ceiling's
        is ``ceiling_albedo``; clipped regions do not reflect)."""
        return (albedo_c * reflect + st.ceiling_albedo * ceiling) / np.pi

    def transport(albedo_c: float) -> np.ndarray:
        """(I - rho_u / pi G)^-1 for an unseen cell albedo of ``albedo_c``."""
        return np.linalg.inv(np.eye(K) - rho_u(albedo_c)[:, None] * G)

    # albedo patches: cells of albedo_cell metres x the dominant normal axis
    keyp = _patch_keys(P, N, st.albedo_cell)
    _, patch = np.unique(keyp, axis=0, return_inverse=True)
    patch = patch.ravel()
    npatch = int(patch.max()) + 1
    summary["albedo_cells"] = npatch
    if st.albedo_group > 0:
        patch, npatch = _chromaticity_groups(patch, keyp, L, st.albedo_group)
    summary["albedo_patches"] = npatch
    # the albedo prior (off by default): each patch's (log) albedo is drawn toward the room's level as if
    # albedo_shrink x the mean points per patch had seen it there
    n_patch = np.bincount(patch, minlength=npatch)[:, None].astype(np.float64)
    # what the unseen sides of sheets (a table top's underside) send: their own albedo times the light of the
    # low surfaces they face, per point and unit albedo of each patch (see _sheet_backs). Sending nothing
    # there (as before) left the floor under the suite's table short of known light: the fit raised the
    # albedo level to explain it, and its lights emitted 0.80-1.00 of the truth's power in the suite's spot
    # and dim rooms (run seeds 0-4; 0.87-1.03 with it)
    backs = _sheet_backs(P, N, patch, npatch, back_owner, back_pos, back_normal, st.albedo_cell, np.pi / M)

    def sheet_light(br, albedo: np.ndarray) -> np.ndarray:
        """(rows, 3) irradiance the sheets' unseen sides send the points of ``br`` (rows of ``backs``) at
        albedo ``albedo (npatch + 1, 3)``: each patch's, then the room's level."""
        return (br @ albedo) * low_rad[None, :]

    kappa = st.albedo_shrink * n / npatch
    w = _relative_weights(P, N, L @ LUMINANCE_F64)
    area_k = np.array([float(tarea[t].sum()) for t in el_tris])
    # the sparsity prior weighs each unknown by how much light it sends to the photographed points (its
    # column's norm), as a lasso on normalised columns does: weighing emitted power instead favoured
    # cells close to the points, which explain them with the least power, and over-lit the table
    # cells the points see only through slivers: _sliver_rule
    cn = np.linalg.norm(A1, axis=0) if K else np.zeros(0)
    med = float(np.median(cn[cn > 0])) if (cn > 0).any() else 1.0
    seen_ok, lam_k = _sliver_rule(cn, np.full(K, med), med)
    active = active[seen_ok[active]]
    # the median cell's column per unit of its area (stage 3's lamps are held to it)
    dens = float(np.median(cn[active] / np.maximum(area_k[active], 1e-12))) if active.size else 0.0

    def alternate(level: np.ndarray, Ekc: np.ndarray, cols: list, lbj: np.ndarray, lamj: np.ndarray,
                  sparsity: float, iters: int, scale: float | list | None = None,
                  rows: np.ndarray | None = None, on=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Alternate the emission of columns ``cols`` (per channel (n, J): irradiance at the points per unit
        radiance, bounded below by ``lbj``) and the patch albedo, each channel's albedo level held at
        ``level (3,)``; ``Ekc`` the irradiance nothing fitted here sends. Returns the emission (J, 3), the
        patch albedo, the irradiance at the points and each channel's objective (channels are independent).
        ``rows``: the points ``Ekc`` and ``cols`` are given for (all by default). ``on``: the pool for the
        channels' solves, where this runs outside it (the fits between the level searches)."""
        pt, wr, Lr, npr, kap, br = patch, w, L, n_patch, kappa, backs
        if rows is not None:
            pt, wr, Lr, br = patch[rows], w[rows], L[rows], backs[rows]
            npr = np.bincount(pt, minlength=npatch)[:, None].astype(np.float64)
            kap = st.albedo_shrink * len(rows) / npatch
        rho = np.tile(level, (npatch, 1))
        ej = lbj.copy()
        Ek0 = Ekc

        def known(rho: np.ndarray) -> np.ndarray:
            """``Ekc`` and the light the sheets' unseen sides send at patch albedo ``rho`` (the level where
            no patch is near)."""
            return Ek0 + sheet_light(br, np.vstack([rho, level[None]]))

        Ekc = known(rho)
        if scale is None and sparsity != 0:   # the prior's scale does not change with the albedo: once
            scale = [_prior_scale(cols[c], wr) for c in range(3)]
        l1 = np.zeros(3)
        for _ in range(iters):
            ej, l1 = _solve_emission(rho[pt], Ekc, cols, Lr, wr, lbj, lamj, sparsity, scale, st.shared_colour, on)
            E = Ekc + np.stack([cols[c] @ ej[:, c] for c in range(3)], axis=1)
            rho_new = np.empty((npatch, 3))
            for ch in range(3):
                num = np.bincount(pt, weights=wr * wr * Lr[:, ch] * E[:, ch], minlength=npatch)
                den = np.bincount(pt, weights=wr * wr * E[:, ch] ** 2, minlength=npatch)
                rho_new[:, ch] = np.where(den > 0, np.pi * num / np.maximum(den, 1e-30), level[ch])
            # keep each channel's overall level: the search over levels sets it, the alternation the pattern
            rho_new = np.clip(rho_new, *ALBEDO_RANGE)
            if kap > 0:   # shrunk toward the room's level: a patch's brightness is light unless its points say not
                lv0 = np.exp(np.mean(np.log(rho_new), axis=0))
                rho_new = np.exp((npr * np.log(rho_new) + kap * np.log(lv0)) / (npr + kap))
            lvl = np.exp(np.mean(np.log(rho_new), axis=0))
            rho = np.clip(rho_new * (level / np.maximum(lvl, 1e-9)), *ALBEDO_RANGE)
            Ekc = known(rho)
        E = Ekc + np.stack([cols[c] @ ej[:, c] for c in range(3)], axis=1)
        pred = rho[pt] / np.pi * E
        res = np.sum((wr[:, None] * (pred - Lr)) ** 2, axis=0)
        return ej, rho, E, res + 2 * l1          # the objective: data + few-bright-emitters prior

    def design(level: np.ndarray, cols: np.ndarray, fixed: np.ndarray, extra: np.ndarray | None = None,
               rows: np.ndarray | None = None) -> tuple[list, list, np.ndarray]:
        """Per channel at albedo levels ``level (3,)``: the transport of the unknown cells, the irradiance at
        the points per unit emission of the unknowns ``cols`` (then of the ``extra (K, J)`` sources that
        light the unseen cells, if given), and the known light at the points: direct, reflected once more by
        the unseen cells, and sent by the unknowns ``fixed`` at their lower bound. Only the columns asked for
        are multiplied out: A (M x) costs the points x K per column, (A M) the points x K x K. ``rows``:
        all points (None), or a subset (``srows``, stage 3's ``crows``)."""
        Ar, Ekr = (A, Ek) if rows is None else (A1, Ek[srows]) if rows is srows else (A[rows], Ek[rows])
        ua = unseen(level).tolist()
        Ms = {a: transport(a) for a in set(ua)}
        Mc = [Ms[a] for a in ua]
        Ac = {}
        for a, M in Ms.items():
            rhs = M[:, cols] if extra is None else np.concatenate([M[:, cols], M @ (rho_u(a)[:, None] * extra)], 1)
            Ac[a] = Ar @ rhs
        Ae = [Ac[a] for a in ua]
        Ekc = np.stack([Ekr[:, c] + Ar @ (Mc[c] @ (rho_u(ua[c]) * Eu[:, c]) + Mc[c][:, fixed] @ lb[fixed, c])
                        for c in range(3)], axis=1)
        return Mc, Ae, Ekc

    def fit_at(level: np.ndarray, iters: int = 4, active: np.ndarray = active, sparsity: float = st.sparsity,
               rows: np.ndarray | None = None, on=None, final: bool = False) -> tuple[tuple, np.ndarray, np.ndarray]:
        """Emission of the unknowns ``active`` (the others stay at their lower bound) and albedo at each
        channel's albedo level ``level (3,)``; returns (emission, unknowns' radiance, irradiance at the
        points ``rows``), the patch albedo and each channel's objective. ``final``: the fit's answer (the lights
        seen clipped take their edges' colour, where the photos show it)."""
        Mc, Ae, Ekc = design(level, active, np.setdiff1d(np.arange(K), active), rows=rows)
        ea, rho, E, obj = alternate(level, Ekc, Ae, lb[active], lam_k[active], sparsity, iters, rows=rows, on=on)
        e = lb.copy()
        e[active] = ea
        if final:
            edge_coloured(e)
        ua = unseen(level)
        Lu = np.stack([Mc[c] @ (e[:, c] + rho_u(ua[c]) * Eu[:, c]) for c in range(3)], axis=1)
        return (e, Lu, E), rho, obj

    lamp_q, lamp_n, lamp_e = np.zeros((0, 4, 3)), np.zeros((0, 3)), np.zeros((0, 3))

    def refine(level: np.ndarray, sup: np.ndarray):
        """Stage 3: the emitting box cells ``sup`` stand for lamps smaller than a cell, at the box or, under
        the ceiling, hanging below it (a 0.4 m cell on the ceiling smears a 10 cm spot 1.2 m above a table
        into a broad glow from 0.65 m higher). Candidates: each emitting cell cut into squares of
        ``refine`` metres, at the cell and ``REFINE_DEPTHS`` below it where no photo saw free space; the
        few-bright-emitters prior picks among them (as much as a whole cell per unit of light sent to the
        points), the box cells then only reflect, and the chosen lamps are refitted without the prior.
        Returns None when there is nothing to refine."""
        cells = sup[sup < nbu]
        quads, qn, parent = _lamp_candidates(isect, box_unknown[cells], BV, bnrm, upv, st.refine,
                                             h_low + LAMP_MIN_M, cameras, eps)
        if len(quads) == 0:
            return None
        # the choice among them on every other point of stage 1's (half the shadow rays of ~900 candidates,
        # the fit's largest single cost); their norms as if on stage 1's points
        crows = srows[::2] if len(srows) >= 2 * MIN_FIT_POINTS else srows
        Ac = _quad_columns(isect, P[crows], N[crows], quads, qn, S, rng, eps, pool)
        cnc = np.linalg.norm(Ac, axis=0) * np.sqrt(len(srows) / len(crows))
        # stage 1's sliver rule, per unit area: a lamp the points see far less of than its size says (a box
        # square behind a wall, seen through a gap in the mesh) is priced as a lamp of its size seen like the
        # median cell, and dropped under 2 % of that. Without it, lamp_in_view (4000 points, seed 0) took
        # 78 % of its light from one square 2 cm behind the wall: 10x the true panel's power
        seen_ok, lam_c = _sliver_rule(cnc, _quad_area(quads) * dens, med)
        use = np.flatnonzero((cnc > 0) & seen_ok)
        quads, qn, parent, Ac, cnc, lam_c = quads[use], qn[use], parent[use], Ac[:, use], cnc[use], lam_c[use]
        if len(quads) == 0:
            return None
        Gc = np.zeros((K, len(quads)))
        Gc[:nbu] = _quad_columns(isect, bcen[box_unknown], bnrm[box_unknown], quads, qn, 4, rng, eps, pool)
        regions = sup[sup >= nbu]                      # clipped mesh regions stay as they are
        rest = np.setdiff1d(np.arange(K), regions)     # every box cell only reflects (or emits its lower bound)
        nr = regions.size

        def problem(lv: np.ndarray, Gcand: np.ndarray, Acand: np.ndarray, rows: np.ndarray | None = None):
            """Transport, known light and columns (the regions', then the lamps', whose light at the unseen
            cells is ``Gcand (K, J)`` and at the points ``rows`` ``Acand``) at levels ``lv``."""
            Mc, Ae, Ekc = design(lv, regions, rest, Gcand, rows=rows)
            cols = [np.concatenate([Ae[c][:, :nr], Acand + Ae[c][:, nr:]], axis=1) for c in range(3)]
            return Mc, Ekc, cols

        def lamp_bounds(J: int) -> tuple[np.ndarray, np.ndarray]:
            """Lower bounds and prior weights of the regions and ``J`` lamps, for the fits without the prior
            (the lamps' lower bound 0)."""
            return np.concatenate([lb[regions], np.zeros((J, 3))]), np.zeros(nr + J)

        def polish(lv: np.ndarray, lq: np.ndarray, ln: np.ndarray, par: np.ndarray, power: np.ndarray,
                   Gk: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
            """Each cluster of touching lamps (``lq (J, 4, 3)``, normals ``ln``, box cells ``par``) with a lamp
            hung below its cell and at least POLISH_SHARE of their ``power`` becomes one rectangle, placed and
            sized by a coordinate search (:func:`_coordinate_search`, ``st.polish`` evaluations each) on stage
            3's objective at levels ``lv`` over stage 1's points, the other lamps held: within REFINE_DEPTHS of
            its ceiling cell, in free space no photo saw (:func:`_hang_ok`), over no other lamp (in the trace
            the lamps are geometry: one under another shades it). See the module's docstring for why. Returns
            the lamps, their light at the unseen cells ``Gk (K, J')`` and the number of rectangles made."""
            groups = _lamp_clusters(lq, ln, st.refine)
            share = np.array([power[g].sum() for g in groups]) / max(float(power.sum()), 1e-30)
            depth_l = np.einsum("ij,ij->i", lq.mean(axis=1) - BV[4 * par], bnrm[par])   # below each lamp's cell
            # only clusters with a lamp hung below its cell: the grid's depths, 0.25 m apart, are what it refines
            todo = [int(i) for i in np.argsort(-share, kind="stable")
                    if share[i] >= POLISH_SHARE and (depth_l[groups[i]] > 1e-6).any()]
            if not todo:
                return lq, ln, Gk, 0
            seed = int(rng.integers(2 ** 63))
            blo, bhi = BV.min(axis=0), BV.max(axis=0)
            # the lamps: one rectangle per cluster polished (where its first square was), the rest as they are
            first = {int(groups[i][0]): i for i in todo}
            gone = {int(j) for i in todo for j in groups[i][1:]}
            rect, nq, nn, ng = {}, [], [], []
            for j in range(len(lq)):
                if j in gone:
                    continue
                if j in first:
                    g = groups[first[j]]
                    at = int(np.argmax(power[g]))
                    c, u, v = _cluster_start(lq[g], power[g], at)      # in lamp at's plane: its depth
                    rect[len(nq)] = (c, u, v, float(depth_l[g[at]]))
                    nq.append(_rectangle(c, u, v, 0.5 * st.refine, 0.5 * st.refine))
                    ng.append(None)
                else:
                    nq.append(lq[j])
                    ng.append(Gk[:, j])
                nn.append(ln[j])
            nq, nn = np.asarray(nq), np.asarray(nn)
            Gn = np.zeros((K, len(nq)))

            def columns(q: np.ndarray, nrm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                """One lamp's light at stage 1's points and at the unseen cells, with the same samples every
                time (the search compares places, not noise)."""
                a = _quad_columns(isect, P[srows], N[srows], q[None], nrm[None], S, np.random.default_rng(seed), eps)
                g = np.zeros(K)
                g[:nbu] = _quad_columns(isect, bcen[box_unknown], bnrm[box_unknown], q[None], nrm[None], 4,
                                        np.random.default_rng(seed + 1), eps)[:, 0]
                return a[:, 0], g

            An = np.zeros((len(srows), len(nq)))
            for j in range(len(nq)):
                An[:, j], g = columns(nq[j], nn[j])
                Gn[:, j] = g if ng[j] is None else ng[j]
            lbp, lamp = lamp_bounds(len(nq))
            # the transport and the other lamps' columns do not change while one lamp moves: only its column
            Mc, Ekc, cols = problem(lv, Gn, An, rows=srows)
            rho_c = [rho_u(a) for a in unseen(lv)]

            def column(j: int, a: np.ndarray, g: np.ndarray) -> list:
                """Each channel's column of lamp ``j`` lighting the points ``a`` and the unseen cells ``g``."""
                return [a + A1 @ (Mc[c] @ (rho_c[c] * g)) for c in range(3)]

            def score(j: int, a: np.ndarray, g: np.ndarray) -> float:
                cj = [col.copy() for col in cols]
                for c, col in enumerate(column(j, a, g)):
                    cj[c][:, nr + j] = col
                return float(alternate(lv, Ekc, cj, lbp, lamp, 0.0, 2, rows=srows)[3].sum())

            for j, (c, u, v, depth) in rect.items():
                n_ = nn[j]

                def place(x: np.ndarray) -> tuple[np.ndarray, float]:
                    return c + x[0] * n_ + x[1] * u + x[2] * v, depth + x[0]

                others = [k for k in range(len(nq)) if k != j and nn[k] @ n_ > 0.999]

                def valid(x: np.ndarray) -> bool:
                    centre, d = place(x)
                    # no other lamp facing the same way may overlap it, seen along the normal: one would shade
                    # the other in the trace, where the lamps are geometry
                    for k in others:
                        o = nq[k].mean(axis=0) - centre
                        ext_u = 0.5 * np.abs((nq[k][2] - nq[k][0]) @ u) + np.exp(x[3])
                        ext_v = 0.5 * np.abs((nq[k][2] - nq[k][0]) @ v) + np.exp(x[4])
                        if abs(o @ u) < ext_u and abs(o @ v) < ext_v:
                            return False
                    if d <= 1e-9:   # at the ceiling cell: inside the box
                        return bool(np.all(centre >= blo - 1e-6) and np.all(centre <= bhi + 1e-6))
                    return bool(centre @ upv >= h_low + LAMP_MIN_M
                                and _hang_ok(isect, centre[None], n_[None], np.array([d]), cameras, eps)[0])

                def evaluate(x: np.ndarray) -> float:
                    centre, _ = place(x)
                    return score(j, *columns(_rectangle(centre, u, v, np.exp(x[3]), np.exp(x[4])), n_))

                # from the grid's square where the cluster's light is: first its height (the grid's depths are
                # 0.25 m apart) on a finer grid, then everything from there; half sizes 1 cm to a cell
                lmin, lmax = np.log(POLISH_MIN_HALF_M), np.log(st.cell)
                x0 = np.array([0.0, 0.0, 0.0, np.log(0.5 * st.refine), np.log(0.5 * st.refine)])
                lo = np.array([-depth, -st.cell, -st.cell, lmin, lmin])
                hi = np.array([REFINE_DEPTHS[-1] - depth, st.cell, st.cell, lmax, lmax])
                ok = [t for t in np.arange(lo[0], hi[0] + 1e-9, POLISH_DEPTH_STEP_M) if valid(np.r_[t, x0[1:]])]
                fs = [evaluate(np.r_[t, x0[1:]]) for t in ok[:max(st.polish // 2, 1)]]
                if fs:
                    x0[0] = ok[int(np.argmin(fs))]
                x, _, _ = _coordinate_search(evaluate, x0, np.array(POLISH_STEPS), lo, hi, valid, st.polish - len(fs))
                centre, _ = place(x)
                nq[j] = _rectangle(centre, u, v, np.exp(x[3]), np.exp(x[4]))
                An[:, j], Gn[:, j] = columns(nq[j], n_)
                for c, col in enumerate(column(j, An[:, j], Gn[:, j])):
                    cols[c][:, nr + j] = col
            return nq, nn, Gn, len(rect)

        lbj = lamp_bounds(len(quads))[0]
        lamj = np.concatenate([lam_k[regions], lam_c])
        # the prior per unit of light sent to the points as in stage 1: its scale from stage 1's columns
        scale0 = float(np.mean(np.sum((A[np.ix_(crows, active)] * (w[crows] * PRIOR_ALBEDO / np.pi)[:, None]) ** 2,
                                      axis=0)))
        _, Ekc, cols = problem(level, Gc, Ac, rows=crows)
        ej, _, _, _ = alternate(level, Ekc, cols, lbj, lamj, st.sparsity, 3, scale0, rows=crows, on=pool)
        pw = (ej[nr:] @ LUMINANCE_F64) * _quad_area(quads)
        if pw.sum() <= 0:
            return None
        order = np.argsort(-pw)
        cum = np.cumsum(pw[order]) / float(pw.sum())
        keep = np.sort(order[:max(1, int(np.searchsorted(cum, st.support_share)) + 1)][:st.max_emitters])
        lq, ln, Gk = quads[keep], qn[keep], Gc[:, keep]
        if st.polish > 0:
            lq, ln, Gk, summary["polished_lamps"] = polish(level, lq, ln, parent[keep], pw[keep], Gk)
        lbk, lamk = lamp_bounds(len(lq))       # no prior from here on
        # the chosen lamps' light at all the points (fresh samples)
        Akeep = _quad_columns(isect, P, N, lq, ln, S, rng, eps, pool)
        # with the lamps where they are, each channel's albedo level again at the residual's minimum
        summary["stage2_level"] = [float(x) for x in level]

        area_j = np.concatenate([area_k[regions], _quad_area(lq)])

        def objective3(lv: float) -> tuple[np.ndarray, np.ndarray]:
            _, Ekc, cols = problem(np.full(3, lv), Gk, Akeep)
            ej3, _, _, obj = alternate(np.full(3, lv), Ekc, cols, lbk, lamk, 0.0, 2)
            return obj, area_j @ ej3

        res3, power3 = _level_search_with_power(objective3, pool)
        level0 = _curve_minimum(np.asarray(ALBEDO_LEVELS), res3)
        summary["stage3_level_data"] = [round(float(x), 4) for x in level0]
        bright = None
        if st.white_patch > 0:   # the room's brightest surfaces at the data's levels, then pulled toward grey
            _, Ekc, cols = problem(level0, Gk, Akeep)
            bright = _brightest_colour(alternate(level0, Ekc, cols, lbk, lamk, 0.0, 2)[1], patch)
        if bright is not None:
            summary["brightest_albedo_data"] = _finite(bright)
            level = _grey_levels(res3, bright, level0, st.white_patch)
        else:
            level = _white_levels(res3, power3, st.white_prior)
        Mc, Ekc, cols = problem(level, Gk, Akeep)
        ej, rho3, E3, obj3 = alternate(level, Ekc, cols, lbk, lamk, 0.0, 5, on=pool)
        e3 = lb.copy()
        e3[regions] = ej[:nr]
        edge_coloured(e3)
        el = ej[nr:]
        ua = unseen(level)
        Lu3 = np.stack([Mc[c] @ (e3[:, c] + rho_u(ua[c]) * (Eu[:, c] + Gk @ el[:, c]))
                        for c in range(3)], axis=1)
        summary["refined_candidates"] = int(len(quads))
        return e3, Lu3, E3, rho3, lq, ln, el, level, res3, obj3

    if kq and st.known_complete:
        # the lights handed in are every light in the room (trace.lights_complete): nothing else emits (the
        # unknown cells reflect; those the photos saw clipped keep their lower bound), and with the lights' power
        # and colour given, each channel's albedo level is where the photos are explained best (a parabola
        # through the grid's lowest residual): no search for more light, no prior on its colour. Searched twice:
        # the unseen walls reflect like the upper walls found under the first level's light
        nothing = np.zeros(0, np.int64)

        def objective_known(lv: float) -> np.ndarray:
            return fit_at(np.full(3, lv), iters=2, active=nothing, sparsity=0.0)[2]

        for again in (True, False):
            res_curve = _level_search(objective_known, pool)
            best_level = _curve_minimum(np.asarray(ALBEDO_LEVELS), res_curve)
            (e, Lu, E), rho, _ = fit_at(best_level, iters=3, active=nothing, sparsity=0.0, on=pool)
            if again:
                unseen_ratio[:] = _wall_ratio(L, E, w, N @ upv, P @ upv - h_low, best_level)
        summary["unseen_albedo_ratio"] = [round(float(x), 4) for x in unseen_ratio]
        best_level = [float(x) for x in best_level]
        res_curve = res_curve @ LUMINANCE_F64
        note = ""
    elif K == 0 or active.size == 0:
        # nothing unknown the points can see: the mesh and observed holes are the light (scan lighting)
        e = lb.copy()
        Lu = lb.copy()
        rho = np.full((npatch, 3), 0.5)
        E = Ek + sheet_light(backs, np.full((npatch + 1, 3), 0.5))
        best_level, res_curve = None, []
        note = "no unseen or clipped light source visible from the photographed surfaces: lit by the scan itself"
    else:
        # each channel's albedo level where the photos are explained best (the light the known surfaces
        # send each other fixes it, channel by channel: the light's colour comes out of the fit)
        # 1. where the light comes from: emission anywhere, priced by the sparsity prior; the level is the
        # highest (the least light) that explains the photos within level_tolerance of the best (with
        # emission free everywhere the level is barely identifiable: unknown cells make up any amount)
        # (the levels are independent searches: on the pool's threads, numpy's products run side by side)
        def objective(lv: float, **kw) -> np.ndarray:
            return fit_at(np.full(3, lv), iters=2, **kw)[2]

        res_curve = _level_search(functools.partial(objective, rows=srows), pool, st.level_tolerance)  # (levels, 3)
        ok = _within(res_curve, st.level_tolerance)
        level1 = np.asarray(ALBEDO_LEVELS)[[int(np.flatnonzero(ok[:, c]).max()) for c in range(3)]]
        summary["stage1_residuals"] = _finite(res_curve @ LUMINANCE_F64, 3)
        (e, Lu, E), rho, _ = fit_at(level1, iters=3, rows=srows, on=pool)
        # the unseen cells reflect like the upper walls under this light from here on
        unseen_ratio[:] = _wall_ratio(L[srows], E, w[srows], N[srows] @ upv, P[srows] @ upv - h_low, level1)
        summary["unseen_albedo_ratio"] = [round(float(x), 4) for x in unseen_ratio]
        best_level = level1
        if st.max_emitters > 0:
            # 2. few emitters: only the cells carrying support_share of that power (and the clipped regions)
            # may emit; every other unseen cell only reflects. With the emitters pinned the light the room's
            # surfaces send each other identifies each channel's level (as it does with the true lights)
            pw = e @ LUMINANCE_F64 * area_k
            order = np.argsort(-pw)
            cum = np.cumsum(pw[order]) / max(float(pw.sum()), 1e-30)
            keep = order[:max(1, int(np.searchsorted(cum, st.support_share)) + 1)][:st.max_emitters]
            sup = np.union1d(np.intersect1d(keep, active), np.intersect1d(np.arange(box_unknown.size, K), active))
            if sup.size:
                def objective2(lv: float) -> tuple[np.ndarray, np.ndarray]:
                    (e2, _, _), _, obj = fit_at(np.full(3, lv), iters=2, active=sup, sparsity=0.0)
                    return obj, area_k @ e2

                res2, power2 = _level_search_with_power(objective2, pool)
                best_level = np.asarray(ALBEDO_LEVELS)[np.argmin(res2, axis=0)]
                if st.refine <= 0 and st.white_prior > 0:   # stage 2 is the last: the light's colour prior
                    best_level = _white_levels(res2, power2, st.white_prior)
                (e, Lu, E), rho, obj2 = fit_at(best_level, iters=5, active=sup, sparsity=0.0, on=pool, final=True)
                summary["stage1_level"] = [float(x) for x in level1]
                summary["level_residuals_rgb"] = [_finite(r) for r in (res2 / res2.min(axis=0)).T]
                summary["support_cells"] = int(sup.size)
                res_curve = res2
                lamps = refine(np.asarray(best_level), sup) if st.refine > 0 else None
                if lamps is not None:
                    summary["stage2_residual"] = round(float(obj2 @ LUMINANCE_F64), 3)
                    summary["stage3_residual"] = round(float(lamps[-1] @ LUMINANCE_F64), 3)
                    e, Lu, E, rho, lamp_q, lamp_n, lamp_e, best_level, res_curve, _ = lamps
                elif st.refine > 0 and st.white_prior > 0:   # stage 3 found no lamps: stage 2 is the last
                    best_level = _white_levels(res2, power2, st.white_prior)
                    (e, Lu, E), rho, obj2 = fit_at(best_level, iters=5, active=sup, sparsity=0.0, on=pool,
                                                   final=True)
        if len(E) < n:   # no second stage: stage 1's answer, fitted to all the points
            (e, Lu, E), rho, _ = fit_at(level1, iters=3, on=pool, final=True)
        best_level = [float(x) for x in best_level]
        res_curve = res_curve @ LUMINANCE_F64
        note = ""
    if edge_raised[0] is not None:      # the clipped lights took the edges' colour (not with every light given)
        summary["clipped_edge_raised"] = round(edge_raised[0], 3)
        _say_edge_raise(name, edge_colour, edge_raised[0])

    # --- result ------------------------------------------------------------------------------------
    rad = vrad.copy()
    for k, tris in enumerate(el_tris):
        rad[np.unique(AF[tris])] = Lu[k]        # emitted + reflected
    lamp_area = _quad_area(lamp_q)
    power = np.concatenate([area_k * (e @ LUMINANCE_F64) if K else np.zeros(0), lamp_area * (lamp_e @ LUMINANCE_F64)])
    total = float(power.sum())
    lit = np.flatnonzero(power[K:] >= LIGHT_SHARE * total) if total > 0 else np.zeros(0, np.int64)
    # the lamps (stage 3) join the room as small one-sided rectangles, wound to face where they emit
    qf = []
    for i, q in enumerate(lamp_q[lit]):
        f = np.array([[0, 1, 2], [0, 2, 3]]) + 4 * i + len(AV)
        if _unit_normal(q) @ lamp_n[lit[i]] < 0:
            f = f[:, ::-1]
        qf.append(f)
    AVo = np.concatenate([AV, lamp_q[lit].reshape(-1, 3).astype(np.float32)])
    AFo = np.concatenate([AF, np.concatenate(qf).astype(np.int32) if qf else np.zeros((0, 3), np.int32)])
    rad = np.concatenate([rad, np.repeat(lamp_e[lit], 4, axis=0)])
    light_tri = np.zeros(len(AFo), bool)
    light_tri[nbt:len(AF)] = True           # the known lights
    light_tri[len(AF):] = True              # the lamps
    emitters = []
    if total > 0:
        order = np.argsort(-power)
        for k in order:
            if power[k] < LIGHT_SHARE * total:
                break
            if k < K:
                light_tri[el_tris[k]] = True
                c, area, rd = p_[el_tris[k]].reshape(-1, 3).mean(axis=0), area_k[k], e[k]
                kind = "box cell" if k < box_unknown.size else "clipped region"
            else:
                c, area, rd, kind = lamp_q[k - K].mean(axis=0), lamp_area[k - K], lamp_e[k - K], "lamp"
            emitters.append({"centre": [round(float(x), 3) for x in c], "area_m2": round(float(area), 4),
                             "radiance": [round(float(x), 4) for x in rd],
                             "power_share": round(float(power[k] / total), 4), "kind": kind})
    if kq:
        # the light the fit found besides the known lights, over theirs: where a file holds every light but the
        # fit is free to add more, it may put light elsewhere (the light suite's window room, its window handed
        # in: 1.6x too bright); said, with the fix
        known_power = float(_quad_area(np.asarray(kq)) @ (k_rad @ LUMINANCE_F64))
        own = total / known_power if known_power > 0 else None
        summary["own_over_known_power"] = None if own is None else round(own, 4)
        if own is not None and own > OWN_OVER_KNOWN_SAID and not st.known_complete:
            log.warning("light fit of %s: the fit added light of its own with %.2fx the power of the %d light(s) in "
                        "trace.lights_file; if the file holds every light in the room, set trace.lights_complete = "
                        "true (the fit then adds none)", name, own, len(kq))
    pred = rho[patch] / np.pi * E
    rel = np.abs(pred - L).sum(axis=1) / np.maximum(L.sum(axis=1), 1e-9)
    summary.update(fitted=note == "", note=note, points=int(n), albedo_level=best_level,
                   level_residuals=_finite(res_curve, 3),
                   albedo_mean=[round(float(x), 3) for x in np.mean(rho[patch], axis=0)],
                   residual_median=round(float(np.median(rel)), 4),
                   emitters=emitters[:32], num_lights=int(len(emitters)),
                   seconds=round(time.process_time() - t0, 2))
    log.info("light fit of %s: %d points, %d unknowns, albedo level %s, %d emitters sampled, residual %.3f, %.1f s",
             name, n, K, best_level, len(emitters), summary["residual_median"], summary["seconds"])
    # the albedo the fit found, per vertex (the trace stage takes the objects' shadows out of the room's
    # light with it): the mesh's from its nearest fit points, the box's the unseen cells' (the upper walls',
    # as they reflect here), the lamps' 0
    lvl = np.full(3, 0.5) if best_level is None else np.asarray(best_level, np.float64)
    albedo = np.zeros((len(AVo), 3))
    albedo[:nv] = _vertex_albedo(V, F, P, N, rho[patch], lvl, st.albedo_cell)
    albedo[nv:nv + len(BV)] = unseen(lvl)
    if st.ceiling_albedo > 0:            # four vertices per box cell
        albedo[nv:nv + len(BV)][np.repeat(ceiling_cell, 4)] = st.ceiling_albedo
    return RoomLights(vertices=AVo, faces=AFo, radiance=rad.astype(np.float32), light_tri=light_tri,
                      num_mesh_vertices=nv, num_mesh_tris=nt, summary=summary,
                      albedo=np.clip(albedo, 0.0, 1.0).astype(np.float32))
