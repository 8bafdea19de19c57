"""Step 3, the unknowns: what may emit light of a radiance the photos do not give.

The radiance of every box cell no photo saw unclipped, and of every mesh region the photos saw clipped (a
lamp or a window in view): non-negative RGB, at least sensor white where clipped. The rest of the room
has its radiance: the mesh's colours, the box cells the photos saw through holes, and below furniture
height the mean of the mesh's low surfaces. The mesh's surface where a known light is (also in the depth
maps) is that light: neither a second emitter nor a bright surface.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.color import srgb_to_linear
from pipeline.trace.lightfit.closure import ASSUMED_CEILING_M, LOW_FILL_M, Room, behind_the_mesh, near_quads
from pipeline.trace.lightfit.observe import Observations
from pipeline.trace.lightfit.settings import FitSettings

# a mesh vertex this close to a known light (trace.lights_file) is that light's surface: a scan's wall around
# a lamp is a voxel or two rough, and a light handed in may stand a little off its wall
KNOWN_LIGHT_REACH_M = 0.05


@dataclass(frozen=True)
class Unknowns:
    """The room's known radiance, and the emitters of unknown radiance the fit solves for (K of them: the box
    cells first, then the clipped mesh regions)."""

    mesh_rad: np.ndarray       # (nv, 3) float64 linear radiance per mesh vertex (0 on the known lights' surface)
    low_rad: np.ndarray        # (3,) float64 mean radiance of the mesh's surfaces below furniture height
    box_unknown: np.ndarray    # (U,) int64 box cells of unknown radiance
    groups: list               # (t,) int64 mesh triangles of each clipped region
    unknown_tri: np.ndarray    # (T,) int64 unknown each triangle of the room belongs to (-1: none)
    vrad: np.ndarray           # (V, 3) float64 known radiance per vertex of the room (unknowns: their box's fill)
    lb: np.ndarray             # (K, 3) float64 lower bound of each unknown's radiance (sensor white if clipped)
    el_tris: list              # (t,) int64 triangles of each unknown
    area_k: np.ndarray         # (K,) float64 m^2 area of each unknown
    summary: dict = field(default_factory=dict)   # what was found (JSON-able)

    @property
    def K(self) -> int:
        return len(self.el_tris)

    @property
    def nbu(self) -> int:
        """Unknown box cells (the first of the unknowns)."""
        return self.box_unknown.size


def find_unknowns(room: Room, obs: Observations, colors: np.ndarray | None, st: FitSettings) -> Unknowns:
    """The :class:`Unknowns` of ``room`` as the photos (``obs``) and the mesh's ``colors`` show it."""
    summary: dict = {}
    V, F = room.V, room.F
    light_v = (obs.seen >= 2) & (obs.clipped_v >= st.min_share * np.maximum(obs.seen, 1))
    if colors is not None:   # where the grid rays barely met a vertex, its colour (from every photo) says
        light_v |= (obs.seen < 2) & (np.asarray(colors).reshape(-1, 3).max(axis=1) >= st.threshold)
    mesh_rad = obs.mesh_rad
    if room.known_quads:
        # the mesh's surface where a known light is (a lamp or window in view) is that light: not a second
        # emitter (clipped, at least sensor white) nor a bright surface in the gathers
        on_known = near_quads(V, np.asarray(room.known_quads), KNOWN_LIGHT_REACH_M)
        summary["vertices_on_known_lights"] = int(on_known.sum())
        light_v &= ~on_known
        mesh_rad = mesh_rad.copy()
        mesh_rad[on_known] = 0.0
    box_known = obs.box_n > 0
    box_rad = np.zeros((len(box_known), 3))
    box_rad[box_known] = obs.box_sum[box_known] / obs.box_n[box_known, None]
    box_unknown = np.flatnonzero((~box_known | (obs.box_clip > obs.box_n)) & ~room.floor_cell)
    # a cell the mesh hides from every camera is behind the scan's surfaces (a wall's far side): nothing there
    # lights the room but through the gap between the mesh and the box. Such cells stay dark, and do not reflect
    unmet = box_unknown[(obs.box_n + obs.box_clip)[box_unknown] == 0]     # cells no photo's ray met
    behind = unmet[behind_the_mesh(room.isect, room.box_v.reshape(-1, 4, 3)[unmet], room.cams, room.eps)]
    box_unknown = np.setdiff1d(box_unknown, behind)
    summary["cells_behind_the_mesh"] = int(behind.size)
    # low cells no photo saw: the mean radiance of the mesh's surfaces below the same height
    fill = ~box_known & room.floor_cell
    low = V[F].mean(axis=1) @ room.up < room.h_low + LOW_FILL_M
    low_rad = mesh_rad[F[low]].mean(axis=(0, 1)) if low.any() else mesh_rad.mean(axis=0)
    box_rad[fill] = low_rad
    groups = _clipped_regions(V, F, light_v, st.cell)
    summary.update(unknown_cells=int(box_unknown.size), clipped_regions=len(groups),
                   ceiling_assumed_m=ASSUMED_CEILING_M if room.ceiling_assumed else None,
                   clipped_vertices=int(light_v.sum()), observed_cells=int(box_known.sum()))
    el_tris = [np.arange(room.nt + 2 * c, room.nt + 2 * c + 2) for c in box_unknown] + list(groups)
    unknown_tri = np.zeros(len(room.all_f), np.int64) - 1       # triangle -> unknown index
    for k, tris in enumerate(el_tris):
        unknown_tri[tris] = k
    # lower bounds: clipped observations are at least sensor white
    thr_lin = float(srgb_to_linear(np.array([st.threshold], np.uint8))[0]) * float(st.radiance_scale)
    lb = np.zeros((len(el_tris), 3))
    for k, c in enumerate(box_unknown):
        if obs.box_clip[c] > 0:
            lb[k] = thr_lin
    lb[box_unknown.size:] = thr_lin
    return Unknowns(mesh_rad=mesh_rad, low_rad=low_rad, box_unknown=box_unknown, groups=groups,
                    unknown_tri=unknown_tri,
                    vrad=np.concatenate([mesh_rad, np.repeat(box_rad, 4, axis=0),
                                         np.repeat(room.known_radiance, 4, axis=0)]),
                    lb=lb, el_tris=el_tris, area_k=np.array([float(room.tri_area[t].sum()) for t in el_tris]),
                    summary=summary)


def _clipped_regions(V: np.ndarray, F: np.ndarray, light_v: np.ndarray, cell: float) -> list[np.ndarray]:
    """The mesh triangles whose vertices are all emitters (``light_v``), grouped into cells of ``cell`` metres."""
    light_t = np.flatnonzero(light_v[F].all(axis=1))
    if not light_t.size:
        return []
    cen_t = V[F[light_t]].mean(axis=1)
    key = np.floor(cen_t / cell).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    return [light_t[inv.ravel() == g] for g in range(inv.max() + 1)]
