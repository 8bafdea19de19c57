"""Step 8, the result: :class:`RoomLights`, the room with a linear radiance per vertex, the triangles to sample
as lights, the albedo the fit found, and a summary of what was fitted and assumed.

The mesh keeps its colours, the unknowns take their fitted radiance (emitted and reflected), the lamps join
the room as small one-sided rectangles; the emitters with a visible share of the power are sampled as lights.
A mesh vertex takes the albedo of its nearest fit point on a surface facing the same way (the level where no
photo saw it), the box's sides the upper walls', its top the ceiling's.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from pipeline.color import LUMINANCE_F64
from pipeline.trace.lightfit.albedo import ALBEDO_RANGE, finite, vertex_albedo
from pipeline.trace.lightfit.closure import Room, quad_area, unit_normal
from pipeline.trace.lightfit.solve import Problem
from pipeline.trace.lightfit.stages import Solution

log = logging.getLogger(__name__)

LIGHT_SHARE = 0.002           # emitters with at least this share of the fitted power are sampled as lights
OWN_OVER_KNOWN_SAID = 0.5     # with lights handed in, more of its own light than this share of theirs is said
MAX_LISTED = 32               # emitters the summary lists


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


def fallback(room: Room, mesh_rad: np.ndarray, summary: dict, note: str, name: str, t0: float) -> RoomLights:
    """The mesh's colours ``mesh_rad`` alone (the "scan" lighting) closed by a box of their mean radiance, with
    the known lights; ``note`` says why, in the summary and one warning."""
    mean = (mesh_rad.mean(axis=0) if room.nv else np.zeros(3))
    rad = np.concatenate([mesh_rad, np.tile(mean, (len(room.box_v), 1)),
                          np.repeat(room.known_radiance, 4, axis=0)]).astype(np.float32)
    summary = dict(summary, note=note, fitted=False, seconds=round(time.process_time() - t0, 2), emitters=[])
    log.warning("light fit of %s: %s", name, note)
    lt = np.zeros(len(room.all_f), bool)
    lt[room.nbt:] = True
    return RoomLights(vertices=room.all_v, faces=room.all_f, radiance=rad, light_tri=lt,
                      num_mesh_vertices=room.nv, num_mesh_tris=room.nt, summary=summary)


def room_lights(pb: Problem, sol: Solution, summary: dict, name: str, t0: float) -> RoomLights:
    """The :class:`RoomLights` of solution ``sol`` to problem ``pb``; ``summary`` completed with the emitters,
    the residual and the levels."""
    room, unk, st = pb.room, pb.unk, pb.st
    K, AV, AF = unk.K, room.all_v, room.all_f
    rad = unk.vrad.copy()
    for k, tris in enumerate(unk.el_tris):
        rad[np.unique(AF[tris])] = sol.Lu[k]        # emitted + reflected
    lamp_area = quad_area(sol.lamp_q)
    power = np.concatenate([unk.area_k * (sol.e @ LUMINANCE_F64) if K else np.zeros(0),
                            lamp_area * (sol.lamp_e @ LUMINANCE_F64)])
    total = float(power.sum())
    lit = np.flatnonzero(power[K:] >= LIGHT_SHARE * total) if total > 0 else np.zeros(0, np.int64)
    AVo, AFo = _with_lamps(AV, AF, sol.lamp_q[lit], sol.lamp_n[lit])
    rad = np.concatenate([rad, np.repeat(sol.lamp_e[lit], 4, axis=0)])
    light_tri = np.zeros(len(AFo), bool)
    light_tri[room.nbt:len(AF)] = True           # the known lights
    light_tri[len(AF):] = True                   # the lamps
    emitters = _emitters(pb, sol, power, lamp_area, light_tri)
    if room.known_quads:
        summary["own_over_known_power"] = _own_over_known(room, total, st.known_complete, name)
    pred = sol.rho[pb.patch] / np.pi * sol.E
    L = pb.pts.L
    rel = np.abs(pred - L).sum(axis=1) / np.maximum(L.sum(axis=1), 1e-9)
    summary.update(fitted=sol.note == "", note=sol.note, points=int(pb.pts.n), albedo_level=sol.level,
                   level_residuals=finite(sol.res_curve, 3),
                   albedo_mean=[round(float(x), 3) for x in np.mean(sol.rho[pb.patch], axis=0)],
                   residual_median=round(float(np.median(rel)), 4),
                   emitters=emitters[:MAX_LISTED], num_lights=int(len(emitters)),
                   seconds=round(time.process_time() - t0, 2))
    log.info("light fit of %s: %d points, %d unknowns, albedo level %s, %d emitters sampled, residual %.3f, %.1f s",
             name, pb.pts.n, K, sol.level, len(emitters), summary["residual_median"], summary["seconds"])
    return RoomLights(vertices=AVo, faces=AFo, radiance=rad.astype(np.float32), light_tri=light_tri,
                      num_mesh_vertices=room.nv, num_mesh_tris=room.nt, summary=summary,
                      albedo=_albedo(pb, sol, len(AVo)))


def _with_lamps(AV: np.ndarray, AF: np.ndarray, quads: np.ndarray, normals: np.ndarray) -> tuple:
    """The room's vertices and triangles with the lamps ``quads`` added as rectangles wound to face their
    ``normals`` (the side they emit on)."""
    qf = []
    for i, q in enumerate(quads):
        f = np.array([[0, 1, 2], [0, 2, 3]]) + 4 * i + len(AV)
        if unit_normal(q) @ normals[i] < 0:
            f = f[:, ::-1]
        qf.append(f)
    AVo = np.concatenate([AV, quads.reshape(-1, 3).astype(np.float32)])
    AFo = np.concatenate([AF, np.concatenate(qf).astype(np.int32) if qf else np.zeros((0, 3), np.int32)])
    return AVo, AFo


def _emitters(pb: Problem, sol: Solution, power: np.ndarray, lamp_area: np.ndarray, light_tri: np.ndarray) -> list:
    """The emitters with at least LIGHT_SHARE of the ``power`` (the unknowns', then the lamps'), brightest first,
    as the summary lists them; their triangles marked in ``light_tri``, in place."""
    unk, K = pb.unk, pb.unk.K
    total = float(power.sum())
    emitters = []
    if total <= 0:
        return emitters
    for k in np.argsort(-power):
        if power[k] < LIGHT_SHARE * total:
            break
        if k < K:
            light_tri[unk.el_tris[k]] = True
            c, area, rd = pb.room.corners[unk.el_tris[k]].reshape(-1, 3).mean(axis=0), unk.area_k[k], sol.e[k]
            kind = "box cell" if k < unk.nbu else "clipped region"
        else:
            c, area, rd, kind = sol.lamp_q[k - K].mean(axis=0), lamp_area[k - K], sol.lamp_e[k - K], "lamp"
        emitters.append({"centre": [round(float(x), 3) for x in c], "area_m2": round(float(area), 4),
                         "radiance": [round(float(x), 4) for x in rd],
                         "power_share": round(float(power[k] / total), 4), "kind": kind})
    return emitters


def _own_over_known(room: Room, total: float, complete: bool, name: str) -> float | None:
    """The power of the light the fit found besides the known lights over theirs (``total`` its own). Where a
    file holds every light but the fit is free to add more, it may put light elsewhere: said, with the fix."""
    known_power = float(quad_area(np.asarray(room.known_quads)) @ (room.known_radiance @ LUMINANCE_F64))
    own = total / known_power if known_power > 0 else None
    if own is not None and own > OWN_OVER_KNOWN_SAID and not complete:
        log.warning("light fit of %s: the fit added light of its own with %.2fx the power of the %d light(s) in "
                    "trace.lights_file; if the file holds every light in the room, set trace.lights_complete = "
                    "true (the fit then adds none)", name, own, len(room.known_quads))
    return None if own is None else round(own, 4)


def _albedo(pb: Problem, sol: Solution, nverts: int) -> np.ndarray:
    """(nverts, 3) float32 albedo per vertex of the result (the trace stage takes the objects' shadows out of the
    room's light with it): the mesh's from its nearest fit points, the box's the unseen cells' (the upper
    walls', as they reflect here; the top the ceiling's), the lamps' 0."""
    room, st = pb.room, pb.st
    nv, nbv = room.nv, len(room.box_v)
    lvl = np.full(3, 0.5) if sol.level is None else np.asarray(sol.level, np.float64)
    albedo = np.zeros((nverts, 3))
    albedo[:nv] = vertex_albedo(room.V, room.F, pb.pts.P, pb.pts.N, sol.rho[pb.patch], lvl, st.albedo_cell)
    albedo[nv:nv + nbv] = np.clip(lvl * sol.unseen_ratio, *ALBEDO_RANGE)     # the unseen cells' albedo
    if st.ceiling_albedo > 0:            # four vertices per box cell
        albedo[nv:nv + nbv][np.repeat(room.ceiling_cell, 4)] = st.ceiling_albedo
    return np.clip(albedo, 0.0, 1.0).astype(np.float32)
