"""``scansynth make-scan``: write a procedural room scan with ground truth in a real scan layout.

Top-level imports are light: :func:`add_arguments` runs for every ``scansynth`` invocation.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from pipeline.errors import UserError

LAYOUT_CHOICES = ("7scenes", "3rscan", "scannet", "transforms", "bop")


def _size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"{text!r} is not WIDTHxHEIGHT (e.g. 640x480)")
    return int(m.group(1)), int(m.group(2))


def add_arguments(p: argparse.ArgumentParser) -> None:
    """Add make-scan's arguments to its sub-parser."""
    p.add_argument("out", type=Path, metavar="OUT", help="folder to write (new, empty, or an earlier make-scan output)")
    p.add_argument("--layout", required=True, choices=LAYOUT_CHOICES, help="scan layout to write")
    p.add_argument("--seed", type=int, required=True, help="random seed (>= 0); same seed, same bytes")
    p.add_argument("--size", type=_size, default=(640, 480), metavar="WxH",
                   help="colour image size (default 640x480; depth is smaller for scannet and 3rscan)")
    p.add_argument("--frames", type=int, default=50, help="number of frames (default 50)")
    p.add_argument("--contact-sheet", type=Path, default=None, metavar="PATH",
                   help="also write a PNG contact sheet of the frames, blurred ones marked")
    p.add_argument("--photo-mode", choices=("raster", "traced"), default="raster",
                   help="photo renderer: raster (pyrender, fast) or traced (path tracer: global illumination, "
                        "soft shadows; ~seconds per 160x120 frame)")


def run(args: argparse.Namespace) -> int:
    """Make the scan; return the exit code (user mistakes raise UserError, printed by the CLI)."""
    from pipeline.synthscan.generate import make_scan

    if args.contact_sheet is not None and args.contact_sheet.suffix.lower() != ".png":
        raise UserError(f"--contact-sheet {args.contact_sheet}: the contact sheet is a PNG; give a path ending in .png")
    width, height = args.size
    out = make_scan(args.out, layout=args.layout, seed=args.seed, width=width, height=height, frames=args.frames,
                    contact_sheet=args.contact_sheet, photo_mode=args.photo_mode)
    if not getattr(args, "quiet", False):
        print(f"make-scan: wrote {args.layout} scan ({args.frames} frames, {width}x{height}) to {out}",
              file=sys.stderr)
    return 0
