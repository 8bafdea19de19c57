"""Procedural, tileable textures: floor tiles, wood, painted walls, cardboard.

Every texture is an (N, N, 3) uint8 sRGB image that tiles seamlessly (all noise lives on a periodic
lattice), so the renderer can repeat it with metre-based UVs. Each is a pure function of a seeded
generator.
"""

from __future__ import annotations

import numpy as np

from pipeline.color import encode_u8, srgb_to_linear


def spectral_noise(rng: np.random.Generator, size: int, fmax: float, fmin: float = 1.0,
                   beta: float = 1.0) -> np.ndarray:
    """Tileable noise in [0, 1] with a 1/f^beta spectrum between ``fmin`` and ``fmax`` cycles per tile.

    Built in the Fourier domain (random phases, inverse real FFT), so it is periodic by construction.

    Returns
    -------
    (size, size) float32
    """
    fy = np.fft.fftfreq(size, 1.0 / size)[:, None]
    fx = np.fft.rfftfreq(size, 1.0 / size)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    amp = np.where((f >= fmin) & (f <= fmax), 1.0 / np.maximum(f, 1.0) ** beta, 0.0)
    phase = rng.random(f.shape) * 2 * np.pi
    spec = amp * np.exp(1j * phase)
    out = np.fft.irfft2(spec, s=(size, size))
    lo, hi = float(out.min()), float(out.max())
    return ((out - lo) / max(hi - lo, 1e-12)).astype(np.float32)


def fractal_noise(rng: np.random.Generator, size: int, octaves: tuple[int, ...] = (4, 8, 16, 32)) -> np.ndarray:
    """Multi-octave tileable noise with features from ``min(octaves)/2`` to ``max(octaves)`` cycles per tile.

    Returns
    -------
    (size, size) float32 in [0, 1]
    """
    return spectral_noise(rng, size, fmax=float(max(octaves)), fmin=max(1.0, min(octaves) / 2.0), beta=1.0)


def tiles(rng: np.random.Generator, size: int = 256, n_tiles: int = 2,
          base: tuple[float, float, float] = (0.55, 0.52, 0.47)) -> np.ndarray:
    """Square floor tiles with grout lines and per-tile colour variation; (size, size, 3) uint8 sRGB."""
    t = size // n_tiles
    ij = np.arange(size)
    tile_idx = (ij // t)
    var = 1.0 + 0.12 * (rng.random((n_tiles, n_tiles, 3)) - 0.5) + 0.10 * (rng.random((n_tiles, n_tiles, 1)) - 0.5)
    col = np.asarray(base, np.float32)[None, None, :] * var[tile_idx[:, None], tile_idx[None, :]]
    speck = fractal_noise(rng, size, (8, 32, 64))[..., None]
    col = col * (0.85 + 0.3 * speck)
    grout_w = max(1, size // 64)
    local = ij % t
    grout = (local[:, None] < grout_w) | (local[None, :] < grout_w)
    col[grout] = np.asarray([0.18, 0.17, 0.16], np.float32)
    return encode_u8(col)


def wood(rng: np.random.Generator, size: int = 256,
         base: tuple[float, float, float] = (0.40, 0.22, 0.10)) -> np.ndarray:
    """Wood-like grain: rings along u distorted by periodic noise; (size, size, 3) uint8 sRGB."""
    u = np.arange(size, dtype=np.float32) / size
    warp = fractal_noise(rng, size, (2, 4, 8))
    rings = int(rng.integers(6, 11))
    phase = 2 * np.pi * (rings * u[:, None] + 1.5 * warp)
    grain = 0.5 + 0.5 * np.sin(phase)
    fine = fractal_noise(rng, size, (16, 64, 128))
    tone = 0.65 + 0.35 * grain ** 3 + 0.15 * (fine - 0.5)
    return encode_u8(np.asarray(base, np.float32)[None, None, :] * tone[..., None])


def paint(rng: np.random.Generator, size: int = 256,
          base: tuple[float, float, float] = (0.62, 0.60, 0.55)) -> np.ndarray:
    """Painted plaster: low-contrast mottling and roller stipple; (size, size, 3) uint8 sRGB."""
    mottle = fractal_noise(rng, size, (2, 4, 8))
    stipple = fractal_noise(rng, size, (32, 64, 128))
    tone = 0.90 + 0.12 * (mottle - 0.5) + 0.10 * (stipple - 0.5)
    return encode_u8(np.asarray(base, np.float32)[None, None, :] * tone[..., None])


def cardboard(rng: np.random.Generator, size: int = 256,
              base: tuple[float, float, float] = (0.45, 0.30, 0.15)) -> np.ndarray:
    """Corrugated cardboard with a printed band and label; (size, size, 3) uint8 sRGB."""
    v = np.arange(size, dtype=np.float32) / size
    fibre = fractal_noise(rng, size, (16, 64, 128))
    corr = 0.5 + 0.5 * np.sin(2 * np.pi * 24 * v)[None, :]
    tone = 0.85 + 0.15 * fibre + 0.05 * corr
    col = np.asarray(base, np.float32)[None, None, :] * tone[..., None]
    band = (np.abs(v - 0.5) < 0.06)
    col[band, :] = col[band, :] * np.asarray([0.3, 0.3, 0.9], np.float32)
    lab = slice(size // 5, size // 5 + size // 6)
    col[lab, size // 8: size // 2] = np.asarray([0.85, 0.85, 0.8], np.float32)
    col[lab, size // 8: size // 2] *= (0.9 + 0.1 * fibre[lab, size // 8: size // 2])[..., None]
    return encode_u8(col)


def fabric(rng: np.random.Generator, size: int = 256,
           base: tuple[float, float, float] = (0.12, 0.20, 0.35)) -> np.ndarray:
    """Woven fabric: fine crossing threads; (size, size, 3) uint8 sRGB."""
    ij = np.arange(size, dtype=np.float32) / size
    weave = 0.5 + 0.25 * np.sin(2 * np.pi * 64 * ij)[:, None] + 0.25 * np.sin(2 * np.pi * 64 * ij)[None, :]
    n = fractal_noise(rng, size, (8, 32))
    tone = 0.75 + 0.25 * weave + 0.1 * (n - 0.5)
    return encode_u8(np.asarray(base, np.float32)[None, None, :] * tone[..., None])


def plain(rng: np.random.Generator, size: int = 8, base: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
    """A flat colour (used for emitters); ``rng`` is accepted for a uniform signature."""
    return encode_u8(np.broadcast_to(np.asarray(base, np.float32), (size, size, 3)).copy())


KINDS = {"tiles": tiles, "wood": wood, "paint": paint, "cardboard": cardboard, "fabric": fabric, "plain": plain}


def make_texture(kind: str, rng: np.random.Generator, base: tuple[float, float, float], size: int = 256) -> np.ndarray:
    """Texture of ``kind`` (one of :data:`KINDS`) around linear colour ``base``; (size, size, 3) uint8 sRGB."""
    if kind == "plain":
        return plain(rng, 8, base)
    return KINDS[kind](rng, size, base=base)


def sample_bilinear(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample a tiling texture at UVs (OpenGL: v up, repeat wrap), bilinear; returns (N, 3) float32 linear.

    Parameters
    ----------
    texture : (H, W, 3) uint8 sRGB
    uv : (N, 2) float, texture coordinates; integer steps repeat the texture
    """
    lin = srgb_to_linear(texture)
    h, w = lin.shape[:2]
    x = (uv[:, 0] % 1.0) * w - 0.5
    y = (1.0 - uv[:, 1] % 1.0) * h - 0.5
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx = (x - x0)[:, None].astype(np.float32)
    fy = (y - y0)[:, None].astype(np.float32)
    x0m, x1m = x0 % w, (x0 + 1) % w
    y0m, y1m = y0 % h, (y0 + 1) % h
    top = lin[y0m, x0m] * (1 - fx) + lin[y0m, x1m] * fx
    bot = lin[y1m, x0m] * (1 - fx) + lin[y1m, x1m] * fx
    return (top * (1 - fy) + bot * fy).astype(np.float32)
