"""Which layout a scan folder is in."""

from __future__ import annotations

from pathlib import Path

from pipeline.errors import InputError
from pipeline.scanformats import rscan, scannet, sevenscenes, transforms

# Checked in this order: the most specific markers first (3RScan frames look like 7-Scenes frames).
READERS = {"transforms": transforms, "scannet": scannet, "3rscan": rscan, "7scenes": sevenscenes}

HINTS = ("transforms.json (posed images)", "color/ + depth/ + pose/ + intrinsic/ (ScanNet export)",
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


def read_scan(root: str | Path, fmt: str = "auto"):
    """Read the scan folder ``root`` in layout ``fmt`` (``"auto"`` = detect) into a :class:`~pipeline.types.Scan`."""
    name = detect_format(root) if fmt == "auto" else fmt
    if name not in READERS:
        raise InputError(f"{root}: unknown scan format {name!r}; valid: {', '.join(READERS)}")
    return READERS[name].read(Path(root))
