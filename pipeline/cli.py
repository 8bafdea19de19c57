"""``scansynth`` command line.

Exit codes: 0 everything finished, 1 some item(s) failed or left out unreadable inputs (the rest finished
and is kept; each cause is on the console and in run.json), 2 usage or
configuration error (nothing was run). User mistakes are printed as one line, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import math
import os
import platform
import signal
import sys
import time
from pathlib import Path

from pipeline import __version__
from pipeline.config import BUILTIN_PREFIX, Config, ConfigError, config_to_dict, dump_config, load_config
from pipeline.errors import InputError, UserError
from pipeline.io import atomic_write_bytes, atomic_write_json, read_json, remove_stale_temps
from pipeline.stages import STAGE_ORDER, get_stage, stage_help

log = logging.getLogger("scansynth")

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2
CONFIG_NAME = "config.toml"     # resolved config of a run folder
META_NAME = "run_meta.json"     # seed and package versions
REPORT_NAME = "run.json"        # per-stage report of the last invocation (timings: not reproducible)

# Keys that change how a run executes but not what it produces: may differ on resume.
EXECUTION_ONLY = {("run", "workers"), ("run", "executor"), ("run", "ray_address"), ("run", "progress")}

# Commands that are not stages: name -> (module with add_arguments(parser) and run(args) -> int, help)
EXTRA_COMMANDS: dict[str, tuple[str, str]] = {
    "make-scan": ("pipeline.synthscan.cli", "write a procedural room scan with ground truth in a real scan layout"),
    "preview": ("pipeline.preview_cli", "contact sheet of a dataset: images with masks, boxes and pose axes drawn "
                                    "from the written annotations"),
    "report": ("pipeline.report_cli", "write RUN/report.html: images, timings, rejections with reasons, "
                                  "annotated samples, frame selection (run writes it too)"),
}

PACKAGES = ("numpy", "open3d", "pymeshlab", "manifold3d", "embreex", "pyrender", "PyOpenGL",
            "opencv-contrib-python-headless", "scikit-image", "pycocotools", "matplotlib")


# ---------------------------------------------------------------------------------------------------
# Progress
# ---------------------------------------------------------------------------------------------------

class ProgressBar:
    """A one-line progress bar with counts and ETA on stderr."""

    def __init__(self, label: str, enabled: bool, stream=sys.stderr):
        self.label, self.enabled, self.stream = label, enabled, stream
        self._last = 0.0

    def __call__(self, finished: int, total: int, elapsed: float) -> None:
        if not self.enabled or total == 0:
            return
        now = time.monotonic()
        if finished < total and now - self._last < 0.2:
            return
        self._last = now
        frac = finished / total
        width = 24
        bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
        eta = "--:--"
        if 0 < frac < 1 and elapsed > 0:
            rem = elapsed / frac * (1 - frac)
            eta = f"{int(rem // 60):02d}:{int(rem % 60):02d}"
        end = "\n" if finished >= total else ""
        self.stream.write(f"\r{self.label:>9} [{bar}] {finished}/{total} {frac:4.0%} ETA {eta}{end}")
        self.stream.flush()


def _progress_enabled(cfg: Config, args: argparse.Namespace) -> bool:
    if args.quiet:
        return False
    mode = args.progress or cfg.run.progress
    return mode == "on" or (mode == "auto" and sys.stderr.isatty())


# ---------------------------------------------------------------------------------------------------
# Run folders
# ---------------------------------------------------------------------------------------------------

def package_versions() -> dict[str, str]:
    from importlib import metadata

    out = {"python": platform.python_version(), "scansynth": __version__}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def _diff(old: dict, new: dict) -> list[str]:
    out = []
    for table in sorted(set(old) | set(new)):
        for key in sorted(set(old.get(table, {})) | set(new.get(table, {}))):
            if (table, key) in EXECUTION_ONLY:
                continue
            a, b = old.get(table, {}).get(key), new.get(table, {}).get(key)
            if a != b:
                out.append(f"{table}.{key}: {a!r} -> {b!r}")
    return out


def init_run_dir(run_dir: Path, cfg: Config) -> None:
    """Create a run folder with its resolved config, or check that an existing one matches ``cfg``."""
    cfg_path = run_dir / CONFIG_NAME
    if cfg_path.exists():
        old = load_config(cfg_path)
        diffs = _diff(config_to_dict(old), config_to_dict(cfg))
        if diffs:
            raise ConfigError(f"{run_dir} was started with a different config ({'; '.join(diffs[:3])}); "
                              f"resume it with the same config, or pass a new --out folder")
    elif run_dir.exists() and any(run_dir.iterdir()):
        raise ConfigError(f"{run_dir} exists, is not empty and is not a scansynth run folder "
                          f"(no {CONFIG_NAME}); pass a new or empty --out folder")
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(cfg_path, dump_config(cfg).encode("utf-8"))
    atomic_write_json(run_dir / META_NAME, {"seed": cfg.run.seed, "versions": package_versions()})
    for p in cfg.scan.paths:
        if p.startswith(BUILTIN_PREFIX):
            generate_builtin_scan(run_dir, p[len(BUILTIN_PREFIX):])


def generate_builtin_scan(run_dir: Path, name: str) -> Path:
    """Generate built-in scan ``name`` into the run folder (once: an existing one is complete, as it only
    appears by a rename, and is checked), so that ingest only ever reads folders."""
    import shutil

    from pipeline import runfolder

    if name not in runfolder.BUILTIN_SCANS:
        raise UserError(f"scan.paths: unknown built-in scan 'builtin:{name}'; valid: "
                        f"{', '.join('builtin:' + n for n in runfolder.BUILTIN_SCANS)}")
    from pipeline.synthscan import builtin_scan

    final = runfolder.path(run_dir, runfolder.BUILTIN_SCAN_TPATH, name=name)
    if final.is_dir():
        return Path(builtin_scan(name, final))  # reused as it is when complete
    # generate beside it and rename into place: a run killed mid-generation never leaves a partial scan
    for stale in final.parent.glob(f"{name}.tmp-*"):
        shutil.rmtree(stale, ignore_errors=True)
    tmp = final.with_name(f"{name}.tmp-{os.getpid()}")
    builtin_scan(name, tmp)
    os.replace(tmp, final)
    return final


def open_run_dir(run_dir: Path, overrides: list[str]) -> Config:
    """Config of an existing run folder, with execution-only overrides (workers, progress) applied."""
    cfg_path = run_dir / CONFIG_NAME
    if not cfg_path.is_file():
        raise ConfigError(f"{run_dir} is not a run folder (no {CONFIG_NAME}); start one with "
                          f"'scansynth run CONFIG --out {run_dir}' or pass --config CONFIG")
    for text in overrides:
        lhs = text.split("=", 1)[0].strip()
        if tuple(lhs.split(".", 1)) not in EXECUTION_ONLY:
            raise ConfigError(f"--set {text!r}: only {', '.join('.'.join(k) for k in sorted(EXECUTION_ONLY))} "
                              f"may change in an existing run folder; start a new one for other changes")
    return load_config(cfg_path, overrides)


def run_stages(run_dir: Path, cfg: Config, names: list[str], args: argparse.Namespace) -> int:
    """Run ``names`` in order; print a summary; write run.json; return the exit code."""
    removed = remove_stale_temps(run_dir)
    if removed:
        log.info("removed %d partial file(s) left by an interrupted run", removed)
    enabled = _progress_enabled(cfg, args)
    reports = []
    t0 = time.perf_counter()
    for name in names:
        stage = get_stage(name)
        log.info("stage %s: %s", name, stage_help(name))
        rep = _run_one(run_dir, cfg, stage, enabled)
        reports.append(rep)
        if rep.failed and name != names[-1]:
            log.error("stage %s: %d item(s) failed; later stages use what finished", name, rep.failed)
    total = time.perf_counter() - t0
    done = sum(r.done for r in reports)
    skipped = sum(r.skipped for r in reports)
    failed = sum(r.failed for r in reports)
    problems = sum(len(v) for r in reports for v in r.problems.values())
    secs = [s for r in reports for s in r.item_seconds]
    per = sum(secs) / len(secs) if secs else 0.0
    placeholders = [r.stage for r in reports if r.placeholder]
    from pipeline import report as run_report

    stage_docs = [r.as_dict() for r in reports]
    report = {"run_dir": str(run_dir), "seconds": round(total, 3), "done": done, "skipped": skipped,
              "failed": failed, "input_problems": problems,
              "throughput": run_report.throughput(run_dir, stage_docs),
              "rejected": run_report.rejected(run_dir), "stages": stage_docs}
    atomic_write_json(run_dir / REPORT_NAME, report)
    html_report = _write_html_report(run_dir)
    msg = (f"scansynth: {done} item(s) done, {skipped} skipped (already finished), {failed} failed, "
           f"{problems} input(s) left out, {per:.2f} s/item, {total:.1f} s total")
    if placeholders:
        msg += f"; PLACEHOLDER stages (not built yet, did nothing): {', '.join(placeholders)}"
    if not args.quiet:
        print(msg, file=sys.stderr)
    for r in reports:
        for key, err in r.failures.items():
            print(f"FAILED {r.stage} {key}: {err}", file=sys.stderr)
        for key, lines in r.problems.items():
            for line in lines:
                print(f"LEFT OUT {r.stage} {key}: {line}", file=sys.stderr)
    if any(r.stage == "export" for r in reports):
        for key, why in report["rejected"].get("export", {}).items():   # frames not in the dataset
            print(f"NOT IN DATASET {key}: {why}", file=sys.stderr)
    if html_report is not None and not args.quiet:
        print(f"report: {html_report}", file=sys.stderr)
    return EXIT_FAILED if failed or problems else EXIT_OK


def _write_html_report(run_dir: Path) -> Path | None:
    """RUN/report.html after every invocation; a report that cannot be drawn costs only itself."""
    from pipeline.report_html import write_report

    try:
        return write_report(run_dir)
    except Exception as e:  # noqa: BLE001 - the run's own results are written; the page is extra
        log.error("could not write %s/report.html (%s: %s); the run's results are unaffected; "
                  "retry with 'scansynth report %s'", run_dir, type(e).__name__, e, run_dir)
        return None


def _run_one(run_dir: Path, cfg: Config, stage, progress_on: bool):
    from pipeline.runner import run_stage

    return run_stage(run_dir, cfg, stage, on_progress=ProgressBar(stage.name, progress_on))


# ---------------------------------------------------------------------------------------------------
# Argument parsing
# ---------------------------------------------------------------------------------------------------

def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="TABLE.KEY=VALUE",
                   help="override a config value (repeatable), e.g. --set run.seed=3")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    p.add_argument("-q", "--quiet", action="store_true", help="only errors")
    p.add_argument("--progress", choices=("auto", "on", "off"), default=None,
                   help="progress bars on stderr (default: the config's run.progress)")


def _add_poses(p: argparse.ArgumentParser) -> None:
    p.add_argument("--poses", type=Path, default=None, metavar="POSES.json",
                   help="render these object poses instead of the simulated drops (same as "
                        "--set raster.poses=POSES.json; schema in pipeline/raster.py)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scansynth",
        description="Make annotated training images by inserting simulated, path-traced objects "
                    "into real RGB-D room scans.")
    parser.add_argument("--version", action="version", version=f"scansynth {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("run", help="run every stage (resumes a run folder that already exists)",
                       description="Run every stage. Re-running with the same --out resumes: finished "
                                   "items are kept, unfinished and failed ones are (re)done.")
    p.add_argument("config", help="TOML config file (see configs/)")
    p.add_argument("--out", required=True, type=Path, help="run folder to create or resume")
    p.add_argument("--from", dest="from_stage", choices=STAGE_ORDER, help="first stage to run")
    p.add_argument("--to", dest="to_stage", choices=STAGE_ORDER, help="last stage to run")
    _add_poses(p)
    _common(p)

    for name in STAGE_ORDER:
        p = sub.add_parser(name, help=stage_help(name), description=stage_help(name).capitalize() + ".")
        p.add_argument("run_dir", type=Path, help="run folder")
        p.add_argument("--config", default=None,
                       help="config file, to start a new run folder with this stage")
        if name == "raster":
            _add_poses(p)
        _common(p)

    for name, (module, help_text) in EXTRA_COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        importlib.import_module(module).add_arguments(p)
        p.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
        p.add_argument("-q", "--quiet", action="store_true", help="only errors")
    return parser


def _setup_logging(args: argparse.Namespace) -> None:
    level = logging.WARNING
    if getattr(args, "quiet", False):
        level = logging.ERROR
    elif getattr(args, "verbose", 0) == 1:
        level = logging.INFO
    elif getattr(args, "verbose", 0) >= 2:
        level = logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr,
                        force=True)
    from pipeline.runner import log_warnings

    log_warnings()


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def install_sigterm_handler() -> None:
    """Treat SIGTERM like Ctrl-C: stop worker processes, keep finished items, exit 130."""
    signal.signal(signal.SIGTERM, _interrupt)


def check_config_files(cfg: Config) -> None:
    """Read the files a config names whose contents the config cannot check itself (trace.lights_file), so
    that a bad one stops the run in one line before any stage runs, not when its stage starts."""
    if cfg.trace.lights_file:
        from pipeline.trace.lightfit import read_lights_file

        try:
            read_lights_file(cfg.trace.lights_file)
        except InputError as e:
            raise ConfigError(f"trace.lights_file: {e}") from None


def main(argv: list[str] | None = None) -> int:
    # Open3D's OpenMP threads spin while they wait; on a shared or busy machine that made TSDF fusion
    # 10-20x slower. Set before anything imports open3d; a value the user set wins.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    install_sigterm_handler()
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args)
    if not args.verbose:
        # Stage progress is shown by the bar; stage start lines only with -v.
        pass
    try:
        if args.command in EXTRA_COMMANDS:
            module = importlib.import_module(EXTRA_COMMANDS[args.command][0])
            return int(module.run(args))
        if getattr(args, "poses", None) is not None:
            args.overrides = [*args.overrides, f"raster.poses={json.dumps(str(args.poses.resolve()))}"]
        if args.command == "run":
            cfg = load_config(args.config, args.overrides)
            check_config_files(cfg)
            run_dir = args.out.resolve()
            init_run_dir(run_dir, cfg)
            lo = STAGE_ORDER.index(args.from_stage) if args.from_stage else 0
            hi = STAGE_ORDER.index(args.to_stage) if args.to_stage else len(STAGE_ORDER) - 1
            if lo > hi:
                raise ConfigError(f"--from {args.from_stage} comes after --to {args.to_stage}")
            return run_stages(run_dir, cfg, list(STAGE_ORDER[lo:hi + 1]), args)
        run_dir = args.run_dir.resolve()
        if args.config is not None:
            cfg = load_config(args.config, args.overrides)
            check_config_files(cfg)
            init_run_dir(run_dir, cfg)
        else:
            cfg = open_run_dir(run_dir, args.overrides)
            check_config_files(cfg)
        return run_stages(run_dir, cfg, [args.command], args)
    except UserError as e:
        print(f"scansynth: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("scansynth: interrupted; finished items are kept, run the same command again to resume",
              file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
