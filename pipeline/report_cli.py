"""``scansynth report`` command: argument parsing and output for :mod:`pipeline.report_html`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.errors import UserError
from pipeline.report_html import MAX_SAMPLES, write_report


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run_dir", type=Path, help="run folder (the --out of 'scansynth run')")
    p.add_argument("--max-images", type=int, default=MAX_SAMPLES,
                   help=f"sample images on the page (default {MAX_SAMPLES})")


def run(args: argparse.Namespace) -> int:
    if args.max_images < 0:
        raise UserError(f"--max-images {args.max_images}: must be 0 or more")
    out = write_report(args.run_dir.resolve(), max_samples=args.max_images)
    if not args.quiet:
        print(f"report: {out}", file=sys.stderr)
    return 0
