"""The repository holds what is true now, in documents a newcomer can read.

History belongs to git: no tracked file names a work session (the text ``session`` followed by a number),
and no results file keeps a ``*_diagnostics`` block. The README stays short enough to finish, and no
markdown table cell in the documents runs to a paragraph. Every check is a small function tested on planted
examples first, so that a check that can no longer fail shows up as a failing test.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README_MAX_BYTES = 15 * 1024
CELL_MAX_CHARS = 300
# "session" and a number, in any case: run together or after a separator ("sessionN_..."), or as words ("session N",
# "sessions N-M"). pytest's scope="session" and subprocess's start_new_session have no number after the word.
SESSION = re.compile(r"session[_-]?[0-9]|\bsessions? [0-9]", re.IGNORECASE)
DIAGNOSTICS = "_diagnostics"


def tracked_text_files(root: Path = ROOT) -> list[tuple[str, str]]:
    """(path relative to ``root``, text) of every file git tracks there that exists and is text (no NUL byte in
    its first 8 KiB, valid UTF-8)."""
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=root, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as e:
        pytest.skip(f"not a git checkout ({e}): the tracked files cannot be listed")
    files = []
    for name in out.decode().split("\0"):
        path = root / name
        if not name or not path.is_file() or path.is_symlink():
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:
            continue
        try:
            files.append((name, data.decode("utf-8")))
        except UnicodeDecodeError:
            continue
    return files


def session_mentions(text: str) -> list[str]:
    """Each line of ``text`` (``N: line``, cut to 120 characters) that names a work session."""
    return [f"{i}: {line.strip()[:120]}" for i, line in enumerate(text.splitlines(), 1) if SESSION.search(line)]


def diagnostic_keys(doc: object, path: str = "") -> list[str]:
    """The paths (``/a/b``) of every key of the JSON value ``doc``, at any depth, that contains ``_diagnostics``."""
    found = []
    if isinstance(doc, dict):
        for k, v in doc.items():
            here = f"{path}/{k}"
            if DIAGNOSTICS in str(k):
                found.append(here)
            found += diagnostic_keys(v, here)
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            found += diagnostic_keys(v, f"{path}[{i}]")
    return found


def table_cells(markdown: str) -> list[tuple[int, str]]:
    """(line number, text) of every cell of every markdown table in ``markdown`` (fenced code blocks skipped)."""
    cells, fenced = [], False
    for i, line in enumerate(markdown.splitlines(), 1):
        s = line.strip()
        if s.startswith("```"):
            fenced = not fenced
            continue
        if fenced or not s.startswith("|"):
            continue
        cells += [(i, c.strip()) for c in re.split(r"(?<!\\)\|", s.strip("|"))]
    return cells


def long_cells(markdown: str, limit: int = CELL_MAX_CHARS) -> list[str]:
    """``line N: length``, cell start, for each table cell of ``markdown`` longer than ``limit`` characters."""
    return [f"line {i}: {len(c)} chars: {c[:60]}..." for i, c in table_cells(markdown) if len(c) > limit]


def documents(root: Path = ROOT) -> list[Path]:
    """The markdown documents whose tables are held short: the README, the benchmarks' and docs/."""
    return [root / "README.md", root / "bench" / "README.md", *sorted((root / "docs").glob("*.md"))]


# --- the checks on planted examples ------------------------------------------------------------------------------

WORD = "sess" + "ion"   # kept apart so that this file does not name a session itself


@pytest.mark.parametrize("line", [
    f"measured in {WORD} 12 against main", f"{WORD.capitalize()} 3: the fit", f"what {WORD}s 18-29 tried",
    f'"{WORD}23_diagnostics": {{}}', f"before_{WORD}22_previous_render", f"{WORD.upper()} 4", f"{WORD}-7 notes",
])
def test_session_mentions_are_found(line):
    assert session_mentions(f"first line\n{line}\nlast line") == [f"2: {line}"]


@pytest.mark.parametrize("line", [
    f'@pytest.fixture(scope="{WORD}")', f"subprocess.Popen(args, start_new_{WORD}=True)",
    f"a {WORD} of the suite", f"one {WORD}, 3 runs", f"pro{WORD}al", "issue 17's target",
])
def test_ordinary_words_are_not_session_mentions(line):
    assert session_mentions(line) == []


def test_diagnostic_keys_are_found_at_any_depth():
    doc = {"rooms": {"a": 1}, f"{WORD}31_diagnostics": {}, "x": [{"y": {"fit_diagnostics": 2}}],
           "note": "a value that says _diagnostics is not a key"}
    assert diagnostic_keys(doc) == [f"/{WORD}31_diagnostics", "/x[0]/y/fit_diagnostics"]
    assert diagnostic_keys({"rooms": {"a": [1, 2]}, "groups": {}}) == []


def test_long_table_cells_are_found_outside_code_blocks():
    text = ("# t\n\n| a | b |\n|---|---|\n| short | " + "x" * 301 + " |\n| " + "y" * 300 + " | `a\\|b` |\n\n"
            "```\n| " + "z" * 400 + " |\n```\n")
    assert [c for _, c in table_cells(text)][:4] == ["a", "b", "---", "---"]
    got = long_cells(text)
    assert len(got) == 1 and got[0].startswith("line 5: 301 chars: xxx"), got
    assert ("`a\\|b`") in [c for _, c in table_cells(text)]


# --- the repository ----------------------------------------------------------------------------------------------

def test_no_tracked_file_names_a_session():
    found = [f"{name}:{hit}" for name, text in tracked_text_files() for hit in session_mentions(text)]
    assert not found, "files that name a work session (history belongs to git):\n" + "\n".join(found)


def test_no_json_file_keeps_diagnostic_blocks():
    found = []
    for name, text in tracked_text_files():
        if name.endswith(".json"):
            found += [f"{name}: {key}" for key in diagnostic_keys(json.loads(text))]
    assert not found, "JSON keys that hold diagnostics instead of current figures:\n" + "\n".join(found)


def test_readme_is_short():
    size = (ROOT / "README.md").stat().st_size
    assert size <= README_MAX_BYTES, f"README.md is {size} bytes, over {README_MAX_BYTES}: move detail to docs/"


def test_no_table_cell_runs_to_a_paragraph():
    docs = documents()
    assert len(docs) >= 4, docs
    found = [f"{p.relative_to(ROOT)} {hit}" for p in docs for hit in long_cells(p.read_text(encoding="utf-8"))]
    assert not found, f"table cells over {CELL_MAX_CHARS} characters:\n" + "\n".join(found)
