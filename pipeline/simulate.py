"""The simulate stage: drops of library objects into each room with our own physics (pipeline.physics).

Items: one per (scene, drop), key ``<scene>/drop<NNNN>``. Each writes
``RUN/simulate/<scene>/drop<NNNN>.json`` (a :class:`~pipeline.types.Placement` plus simulation facts);
rejected drops are written too, with their verdict, and counted in ``RUN/simulate/summary.json``
(downstream stages use accepted drops only). A drop rejected for a reason that depends on its draw is
simulated again with a new draw (``simulate.retries``); its file lists the attempts.
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import numpy as np

from pipeline.config import SimulateConfig
from pipeline.errors import InputError, UserError
from pipeline.io import atomic_write_json
from pipeline.runfolder import (DROP_TPATH, PLACEMENT_TPATH, ROOM_PROXY_TPATH, SELECTION_TPATH, SUMMARY_TPATH,
                                file_stamp, list_scenes, load_object_proxy, load_objects, load_scan, load_selection,
                                path, save_placement)
from pipeline.stages import Item, Stage, StageContext
from pipeline.types import Placement

log = logging.getLogger(__name__)


FOCUS_MIN_HALF_WIDTH = 0.25   # m, smallest half-width of a view-focused spawn square
FOCUS_SPREAD = 1.2            # half-width = this x sqrt(objects) x median bounding radius (room to fall apart)
FOCUS_TRIES = 3               # focus cells tried before falling back to the whole-room spawn box
SPAWN_CLEARANCE = 0.02        # m, a view-focused slab starts this far above the seen surface + the largest bound


def body_of(proxy: dict[str, np.ndarray], friction: float):
    """A physics body from an object proxy (meshprep keys: hull_vertices, mass, com, inertia)."""
    from pipeline.physics import Body

    return Body(vertices=np.asarray(proxy["hull_vertices"], float), mass=float(proxy["mass"]),
                com=np.asarray(proxy["com"], float), inertia=np.asarray(proxy["inertia"], float),
                friction=friction)


def simulate(cfg: SimulateConfig, *, scene: str, drop: int, room, up: np.ndarray,
             proxies: dict[int, dict], rng: np.random.Generator, view=None, info=None
             ) -> tuple[Placement, dict]:
    """One drop: sample objects, spawn them above the room and simulate them to rest.

    With ``view`` (a :class:`pipeline.view_spawn.ViewMap` of the kept frames) the spawn box is a square
    above a horizontal surface the kept frames see (sampled by their votes; a few tries, then the whole
    room), so the objects come to rest in view; without it, the published whole-room spawn box.

    Parameters
    ----------
    cfg
        The ``[simulate]`` table.
    room
        Room proxy (``origin``, ``spacing``, ``udf``).
    up
        (3,) world up vector of the scan.
    proxies
        ``{obj_id: object proxy}`` of the library.
    rng
        The drop's own generator.
    info
        :func:`pipeline.physics.drop.room_info` of ``room`` for ``up`` (computed when None).

    Returns
    -------
    placement, facts (simulated seconds, steps)
    """
    from pipeline.physics.drop import DropSettings, room_info, simulate_drop

    ids = np.array(sorted(proxies), np.int32)
    n = cfg.objects_per_drop
    if not cfg.repeat_objects and n > len(ids):
        raise InputError(f"simulate.objects_per_drop = {n} distinct objects but the library has "
                         f"{len(ids)}; set simulate.repeat_objects = true or lower objects_per_drop")
    chosen = rng.choice(ids, size=n, replace=cfg.repeat_objects)
    bodies = [body_of(proxies[int(i)], cfg.friction) for i in chosen]
    st = DropSettings(timestep=cfg.timestep, max_time=cfg.max_time, p_velocity=cfg.p_velocity,
                      friction=cfg.friction, room_thickness=cfg.room_thickness,
                      rest_thickness=cfg.rest_thickness, max_penetration=cfg.max_penetration)
    facts: dict = {}
    r = None
    info = room_info(room, up) if info is None else info
    if view is not None and len(view.score):
        from dataclasses import replace

        from pipeline.view_spawn import focus_bounds, sample_focus

        room_lo, room_hi = info.lo, info.hi    # view.R_w2g is the room frame (info.R_w2g)
        radii = [float(np.max(np.linalg.norm(np.asarray(proxies[int(i)]["hull_vertices"], float)
                                             - np.asarray(proxies[int(i)]["com"], float), axis=1)))
                 for i in chosen]
        half = max(FOCUS_MIN_HALF_WIDTH, FOCUS_SPREAD * np.sqrt(n) * float(np.median(radii)))
        for _ in range(FOCUS_TRIES):
            c = view.centers[sample_focus(view, rng)]
            # the slab's bottom clear, by the largest body, of the highest surface seen under the square
            under = np.all(np.abs(view.centers - c) <= half + 0.5 * view.cell, axis=1)
            lowest = float(view.top[under].max()) + max(radii) + st.room_thickness + SPAWN_CLEARANCE
            bounds, spawn_z = focus_bounds(c, half, room_lo, room_hi, st.spawn_z, lowest)
            r = simulate_drop(bodies, room=room, up=up, settings=replace(st, spawn_xy=1.0, spawn_z=spawn_z),
                              rng=rng, spawn_bounds=bounds, info=info)
            if r.verdict != "rejected:spawn":
                facts = {"focus_xy": [round(float(v), 6) for v in c], "focus_half_width": round(half, 6)}
                break
            r = None
    if r is None:
        r = simulate_drop(bodies, room=room, up=up, settings=st, rng=rng, info=info)
    pl = Placement(scene=scene, drop=drop, obj_ids=chosen.astype(np.int32), R_m2w=r.R_m2w, t_m2w=r.t_m2w,
                   at_rest=r.at_rest, max_penetration=r.max_penetration, verdict=r.verdict)
    return pl, {"seconds": round(r.sim_time, 6), "steps": r.steps, **facts}


# Verdicts that depend on the draw (which objects, where they spawn, how they fall), so that another draw
# can be accepted. "rejected:spawn" is not among them: the spawn sampler already tried hundreds of poses
# per body in the view-focused squares and the whole room; failing means the objects do not fit the room's
# spawn box, which another draw does not change and the user must see.
RETRIED_VERDICTS = ("rejected:never-settled", "rejected:left-room", "rejected:penetration")


def simulate_with_retries(cfg: SimulateConfig, rng_of, **kwargs) -> tuple[Placement, dict]:
    """:func:`simulate`, again with a fresh draw while the verdict is one of :data:`RETRIED_VERDICTS`, up
    to ``cfg.retries`` more times.

    Parameters
    ----------
    rng_of : callable
        ``attempt -> numpy.random.Generator``: attempt 0 is the drop's own generator, each later attempt
        gets its own (deterministic: the same seed gives the same attempts).
    **kwargs
        The other arguments of :func:`simulate`.

    Returns
    -------
    placement, facts
        The last attempt's; ``facts["attempt"]`` is its index and ``facts["attempts"]`` lists every
        attempt's verdict and simulated seconds.
    """
    attempts = []
    for k in range(cfg.retries + 1):
        pl, facts = simulate(cfg, rng=rng_of(k), **kwargs)
        attempts.append({"verdict": pl.verdict, "seconds": facts["seconds"]})
        if pl.verdict not in RETRIED_VERDICTS:
            break
    return pl, {**facts, "attempt": len(attempts) - 1, "attempts": attempts}


def plan(ctx: StageContext) -> list[Item]:
    return [Item(key=DROP_TPATH.format(scene=s, drop=d), data={"scene": s, "drop": d})
            for s in list_scenes(ctx.run_dir) for d in range(ctx.cfg.simulate.drops)]


@functools.lru_cache(maxsize=2)
def _cached_room(stamp: tuple[str, int, int], up: tuple[float, float, float]):
    """The :class:`~pipeline.physics.types.Room` of a room proxy file (its exact-distance mesh built) and
    its :class:`~pipeline.physics.drop.RoomInfo`, once per worker process and room file (loading the
    grid, building the mesh's BVH and finding the surface cost ~0.5 s, about a whole drop)."""
    from pipeline.io import load_npz
    from pipeline.physics.drop import room_info
    from pipeline.physics.io import room_from_arrays

    room = room_from_arrays(load_npz(stamp[0]))
    return room, room_info(room, np.array(up))


@functools.lru_cache(maxsize=2)
def _cached_view_map(run_dir: str, scene: str, selection: tuple[str, int, int],
                     room_stamp: tuple[str, int, int], up: tuple[float, float, float]):
    """:func:`_view_map` once per worker process, scene and selection file."""
    room, info = _cached_room(room_stamp, up)
    return _view_map(Path(run_dir), load_scan(run_dir, scene), room, info.R_w2g)


def run_item(ctx: StageContext, item: Item) -> dict:
    scene, drop = item.data["scene"], int(item.data["drop"])
    scan = load_scan(ctx.run_dir, scene)
    proxy = path(ctx.run_dir, ROOM_PROXY_TPATH, scene=scene)
    if not proxy.is_file():
        raise UserError(f"{proxy}: room proxy is missing; run the 'prep' stage first")
    up = tuple(float(v) for v in np.asarray(scan.up_w, float))
    room, info = _cached_room(file_stamp(proxy), up)
    selection = file_stamp(path(ctx.run_dir, SELECTION_TPATH, scene=scene))
    view = _cached_view_map(str(ctx.run_dir), scene, selection, file_stamp(proxy), up)
    proxies = {o.obj_id: load_object_proxy(ctx.run_dir, o.obj_id) for o in load_objects(ctx.run_dir)}
    if not proxies:
        raise InputError("the object library is empty; give objects.paths in the config")

    def rng_of(attempt: int) -> np.random.Generator:
        from pipeline.seeding import item_rng

        return ctx.rng(item) if attempt == 0 else item_rng(ctx.cfg.run.seed, ctx.stage, item.key,
                                                          f"attempt{attempt}")

    pl, facts = simulate_with_retries(ctx.cfg.simulate, rng_of, scene=scene, drop=drop, room=room, up=scan.up_w,
                                      proxies=proxies, view=view, info=info)
    save_placement(path(ctx.run_dir, PLACEMENT_TPATH, scene=scene, drop=drop), pl, extra=facts)
    if facts["attempt"]:
        log.info("%s: %s after %d attempts (%s)", item.key, pl.verdict, facts["attempt"] + 1,
                 ", ".join(a["verdict"] for a in facts["attempts"][:-1]))
    elif pl.verdict != "accepted":
        log.info("%s: %s", item.key, pl.verdict)
    return {"verdict": pl.verdict, "max_penetration": pl.max_penetration,
            "asleep": int(np.sum(pl.at_rest)), "objects": len(pl.obj_ids), **facts}


def _view_map(run_dir: Path, scan, room, R_w2g: np.ndarray | None = None):
    """Votes of the scene's kept frames for spawn cells in the room frame ``R_w2g`` of
    :func:`pipeline.physics.drop.room_frame` (computed when None; None when nothing was selected or
    seen)."""
    from pipeline.physics.collide import grid_distance
    from pipeline.physics.drop import room_frame
    from pipeline.view_spawn import view_map

    try:
        frames = load_selection(run_dir, scan.name)
    except UserError:
        return None
    vm = view_map(scan, frames, room_frame(room, scan.up_w) if R_w2g is None else R_w2g,
                  surface_distance=lambda p: grid_distance(room.origin, room.spacing, room.udf, p,
                                                           gradient=False)[0])
    if not len(vm.score):
        log.warning("%s: no kept frame sees an upward-facing surface; drops spawn over the whole room",
                    scan.name)
        return None
    return vm


def finish(ctx: StageContext, results: dict[str, dict]) -> None:
    """Count accepted and rejected drops (by reason) in RUN/simulate/summary.json."""
    counts: dict[str, int] = {}
    tried: dict[str, int] = {}    # verdicts of every attempt, retried ones included
    for r in results.values():
        counts[r["verdict"]] = counts.get(r["verdict"], 0) + 1
        for a in r.get("attempts", [{"verdict": r["verdict"]}]):
            tried[a["verdict"]] = tried.get(a["verdict"], 0) + 1
    total = sum(counts.values())
    atomic_write_json(path(ctx.run_dir, SUMMARY_TPATH, stage=ctx.stage),
                      {"drops": total, "verdicts": counts,
                       "accepted_share": (counts.get("accepted", 0) / total) if total else 0.0,
                       "attempts": sum(tried.values()), "attempt_verdicts": tried})
    rejected = total - counts.get("accepted", 0)
    if rejected:
        log.warning("simulate: %d of %d drops rejected (%s)", rejected, total,
                    ", ".join(f"{k}: {v}" for k, v in sorted(counts.items()) if k != "accepted"))


STAGE = Stage("simulate", plan, run_item, finish)
