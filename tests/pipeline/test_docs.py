"""Documentation derived from code stays in sync with it, and the documents point at files that exist."""

from __future__ import annotations

import re

from pipeline.config import load_config, Config, TABLES
from pipeline.docs import CONFIG_DOC, REPO, TEMPLATE, expected_config_doc, expected_template

DOCS = [REPO / "README.md", REPO / "bench" / "README.md", *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def test_template_lists_every_key_and_loads_to_the_defaults():
    assert TEMPLATE.read_text(encoding="utf-8") == expected_template(), \
        "configs/template.toml is stale: run .venv/bin/python -m pipeline.docs"
    assert load_config(TEMPLATE) == Config()


def test_config_reference_is_current_and_the_readme_points_at_it():
    assert CONFIG_DOC.read_text(encoding="utf-8") == expected_config_doc(), \
        "docs/config.md is stale: run .venv/bin/python -m pipeline.docs"
    text = CONFIG_DOC.read_text(encoding="utf-8")
    for table in TABLES:
        assert f"## `[{table}]`" in text
    assert "(docs/config.md)" in (REPO / "README.md").read_text(encoding="utf-8")


def relative_links(text: str) -> list[str]:
    """The link and image targets of markdown ``text`` that are paths in the repository (no URL, no anchor)."""
    return [t.split("#")[0] for t in LINK.findall(text) if "://" not in t and not t.startswith(("#", "mailto:"))]


def test_relative_links_finds_paths_only():
    text = "[a](docs/x.md) ![p](img.png) [b](https://example.org/y) [c](#anchor) [d](../z.md#part)"
    assert relative_links(text) == ["docs/x.md", "img.png", "../z.md"]


def test_documents_link_only_to_files_that_exist():
    assert len(DOCS) >= 4 and all(p.is_file() for p in DOCS), DOCS
    missing = [f"{doc.relative_to(REPO)}: {target}" for doc in DOCS
               for target in relative_links(doc.read_text(encoding="utf-8"))
               if not (doc.parent / target).exists()]
    assert not missing, f"links to files that do not exist: {missing}"
