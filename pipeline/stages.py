"""The ordered list of pipeline stages and where each one lives.

Stage modules are imported only when their stage runs (heavy backends stay out of start-up). A stage
that is not built yet is a placeholder: it runs nothing and says so loudly in the log and in the
summary, naming the issue that builds it.
"""

from __future__ import annotations

import importlib

from pipeline.runner import Stage

# name -> "module:attribute" of its Stage, or a placeholder note
STAGE_ORDER: tuple[str, ...] = ("ingest", "select", "prep", "simulate", "raster", "trace", "composite", "export")

_LOCATIONS: dict[str, str] = {
    "ingest": "pipeline.ingest:STAGE",
    "select": "pipeline.select:STAGE",
    "prep": "pipeline.prep:STAGE",
    "simulate": "pipeline.simulate:STAGE",
    "raster": "pipeline.raster:STAGE",
    "trace": "pipeline.trace.stage:STAGE",
    "composite": "pipeline.composite:STAGE",
    "export": "pipeline.export:STAGE",
}

_HELP: dict[str, str] = {
    "ingest": "read the scans and object libraries into the run folder (reconstruct room meshes)",
    "select": "score frames for blur and keep a sharp, diverse subset",
    "prep": "repair and simplify room and object meshes; build collision proxies",
    "simulate": "drop objects into each room with rigid-body physics",
    "raster": "rasterize depth, labels and masks; compute annotations",
    "trace": "path-trace ambient occlusion and PBR shading of the objects",
    "composite": "fuse the rendered objects into the real photos",
    "export": "write the dataset in BOP, COCO and YOLO formats",
}


def _noop_plan(ctx):  # pragma: no cover - placeholders never plan
    return []


def _noop_item(ctx, item):  # pragma: no cover
    return None


def get_stage(name: str) -> Stage:
    """The :class:`~pipeline.runner.Stage` called ``name`` (imports its module).

    ``name`` may also be ``"module:attribute"`` of a Stage outside the registry (tests use this).
    """
    if ":" in name:
        module, attr = name.split(":")
        return getattr(importlib.import_module(module), attr)
    if name not in _LOCATIONS:
        raise KeyError(f"unknown stage {name!r}; stages: {', '.join(STAGE_ORDER)}")
    loc = _LOCATIONS[name]
    if loc.startswith("placeholder:"):
        note = f"not built yet ({loc.split(':', 1)[1]})"
        return Stage(name=name, plan=_noop_plan, run_item=_noop_item, placeholder=note)
    module, attr = loc.split(":")
    stage = getattr(importlib.import_module(module), attr)
    if stage.name != name:
        raise RuntimeError(f"{loc} is stage {stage.name!r}, expected {name!r}")
    return stage


def stage_help(name: str) -> str:
    return _HELP[name]
