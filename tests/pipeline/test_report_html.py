"""report.html on runs that have not got far, and on text from files that looks like HTML.

The full page of a finished run is opened in Chromium by tests/pipeline/test_e2e.py.
"""

from __future__ import annotations

import json

import pytest

from pipeline.errors import UserError
from pipeline.report_html import write_report


def test_a_run_that_has_not_started_gives_a_page_that_says_so(tmp_path):
    (tmp_path / "config.toml").write_text('[run]\nseed = 3\n[scan]\npaths = ["builtin:tiny"]\n')
    text = write_report(tmp_path).read_text(encoding="utf-8")
    assert "No stage has run yet" in text and "No dataset yet" in text and "No scan ingested yet" in text
    assert "seed 3" in text


def test_text_from_the_run_folder_is_escaped(tmp_path):
    (tmp_path / "config.toml").write_text("[run]\nseed = 0\n")
    evil = "<script>alert(1)</script> & more"
    run = {"seconds": 1.0, "done": 1, "skipped": 0, "failed": 1, "input_problems": 0,
           "throughput": {"images": 0}, "rejected": {"frames": {"s/drop0000/f000001": evil}},
           "stages": [{"stage": "ingest", "seconds": 1.0, "done": 0, "skipped": 0,
                       "failures": {"s": evil}, "input_problems": {}}]}
    (tmp_path / "run.json").write_text(json.dumps(run))
    text = write_report(tmp_path).read_text(encoding="utf-8")
    assert "<script>" not in text
    assert text.count("&lt;script&gt;alert(1)&lt;/script&gt; &amp; more") == 2


def test_not_a_run_folder(tmp_path):
    with pytest.raises(UserError, match="no such run folder"):
        write_report(tmp_path / "nope")
    with pytest.raises(UserError, match="not a scansynth run folder"):
        write_report(tmp_path)
