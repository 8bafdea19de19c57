"""Shared benchmark helper: every stage's benchmark writes JSON + a speed-vs-accuracy PNG the same way.

A benchmark measures its own baseline in the same process and reports ratios beside absolute figures,
because this machine is shared and noisy. Benchmarks are not tests and nothing asserts on wall time.

Usage::

    res = BenchResult("select", speed_label="ms per frame", accuracy_label="F1")
    res.add_point("thesis", speed=3.2, accuracy=0.71, baseline=True)
    res.add_point("ours", speed=4.1, accuracy=0.95)
    res.figures["f1_default"] = 0.95
    res.write()   # bench/results/select.json and select.png
"""

from __future__ import annotations

import json
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@dataclass
class BenchResult:
    stage: str
    speed_label: str          # x axis, e.g. "seconds per frame"
    accuracy_label: str       # y axis, e.g. "RMSE" or "F1"
    lower_is_better: bool = False  # for the accuracy axis
    series: dict[str, list[dict]] = field(default_factory=dict)
    figures: dict[str, object] = field(default_factory=dict)   # headline numbers for the README/notes
    notes: list[str] = field(default_factory=list)
    started: float = field(default_factory=time.time)

    def add_point(self, series: str, *, speed: float, accuracy: float, label: str = "",
                  baseline: bool = False, **extra: object) -> None:
        """One measured point of a method/setting: its speed and its accuracy."""
        self.series.setdefault(series, []).append(
            {"speed": float(speed), "accuracy": float(accuracy), "label": label, "baseline": baseline,
             **extra})

    def baseline_ratio(self, series: str, value_key: str = "speed") -> list[float]:
        """Each point's ``value_key`` divided by the baseline point's (measured in the same run)."""
        base = [p for pts in self.series.values() for p in pts if p["baseline"]]
        if not base:
            return []
        return [p[value_key] / base[0][value_key] for p in self.series[series]]

    def plot_series(self, ax) -> None:
        """Draw every series (accuracy against speed, baseline starred) on a matplotlib axis."""
        for name, pts in self.series.items():
            ax.plot([p["speed"] for p in pts], [p["accuracy"] for p in pts], "o-", label=name)
            for p in pts:
                if p["label"]:
                    ax.annotate(p["label"], (p["speed"], p["accuracy"]), fontsize=7,
                                textcoords="offset points", xytext=(3, 3))
                if p["baseline"]:
                    ax.plot([p["speed"]], [p["accuracy"]], "k*", ms=12)
        ax.set_xlabel(self.speed_label)
        ax.set_ylabel(self.accuracy_label + (" (lower is better)" if self.lower_is_better else ""))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)

    def write(self, out_dir: Path = RESULTS) -> tuple[Path, Path]:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        out_dir.mkdir(parents=True, exist_ok=True)
        doc = {"stage": self.stage, "speed_label": self.speed_label,
               "accuracy_label": self.accuracy_label, "lower_is_better": self.lower_is_better,
               "series": self.series, "figures": self.figures, "notes": self.notes,
               "machine": {"python": platform.python_version(), "machine": platform.machine(),
                           "processor": platform.processor()},
               "wall_seconds": round(time.time() - self.started, 1)}
        jpath = out_dir / f"{self.stage}.json"
        jpath.write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
        fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
        self.plot_series(ax)
        ax.set_title(f"{self.stage}: accuracy against speed (star = baseline, same run)")
        fig.tight_layout()
        ppath = out_dir / f"{self.stage}.png"
        fig.savefig(ppath)
        plt.close(fig)
        return jpath, ppath
