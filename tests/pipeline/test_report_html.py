"""report.html on runs that have not got far, on a small real dataset, and on text from files that looks like HTML.

A small real dataset (raster + export of the test room, no full run) is opened in headless Chromium
here; the page of a full run is opened by tests/pipeline/test_e2e.py.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

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


# --- a small real dataset (raster + export of the test room, as tests/pipeline/test_preview.py) -----------

@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    from pipeline import export, raster
    from pipeline.config import build_config
    from pipeline.render_gl import shared_rasterizer
    from tests.pipeline import raster_scenes as S

    rd = tmp_path_factory.mktemp("report") / "RUN"
    made = S.make_run(rd, shared_rasterizer())
    cfg = build_config({"raster": {"poses": str(made["poses"])}, "export": {"image_format": "png"}})
    S.run_stage_direct(raster.STAGE, rd, cfg)
    S.write_composites(rd)
    S.run_stage_direct(export.STAGE, rd, cfg)
    (rd / "config.toml").write_text("[run]\nseed = 0\n")
    # a scan whose ingest recorded registration figures, and a selection with a score the report
    # does not know by name: both are shown
    (rd / "ingest" / "room" / "scan.json").write_text(json.dumps(
        {"format": "7scenes", "meta": {"registration_figures": {"colour focal px": 525.25,
                                                               "edge offset <px>": 1.5}}}))
    (rd / "select" / "room").mkdir(parents=True)
    (rd / "select" / "room" / "selection.json").write_text(json.dumps(
        {"method": "greedy", "frames": [
            {"index": 0, "frame_id": 0, "kept": True, "reason": "kept", "scores": {"relative": 1.0, "sharpness2": 7.5}},
            {"index": 1, "frame_id": 10, "kept": False, "reason": "blurred", "scores": {"relative": 0.25}}]}))
    return rd


def _links(text: str) -> list[str]:
    return re.findall(r'<a href="([^"]+)">', text)


def test_samples_are_the_previews_drawing_at_full_size(small_run):
    """Each sample links to its full-size image in RUN/report/, drawn by preview.draw_annotations from
    the written annotations; an earlier invocation's sample that is no longer shown is removed."""
    import cv2

    from pipeline.preview import draw_annotations
    from pipeline.io import read_json

    stale = small_run / "report" / "train_pbr_000099_000000.jpg"
    stale.parent.mkdir(exist_ok=True)
    stale.write_bytes(b"old")
    text = write_report(small_run).read_text(encoding="utf-8")
    assert not stale.exists()
    links = _links(text)
    dataset = small_run / "export" / "dataset"
    scene = sorted((dataset / "train_pbr").iterdir())[0]
    gt, info, cam = (read_json(scene / n) for n in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"))
    assert len(links) == len(gt) and sorted(p.name for p in (small_run / "report").iterdir()) == \
        sorted(Path(h).name for h in links)
    for href in links:
        im = int(Path(href).stem.rsplit("_", 1)[1])
        rgb = cv2.imread(str(scene / "rgb" / f"{im:06d}.png"))[..., ::-1]
        want = draw_annotations(rgb, scene, im, gt[str(im)], info[str(im)], cam[str(im)],
                                read_json(dataset / "models" / "models_info.json"))
        got = cv2.imread(str(small_run / href))[..., ::-1]
        assert np.array_equal(got, want), href     # lossless: exactly the preview's drawing


def test_scan_section_shows_registration_figures_and_every_selection_score(small_run):
    text = write_report(small_run).read_text(encoding="utf-8")
    assert "Colour-depth registration" in text and "edge offset &lt;px&gt;" in text and "525.250" in text
    assert "sharpness2" in text and "7.500" in text and "blurred" in text
    assert "Frame selection: 1 of 2 frames kept" in text


def test_registration_section_only_when_figures_exist(tmp_path):
    (tmp_path / "config.toml").write_text("[run]\nseed = 0\n")
    (tmp_path / "ingest" / "s").mkdir(parents=True)
    (tmp_path / "ingest" / "s" / "scan.json").write_text(json.dumps({"format": "7scenes", "meta": {}}))
    text = write_report(tmp_path).read_text(encoding="utf-8")
    assert "<h3>s</h3>" in text and "Colour-depth registration" not in text and "colour-depth" not in text


def test_a_sample_whose_image_is_missing_is_named_not_a_traceback(small_run, tmp_path):
    import shutil

    run = tmp_path / "RUN"
    shutil.copytree(small_run, run)
    scene = sorted((run / "export" / "dataset" / "train_pbr").iterdir())[0]
    victim = sorted((scene / "rgb").iterdir())[0]
    victim.unlink()
    text = write_report(run).read_text(encoding="utf-8")
    assert f"image {victim.stem} is listed in scene_gt.json but missing" in text
    assert all((run / h).is_file() for h in _links(text))


def test_report_of_a_small_run_loads_every_image_in_chromium(small_run, tmp_path):
    """Headless Chromium (bin/setup --test installs it): every <img> loaded, no error logged; the
    screenshot is kept in .cache/test-artifacts/report-small.png."""
    import shutil

    from tests.pipeline import browser

    page = write_report(small_run)
    if not browser.available():
        pytest.skip(f"Chromium is not installed ({browser.CHROMIUM}); bin/setup --test installs Debian's "
                    f"chromium package")
    shot = tmp_path / "report.png"
    r = browser.check_page(page, tmp_path / "profile", screenshot=shot, height=1600)
    n = len(_links(page.read_text(encoding="utf-8")))
    assert n >= 2 and r["images"] == n, r           # the samples (no stage chart: no run.json)
    assert r["broken"] == [] and r["errors"] == [] and r["console_errors"] == [], r
    assert shot.is_file() and shot.stat().st_size > 10_000
    artifacts = Path(__file__).resolve().parents[2] / ".cache" / "test-artifacts"
    artifacts.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(shot, artifacts / "report-small.png")


@pytest.mark.parametrize("stages, why", [
    (None, "no run.json yet"),
    ([{"stage": "raster", "seconds": 1.0, "done": 1, "skipped": 0}], "export did not run in the last invocation"),
    ([{"stage": "export", "seconds": 1.0, "done": 1, "skipped": 2}], "resumed run: not measured"),
])
def test_the_page_says_why_there_is_no_rate(tmp_path, stages, why):
    (tmp_path / "config.toml").write_text("[run]\nseed = 0\n")
    if stages is not None:
        (tmp_path / "run.json").write_text(json.dumps({"seconds": 1.0, "throughput": {"images": 0},
                                                       "stages": stages}))
    assert f"images/hour ({why})" in write_report(tmp_path).read_text(encoding="utf-8")


@pytest.mark.parametrize("name, doc", [
    ("run.json", [1, 2]),
    ("run.json", {"rejected": [1], "stages": "x"}),
    ("ingest/s/scan.json", {"meta": [1]}),
    ("select/s/selection.json", {"frames": [{"scores": [1]}]}),
    ("select/s/selection.json", "text"),
    ("prep/_items/objects.done.json", {"objects": [1]}),
    ("raster/summary.json", {"rejected_frames": [2]}),
    ("simulate/s/drop0000.json", 3),
])
def test_a_damaged_file_costs_its_section_not_the_page(tmp_path, capsys, name, doc):
    """A run folder file that is not what its stage writes: `scansynth report` still writes the page
    (exit 0, no traceback), and the report's rejection summary for run.json does not raise."""
    from pipeline.cli import main
    from pipeline.report import rejected

    (tmp_path / "config.toml").write_text("[run]\nseed = 0\n")
    (tmp_path / "ingest" / "s").mkdir(parents=True)
    (tmp_path / "ingest" / "s" / "scan.json").write_text(json.dumps({"format": "7scenes", "meta": {}}))
    path = tmp_path / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))
    assert main(["report", str(tmp_path), "-q"]) == 0
    assert "Traceback" not in capsys.readouterr().err
    text = (tmp_path / "report.html").read_text(encoding="utf-8")
    assert "<h2>Summary</h2>" in text and "<h2>Objects</h2>" in text
    assert isinstance(rejected(tmp_path), dict)


def test_a_long_list_of_rejected_frames_is_folded_but_complete(tmp_path):
    (tmp_path / "config.toml").write_text("[run]\nseed = 0\n")
    frames = {f"s/drop0000/f{i:06d}": f"reason {i}" for i in range(25)}
    (tmp_path / "run.json").write_text(json.dumps({"rejected": {"frames": frames}, "stages": []}))
    text = write_report(tmp_path).read_text(encoding="utf-8")
    folded = text[text.index("<details><summary>show all 25"):]
    assert all(f"<td>{k}</td><td>{v}</td>" in folded for k, v in frames.items())
