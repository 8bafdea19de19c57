"""Documentation derived from code stays in sync with it."""

from __future__ import annotations

from pipeline.config import load_config, Config
from pipeline.docs import README, TEMPLATE, expected_readme, expected_template


def test_template_lists_every_key_and_loads_to_the_defaults():
    assert TEMPLATE.read_text(encoding="utf-8") == expected_template(), \
        "configs/template.toml is stale: run .venv/bin/python -m pipeline.docs"
    assert load_config(TEMPLATE) == Config()


def test_readme_reference_is_current():
    text = README.read_text(encoding="utf-8")
    assert text == expected_readme(text), "README's configuration reference is stale: run python -m pipeline.docs"
