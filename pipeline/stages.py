"""The stage contract and the pipeline's stages, in order.

The types every stage module and :mod:`pipeline.runner` share live here, below both: :class:`Stage` (how
to list a stage's items and how to do one), :class:`Item` and :class:`StageContext`. Then one table of
each stage's name, where it lives and what it does. Stage modules are imported only when their stage
runs (heavy backends stay out of start-up); this module imports nothing of the project at load time
(:meth:`StageContext.rng` imports :mod:`pipeline.seeding` when a stage runs), so the runner and the CLI
can use it freely.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable, NamedTuple

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

    from pipeline.config import Config

INPUT_PROBLEMS = "input_problems"  # key of a run_item result: inputs the item left out, one line each


@dataclass(frozen=True)
class Item:
    """One independent unit of a stage's work."""

    key: str                 # unique within the stage; folder-safe words joined by "/", e.g. "demo/drop0001"
    data: dict = field(default_factory=dict)  # JSON-able parameters the stage needs to do it


@dataclass(frozen=True)
class StageContext:
    """What a stage function may read: the run folder and the resolved config."""

    run_dir: Path
    cfg: Config
    stage: str

    @property
    def stage_dir(self) -> Path:
        return self.run_dir / self.stage

    def rng(self, item: Item) -> np.random.Generator:
        """The item's own generator, derived from the root seed, the stage name and the item key."""
        from pipeline.seeding import item_rng   # numpy: imported when a stage runs, not at start-up

        return item_rng(self.cfg.run.seed, self.stage, item.key)


@dataclass(frozen=True)
class Stage:
    """A pipeline stage: how to list its items and how to do one (run by :func:`pipeline.runner.run_stage`)."""

    name: str
    plan: Callable[[StageContext], list[Item]]
    run_item: Callable[[StageContext, Item], dict | None]
    # Called once after every item finished (merging, reports); must itself be idempotent.
    finish: Callable[[StageContext, dict[str, dict]], None] | None = None
    # A stage not built yet: runs nothing and says so. The string says which issue builds it.
    placeholder: str = ""
    # Optional start-up of each worker process, run while ``plan`` runs in the main one (imports, reading
    # what every item reads): a plan that takes long (trace's light fit) would otherwise leave the cores it
    # does not use idle, and the workers would start cold after it. Writes nothing; a failure is only logged
    # (the items meet it again and say so).
    warm: Callable[[StageContext], None] | None = None


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
    """The :class:`Stage` called ``name`` (imports its module).

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
