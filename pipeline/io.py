"""Atomic file output.

Every file a stage writes goes through these helpers: the bytes go to a temporary file in the same
folder, which is then renamed over the target (``os.replace`` is atomic on POSIX). A run killed at any
moment, SIGKILL included, leaves either the old file, the complete new one, or a stray ``*.tmp-*``
that :func:`remove_stale_temps` deletes on resume; never a truncated output.

Outputs are deterministic: JSON is written with sorted keys and fixed float formatting; NPZ files are
written without timestamps; PNGs without metadata. Same inputs, same bytes.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

# One atomic writer, one JSON and one NPZ encoding for the whole project: meshprep's (meshprep is
# standalone and cannot import these from here; the pipeline can import them from there).
from meshprep.io import TMP_MARK, atomic_write_bytes, dumps_json, npz_bytes

__all__ = ["TMP_MARK", "atomic_write_bytes", "dumps_json", "npz_bytes", "atomic_write_json", "read_json",
           "atomic_save_npz", "load_npz", "encode_image", "atomic_write_image", "remove_stale_temps"]



def atomic_write_json(path: str | Path, obj: Any, *, indent: int | None = 2) -> Path:
    """Write ``obj`` as deterministic JSON, atomically."""
    return atomic_write_bytes(path, dumps_json(obj, indent=indent).encode("utf-8"))


def read_json(path: str | Path) -> Any:
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def atomic_save_npz(path: str | Path, **arrays: np.ndarray) -> Path:
    """Save arrays to an NPZ file deterministically and atomically."""
    return atomic_write_bytes(path, npz_bytes(arrays))


def load_npz(path: str | Path) -> dict[str, np.ndarray]:
    """Load every array of an NPZ file into a dict (the file is closed on return)."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def encode_image(path: str | Path, image: np.ndarray, *, jpeg_quality: int = 95) -> bytes:
    """Encode an image for ``path``'s extension (.png, .jpg/.jpeg, .exr) with OpenCV.

    ``image`` is RGB (H, W, 3) or single-channel (H, W); uint8 or uint16 for PNG. No metadata is
    written, so equal pixels give equal bytes.
    """
    import cv2

    ext = Path(path).suffix.lower()
    img = image
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[..., ::-1]  # RGB -> BGR for OpenCV
    params: list[int] = []
    if ext in (".jpg", ".jpeg"):
        params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality]
    elif ext == ".png":
        params = [cv2.IMWRITE_PNG_COMPRESSION, 3]
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(img), params)
    if not ok:
        raise ValueError(f"could not encode {img.dtype} image of shape {image.shape} as {ext}")
    return buf.tobytes()


def atomic_write_image(path: str | Path, image: np.ndarray, *, jpeg_quality: int = 95) -> Path:
    """Write an RGB or single-channel image atomically; format from the extension."""
    return atomic_write_bytes(path, encode_image(path, image, jpeg_quality=jpeg_quality))


def remove_stale_temps(root: str | Path) -> int:
    """Delete temporary files left by a killed run under ``root``; return how many."""
    n = 0
    root = Path(root)
    if not root.exists():
        return 0
    for p in root.rglob(f"*{TMP_MARK}*"):
        if p.is_file():
            p.unlink(missing_ok=True)
            n += 1
    return n
