"""Which layout a scan folder is in."""

from __future__ import annotations

from pathlib import Path

from pipeline.errors import InputError
from pipeline.scanformats import bop, rscan, scannet, sevenscenes, transforms

# Checked in this order: the most specific markers first (3RScan frames look like 7-Scenes frames).
READERS = {"transforms": transforms, "bop": bop, "scannet": scannet, "3rscan": rscan, "7scenes": sevenscenes}

HINTS = ("transforms.json (posed images)", "rgb/ + depth/ + scene_camera.json (BOP scene)",
         "color/ + depth/ + pose/ + intrinsic/ (ScanNet export)",
         "sequence/_info.txt + frame-XXXXXX.depth.pgm (3RScan)",
         "frame-XXXXXX.color.png|jpg + .depth.png + .pose.txt + camera-intrinsics.txt (7-Scenes)")


def detect_format(root: str | Path) -> str:
    """Name of the layout of the scan folder ``root`` (a key of :data:`READERS`)."""
    root = Path(root)
    if not root.is_dir():
        raise InputError(f"{root}: scan folder does not exist or is not a folder; fix scan.paths")
    for name, mod in READERS.items():
        if mod.looks_like(root):
            return name
    raise InputError(f"{root}: unknown scan format; expected one of: {'; '.join(HINTS)}. Set scan.format "
                     f"to force a layout")


def read_scan(root: str | Path, fmt: str = "auto", frame: int | None = None):
    """Read the scan folder ``root`` in layout ``fmt`` (``"auto"`` = detect) into a :class:`~pipeline.types.Scan`;
    ``frame``: one unit of :func:`scan_units` (an image of a BOP scene without a world pose)."""
    name = detect_format(root) if fmt == "auto" else fmt
    if name not in READERS:
        raise InputError(f"{root}: unknown scan format {name!r}; valid: {', '.join(READERS)}")
    if frame is not None:
        if name != "bop":
            raise ValueError(f"{name} scans have no per-image units")
        return bop.read(Path(root), frame)
    return READERS[name].read(Path(root))


def scan_units(root: str | Path, fmt: str = "auto") -> list[int | None]:
    """The scans one folder makes: ``[None]`` (the folder is one scan) except for a BOP scene whose images
    have no common world frame: then one per such image (its id), after ``None`` for the posed ones.

    A folder that cannot be read gives ``[None]``: reading it as one scan then reports why, for that
    folder alone.
    """
    try:
        name = detect_format(root) if fmt == "auto" else fmt
        return bop.units(Path(root)) if name == "bop" else [None]
    except InputError:
        return [None]
