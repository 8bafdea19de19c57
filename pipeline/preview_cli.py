"""``scansynth preview`` command: argument parsing and output for :mod:`pipeline.preview`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.errors import UserError
from pipeline.io import atomic_write_image
from pipeline.preview import DEFAULT_NAME, contact_sheet, find_dataset


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", type=Path, help="run folder or BOP dataset folder")
    p.add_argument("--out", type=Path, default=None,
                   help=f"PNG to write (default: {DEFAULT_NAME} in the run folder)")
    p.add_argument("--max-images", type=int, default=12, help="images on the sheet (default 12)")


def run(args: argparse.Namespace) -> int:
    if args.max_images < 1:
        raise UserError(f"--max-images {args.max_images}: must be at least 1")
    dataset = find_dataset(args.path.resolve())
    out = args.out or (args.path / DEFAULT_NAME)
    atomic_write_image(out, contact_sheet(dataset, max_images=args.max_images))
    if not args.quiet:
        print(f"preview: {out.resolve()}", file=sys.stderr)
    return 0
