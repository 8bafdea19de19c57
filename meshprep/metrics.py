"""Surface deviation (sampled symmetric Hausdorff distance) between two triangle meshes.

Points are drawn uniformly by area on each surface (seeded), and their exact point-to-triangle
distances to the other surface are computed with Open3D's RaycastingScene (~0.25 M queries/s per
core on a 175k-triangle room).
"""

from __future__ import annotations

import numpy as np

from meshprep import constants


# Open3D 0.19's __init__ imports two parts nothing here uses: open3d.ml, whose datasets import scikit-learn, and its
# plotly viewer (dash, plotly, pandas). They were 1-2 of the ~2.5 s `import open3d` took in each process that
# reads a mesh or fuses depth (4 per 7-Scenes run). open3d_module() lets them load on first use instead
_LAZY_OPEN3D = {"open3d.ml": (), "open3d.visualization.draw_plotly": ("draw_plotly", "draw_plotly_server")}


def _lazy_module(name: str, functions: tuple[str, ...]):
    """A stand-in for module ``name`` while ``open3d`` is first imported: its ``functions``, called, import the
    real module (by then the stand-in is gone from ``sys.modules``), put its functions in their place on the
    parent module and hand on the call."""
    import importlib
    import sys
    import types

    mod = types.ModuleType(name, f"stand-in for {name} during `import open3d` (meshprep.metrics.open3d_module)")

    def forward(fn: str):
        def call(*args, **kwargs):
            real = importlib.import_module(name)
            parent = sys.modules[name.rpartition(".")[0]]
            for f in functions:
                setattr(parent, f, getattr(real, f))
            return getattr(real, fn)(*args, **kwargs)

        call.__name__ = call.__qualname__ = fn
        return call

    for fn in functions:
        setattr(mod, fn, forward(fn))
    return mod


def open3d_module():
    """Import Open3D: its "built with CUDA support, but no suitable CUDA devices found" ImportWarning silenced,
    ``OMP_WAIT_POLICY`` defaulting to ``PASSIVE`` before the first import (a value the user set wins: Open3D's
    OpenMP threads otherwise spin while waiting, and on a small machine shared with other jobs that made TSDF
    fusion of the 7-Scenes sample 10-20x slower, 98 s instead of 5 s wall at load 10 on 2 cores; it only takes
    effect when no OpenMP runtime is loaded yet), and without :data:`_LAZY_OPEN3D`'s modules: ``open3d.ml`` is
    there after ``import open3d.ml``, the plotly viewer's functions import it when called."""
    import os
    import sys
    import warnings

    if "open3d" in sys.modules:
        return sys.modules["open3d"]
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    lazy = {name: _lazy_module(name, fns) for name, fns in _LAZY_OPEN3D.items() if name not in sys.modules}
    sys.modules.update(lazy)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*CUDA", category=ImportWarning)
            import open3d
    finally:
        for name, mod in lazy.items():
            if sys.modules.get(name) is mod:
                del sys.modules[name]
    return open3d


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, *, seed: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniformly distributed by area on a triangle mesh.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    n : int
    seed : int
        Seed of the generator (same seed, same points).

    Returns
    -------
    points : (n, 3) float64
    face_index : (n,) int64, the face each point lies on
    """
    rng = np.random.default_rng(seed)
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = area.sum()
    if not np.isfinite(total) or total <= 0:
        raise ValueError("cannot sample a surface with zero or non-finite area")
    cdf = np.cumsum(area)
    idx = np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), len(f) - 1)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w0, w1, w2 = 1 - s, s * (1 - r2), s * r2
    pts = w0[:, None] * a[idx] + w1[:, None] * b[idx] + w2[:, None] * c[idx]
    return pts, idx


def distance_to_surface(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Exact unsigned distance (P,) float64 from each point to the nearest triangle.

    Coordinates are shifted to the mesh's bounding-box centre before the float32 conversion Open3D
    needs, so meshes far from the origin keep their precision.
    """
    o3d = open3d_module()
    v = np.asarray(vertices, dtype=np.float64)
    c = 0.5 * (v.min(axis=0) + v.max(axis=0))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(np.ascontiguousarray(v - c, dtype=np.float32),
                        np.ascontiguousarray(faces, dtype=np.uint32))
    q = np.ascontiguousarray(np.asarray(points, dtype=np.float64) - c, dtype=np.float32)
    out = np.empty(len(q), dtype=np.float64)
    step = 1 << 20
    for i in range(0, len(q), step):
        out[i:i + step] = scene.compute_distance(q[i:i + step]).numpy()
    return out


def surface_deviation(vertices_a: np.ndarray, faces_a: np.ndarray, vertices_b: np.ndarray,
                      faces_b: np.ndarray, *, samples: int = constants.DEVIATION_SAMPLES,
                      seed: int = 0) -> dict[str, float]:
    """Sampled symmetric Hausdorff statistics between surfaces A and B, in mesh units.

    ``samples`` points on each surface; distances A->B and B->A are pooled for ``mean`` and
    ``p95``; ``max`` is the sampled Hausdorff distance. ``diagonal`` is A's bounding-box diagonal
    (divide by it for the relative figures).
    """
    pa, _ = sample_surface(vertices_a, faces_a, samples, seed=seed)
    pb, _ = sample_surface(vertices_b, faces_b, samples, seed=seed + 1)
    dab = distance_to_surface(vertices_b, faces_b, pa)
    dba = distance_to_surface(vertices_a, faces_a, pb)
    d = np.concatenate([dab, dba])
    va = np.asarray(vertices_a, dtype=np.float64)
    return {"mean": float(d.mean()), "p95": float(np.percentile(d, 95)), "max": float(d.max()),
            "a_to_b_max": float(dab.max()), "b_to_a_max": float(dba.max()),
            "diagonal": float(np.linalg.norm(va.max(0) - va.min(0)))}
