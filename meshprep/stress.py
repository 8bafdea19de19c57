"""A generated stress corpus of broken meshes (nothing downloaded), for tests and benchmarks.

Each generator returns ``(vertices (V,3) float64, faces (F,3) int32)``; :func:`write_corpus` writes
them (plus the unreadable-file cases) to a folder. ``expect`` tells what repair should make of each:
``object`` (watertight and manifold), ``scan`` (manifold, open) or ``error:N`` (exit code N).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from meshprep.creation import box, sphere

Mesh = tuple[np.ndarray, np.ndarray]


def _ball(n: int = 24) -> Mesh:
    return sphere(1.0, stacks=n, slices=2 * n)


def _drop_faces_near(v: np.ndarray, f: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    cen = v[f].mean(axis=1)
    keep = np.ones(len(f), dtype=bool)
    for c, r in zip(centres, radii):
        keep &= np.linalg.norm(cen - c, axis=1) > r
    return f[keep]


def holes(seed: int = 0) -> Mesh:
    """A sphere with holes from one face to a wide opening."""
    v, f = _ball(32)
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(6, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return v, _drop_faces_near(v, f, d, np.array([0.03, 0.08, 0.15, 0.25, 0.4, 0.6]))


def flipped(seed: int = 0) -> Mesh:
    """A sphere with 15 % of its faces flipped."""
    v, f = _ball()
    rng = np.random.default_rng(seed)
    f = f.copy()
    sel = rng.random(len(f)) < 0.15
    f[sel] = f[sel][:, ::-1]
    return v, f


def inside_out() -> Mesh:
    """A closed sphere with every face flipped (negative volume)."""
    v, f = _ball()
    return v, f[:, ::-1].copy()


def nonmanifold_fan() -> Mesh:
    """A sphere with three extra fins hinged on one of its edges (an edge with 5 faces)."""
    v, f = _ball()
    a, b = f[0, 0], f[0, 1]
    mid = 0.5 * (v[a] + v[b])
    extra = mid + np.array([[0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]])
    n = len(v)
    return np.vstack([v, extra]), np.vstack([f, [[a, b, n], [a, b, n + 1], [b, a, n + 2]]]).astype(np.int32)


def bowtie() -> Mesh:
    """Two closed boxes touching at a single shared vertex (a non-manifold vertex)."""
    v1, f1 = box()
    v2, f2 = box()
    v1 = v1 + 0.5          # corner (0,0,0) of box 1 is vertex 0 (-0.5,-0.5,-0.5) + 0.5
    v2 = v2 - 0.5          # corner (0,0,0) of box 2 is vertex 7 (+0.5,+0.5,+0.5) - 0.5
    f2 = np.where(f2 == 7, 0, f2 + 8)
    return np.vstack([v1, v2]), np.vstack([f1, f2]).astype(np.int32)


def bowtie_open() -> Mesh:
    """Two triangles sharing only a vertex (an open bow-tie)."""
    v = np.array([[0, 0, 0], [1, 0.2, 0], [1, -0.2, 0], [-1, 0.2, 0], [-1, -0.2, 0]], dtype=np.float64)
    return v, np.array([[0, 2, 1], [0, 3, 4]], dtype=np.int32)


def duplicates() -> Mesh:
    """A triangle soup (every corner its own vertex) with 10 % of the faces repeated."""
    v, f = _ball()
    soup_v = v[f.reshape(-1)]
    soup_f = np.arange(len(soup_v)).reshape(-1, 3)
    return soup_v, np.vstack([soup_f, soup_f[::10]]).astype(np.int32)


def degenerate() -> Mesh:
    """A sphere plus zero-area faces (repeated index, collinear corners) and split slivers."""
    v, f = _ball()
    n = len(v)
    line = np.array([[2, 0, 0], [2.5, 0, 0], [3, 0, 0]])
    # Sliver: split face 0 at a point 1e-9 off its first edge's midpoint.
    a, b, c = f[0]
    p = 0.5 * (v[a] + v[b]) + 1e-9 * (v[c] - 0.5 * (v[a] + v[b]))
    vv = np.vstack([v, line, p[None]])
    ff = np.vstack([f[1:], [[a, n + 3, c], [n + 3, b, c], [a, b, n + 3]],
                    [[0, 0, 1], [5, 6, 5], [n, n + 1, n + 2]]])
    return vv, ff.astype(np.int32)


def non_finite() -> Mesh:
    """A sphere with NaN and inf coordinates in three vertices."""
    v, f = _ball()
    v = v.copy()
    v[5, 0] = np.nan
    v[40, 1] = np.inf
    v[77, 2] = -np.inf
    return v, f


def isolated() -> Mesh:
    """A sphere with 100 unreferenced vertices."""
    v, f = _ball()
    extra = np.random.default_rng(0).uniform(-2, 2, size=(100, 3))
    return np.vstack([v, extra]), f


def junk(seed: int = 0) -> Mesh:
    """A sphere with 50 floating specks (single triangles and tiny tetrahedra) around it."""
    v, f = _ball()
    rng = np.random.default_rng(seed)
    vs, fs = [v], [f]
    n = len(v)
    for _ in range(50):
        c = rng.uniform(-2, 2, 3)
        vs.append(c + 0.005 * rng.normal(size=(3, 3)))
        fs.append(np.array([[n, n + 1, n + 2]]))
        n += 3
    return np.vstack(vs), np.vstack(fs).astype(np.int32)


def self_intersecting() -> Mesh:
    """Two closed spheres that overlap (each manifold, together self-intersecting)."""
    v, f = _ball()
    return np.vstack([v, v + [0.8, 0, 0]]), np.vstack([f, f + len(v)]).astype(np.int32)


def single_triangle() -> Mesh:
    """One triangle."""
    return np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float64), np.array([[0, 1, 2]], np.int32)


def far_away() -> Mesh:
    """A unit sphere with holes centred at (1e6, 1e6, 1e6)."""
    v, f = holes()
    return v + 1e6, f


def terrain(n: int = 200, *, seed: int = 0, defects: bool = True) -> Mesh:
    """An open height field (2 (n-1)^2 faces) like a scan patch, with holes and defects.

    Defects (when asked): small and large holes, a few flipped faces, duplicate faces, specks.
    """
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(0, 4, n), np.linspace(0, 4, n), indexing="ij")
    z = 0.2 * np.sin(1.5 * x) * np.cos(1.1 * y) + 0.003 * rng.normal(size=x.shape)
    v = np.stack([x, y, z], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (i * n + j).reshape(-1)
    f = np.concatenate([np.stack([a, a + n, a + 1], -1), np.stack([a + 1, a + n, a + n + 1], -1)])
    if not defects:
        return v, f.astype(np.int32)
    cen = v[f].mean(axis=1)
    k = 20
    hc = np.column_stack([rng.uniform(0.3, 3.7, (k, 2)), np.zeros(k)])
    hr = np.geomspace(0.01, 0.3, k)
    keep = np.ones(len(f), dtype=bool)
    for c, r in zip(hc, hr):
        keep &= np.linalg.norm((cen - c)[:, :2], axis=1) > r
    f = f[keep]
    flip = rng.random(len(f)) < 0.001
    f[flip] = f[flip][:, ::-1]
    f = np.vstack([f, f[:: max(len(f) // 500, 1)]])
    nv = len(v)
    specks = rng.uniform(0, 4, (30, 3)) + 0.01 * rng.normal(size=(30, 3))
    sv = (specks[:, None, :] + 0.004 * rng.normal(size=(30, 3, 3))).reshape(-1, 3)
    sf = nv + np.arange(90).reshape(-1, 3)
    return np.vstack([v, sv]), np.vstack([f, sf]).astype(np.int32)


def generators() -> dict[str, tuple[Callable[[], Mesh], str]]:
    """Name -> (generator, expected repair outcome: 'object' or 'scan')."""
    return {
        "holes": (holes, "object"), "flipped": (flipped, "object"), "inside_out": (inside_out, "object"),
        "nonmanifold_fan": (nonmanifold_fan, "object"), "bowtie": (bowtie, "object"),
        "bowtie_open": (bowtie_open, "scan"), "duplicates": (duplicates, "object"),
        "degenerate": (degenerate, "object"), "non_finite": (non_finite, "object"),
        "isolated": (isolated, "object"), "junk": (junk, "object"),
        "self_intersecting": (self_intersecting, "object"), "single_triangle": (single_triangle, "scan"),
        "far_away": (far_away, "object"), "terrain": (lambda: terrain(120), "scan"),
    }


def write_mesh(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Write arrays as a mesh file (format from the extension) with PyMeshLab."""
    from meshprep.io import meshset_from_arrays

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    meshset_from_arrays(vertices, faces).save_current_mesh(str(p))
    return p


def write_corpus(folder: str | Path) -> dict[str, tuple[Path, str]]:
    """Write every case to ``folder``; returns name -> (path, expected outcome).

    Expected outcomes: 'object', 'scan', or 'error:2' (unreadable input).
    """
    out: dict[str, tuple[Path, str]] = {}
    folder = Path(folder)
    for name, (gen, expect) in generators().items():
        v, f = gen()
        out[name] = (write_mesh(folder / f"{name}.ply", v, f), expect)
    empty = folder / "empty.ply"
    empty.write_bytes(b"")
    out["empty"] = (empty, "error:2")
    wrong = folder / "holes.xyzw"
    wrong.write_bytes((folder / "holes.ply").read_bytes())
    out["wrong_extension"] = (wrong, "error:2")
    data = (folder / "holes.ply").read_bytes()
    trunc = folder / "truncated.ply"
    trunc.write_bytes(data[: len(data) // 2])
    out["truncated"] = (trunc, "error:2")
    garbage = folder / "garbage.obj"
    garbage.write_bytes(bytes(range(256)) * 10)
    out["garbage_obj"] = (garbage, "error:any")
    return out
