"""The same scene in MuJoCo, as a reference for tests and the benchmark (``mujoco`` is a test and
benchmark dependency only; it is imported inside these functions).

Bodies keep our body frames (com, principal axes), so poses compare directly: boxes become MuJoCo boxes,
spheres spheres, other hulls convex meshes; static planes become MuJoCo planes. No room fields.
"""

from __future__ import annotations

import numpy as np

from pipeline.physics.types import KIND_SPHERE, Model, State


def _f(a) -> str:
    return " ".join(f"{x:.10g}" for x in np.ravel(a))


def mjcf(model: Model, state: State, *, boxes: dict[int, np.ndarray] | None = None,
         timestep: float = 0.002) -> str:
    """MJCF text of ``model`` at ``state``.

    Parameters
    ----------
    boxes
        ``{body: half_extents in the object-model frame}`` for bodies that are boxes (exact box geoms).
    timestep
        MuJoCo's step, s.
    """
    boxes = boxes or {}
    opt = model.opt
    g = np.asarray(opt.gravity, float)
    tc = max(opt.solref[0], 2 * timestep)
    lines = [f'<mujoco><option timestep="{timestep}" gravity="{_f(g)}" cone="elliptic" '
             f'impratio="{opt.impratio}"/>',
             f'<default><geom solref="{tc} {opt.solref[1]}" solimp="{_f(opt.solimp)} 0.5 2" '
             f'condim="3"/></default>', "<asset>"]
    for i in range(model.nbody):
        if model.body_kind[i] != KIND_SPHERE and i not in boxes:
            lines.append(f'<mesh name="m{i}" vertex="{_f(model.body_verts[i, :model.body_nvert[i]])}"/>')
    lines.append("</asset><worldbody>")
    for p, pl in enumerate(model.plane):
        n = pl[:3]
        # MuJoCo planes have +z normals: rotate z onto n
        z = np.array([0.0, 0, 1])
        ax = np.cross(z, n)
        s = np.linalg.norm(ax)
        ang = np.arctan2(s, n @ z)
        q = np.r_[np.cos(ang / 2), (ax / s if s > 1e-12 else np.zeros(3)) * np.sin(ang / 2)]
        lines.append(f'<geom name="plane{p}" type="plane" size="0 0 1" pos="{_f(n * pl[3])}" quat="{_f(q)}" '
                     f'friction="{model.opt.friction} 0.005 0.0001"/>')
    for i in range(model.nbody):
        fr = f'friction="{model.body_friction[i]} 0.005 0.0001"'
        lines.append(f'<body name="b{i}" pos="{_f(state.pos[i])}" quat="{_f(state.quat[i])}"><freejoint/>'
                     f'<inertial pos="0 0 0" mass="{model.body_mass[i]:.10g}" '
                     f'diaginertia="{_f(model.body_inertia[i])}"/>')
        if model.body_kind[i] == KIND_SPHERE:
            lines.append(f'<geom type="sphere" size="{model.body_radius[i]:.10g}" {fr} mass="0"/>')
        elif i in boxes:
            h = np.abs(model.body_R_m2b[i]) @ np.asarray(boxes[i], float)
            lines.append(f'<geom type="box" size="{_f(h)}" {fr}/>')
        else:
            lines.append(f'<geom type="mesh" mesh="m{i}" {fr}/>')
        lines.append("</body>")
    lines.append("</worldbody></mujoco>")
    return "\n".join(lines)


def simulate_mujoco(model: Model, state: State, seconds: float, *, boxes: dict[int, np.ndarray] | None = None,
                    timestep: float = 0.002) -> tuple[np.ndarray, np.ndarray, float]:
    """Run the scene in MuJoCo for ``seconds``; return com positions (B,3), quaternions (B,4 wxyz) and
    the wall seconds MuJoCo's stepping took."""
    import time

    import mujoco

    m = mujoco.MjModel.from_xml_string(mjcf(model, state, boxes=boxes, timestep=timestep))
    # our body frames are principal frames already: keep MuJoCo's body inertial frame equal to them
    d = mujoco.MjData(m)
    n = int(round(seconds / timestep))
    t0 = time.perf_counter()
    for _ in range(n):
        mujoco.mj_step(m, d)
    wall = time.perf_counter() - t0
    q = d.qpos.reshape(model.nbody, 7)
    return q[:, :3].copy(), q[:, 3:].copy(), wall
