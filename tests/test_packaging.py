"""Every subpackage ships in a (non-editable) install."""

from __future__ import annotations

import tomllib
from pathlib import Path

from setuptools import find_packages

REPO = Path(__file__).resolve().parents[1]


def test_every_package_folder_is_included():
    conf = tomllib.loads((REPO / "pyproject.toml").read_text())
    include = conf["tool"]["setuptools"]["packages"]["find"]["include"]
    found = set(find_packages(where=REPO, include=include))
    on_disk = {str(p.parent.relative_to(REPO)).replace("/", ".")
               for top in ("pipeline", "meshprep") for p in (REPO / top).rglob("__init__.py")}
    assert on_disk <= found, f"left out of the distribution: {sorted(on_disk - found)}"


def test_meshprep_stands_alone():
    for p in (REPO / "meshprep").rglob("*.py"):
        text = p.read_text()
        assert "from pipeline" not in text and "import pipeline" not in text, f"{p} imports pipeline"
