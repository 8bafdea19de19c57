"""The pipeline's stages, in order: one table of name, where the stage lives and what it does.

Stage modules are imported only when their stage runs (heavy backends stay out of start-up). This module
imports nothing of the project at load time, so :mod:`pipeline.runner` and the CLI can use it freely.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, NamedTuple

if TYPE_CHECKING:  # pragma: no cover
    from pipeline.runner import Stage


class StageEntry(NamedTuple):
    name: str
    location: str   # "module:attribute" of its Stage
    help: str


STAGES: tuple[StageEntry, ...] = (
    StageEntry("ingest", "pipeline.ingest:STAGE",
               "read the scans and object libraries into the run folder (reconstruct room meshes)"),
    StageEntry("select", "pipeline.select:STAGE", "score frames for blur and keep a sharp, diverse subset"),
    StageEntry("prep", "pipeline.prep:STAGE",
               "repair and simplify room and object meshes; build collision proxies"),
    StageEntry("simulate", "pipeline.simulate:STAGE", "drop objects into each room with rigid-body physics"),
    StageEntry("raster", "pipeline.raster:STAGE", "rasterize depth, labels and masks; compute annotations"),
    StageEntry("trace", "pipeline.trace.stage:STAGE",
               "path-trace ambient occlusion and PBR shading of the objects"),
    StageEntry("composite", "pipeline.composite:STAGE", "fuse the rendered objects into the real photos"),
    StageEntry("export", "pipeline.export:STAGE", "write the dataset in BOP, COCO and YOLO formats"),
)

STAGE_ORDER: tuple[str, ...] = tuple(e.name for e in STAGES)
_BY_NAME = {e.name: e for e in STAGES}


def get_stage(name: str) -> Stage:
    """The :class:`~pipeline.runner.Stage` called ``name`` (imports its module).

    ``name`` may also be ``"module:attribute"`` of a Stage outside the table (tests use this).
    """
    if ":" in name:
        module, attr = name.split(":")
        return getattr(importlib.import_module(module), attr)
    if name not in _BY_NAME:
        raise KeyError(f"unknown stage {name!r}; stages: {', '.join(STAGE_ORDER)}")
    module, attr = _BY_NAME[name].location.split(":")
    stage = getattr(importlib.import_module(module), attr)
    if stage.name != name:
        raise RuntimeError(f"{_BY_NAME[name].location} is stage {stage.name!r}, expected {name!r}")
    return stage


def stage_help(name: str) -> str:
    return _BY_NAME[name].help
