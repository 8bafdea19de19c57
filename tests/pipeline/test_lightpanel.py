"""The report's lighting panel (pipeline/lightpanel.py, drawn by pipeline/report_html.py) on a real run folder.

The run folder is the test room of tests/pipeline/raster_scenes.py (photos, cameras, room mesh as ingest writes
them). Lights put at known places are checked where the pictures show them, against positions worked out here
from the room's own pixels and a pinhole projection written out by hand; a real two-view fit checks the
colours and levels the panel draws.
"""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from pipeline.report_html import write_report
from pipeline.trace.lightfit import RoomLights

ALBEDO = (0.5, 0.25, 0.05)        # the room's fitted albedo: orange, told apart from markers, text and background
RED, GREEN, BLUE = (255, 0, 0), (0, 255, 0), (0, 0, 255)
# in view of the first photo (under the table top), left of its view, behind its camera (at (0.1, -1.3, 1.1))
IN_VIEW, LEFT, BEHIND = (0.35, 0.1, 0.5), (-1.9, 0.0, 0.3), (0.12, -1.95, 1.1)


@pytest.fixture(scope="module")
def room_run(tmp_path_factory):
    """A run folder with an ingested scan (3 photos) and nothing else."""
    from pipeline.render_gl import shared_rasterizer
    from tests.pipeline import raster_scenes as S

    rd = tmp_path_factory.mktemp("lightpanel") / "RUN"
    S.make_run(rd, shared_rasterizer(), frames=3, drops=1)
    (rd / "config.toml").write_text('[run]\nseed = 0\n[trace]\nlighting = "fit"\n')
    return rd


def _copy(run, tmp_path):
    out = tmp_path / "RUN"
    shutil.copytree(run, out)
    return out


def _known_lights(run) -> RoomLights:
    """The room mesh with ALBEDO and three emitters at known places (red, green, blue, brightest first)."""
    from pipeline.runfolder import load_room_mesh, load_scan

    v, f, _ = load_room_mesh(load_scan(run, "room"))
    emitters = [{"centre": list(c), "area_m2": 0.01, "radiance": list(rgb), "power_share": share, "kind": "lamp"}
                for c, rgb, share in ((IN_VIEW, (20.0, 0, 0), 0.6), (LEFT, (0, 20.0, 0), 0.3),
                                      (BEHIND, (0, 0, 20.0), 0.1))]
    summary = {"fitted": True, "note": "", "emitters": emitters, "num_lights": 3, "seen_side": 1, "frames": 3,
               "albedo_level": [0.5, 0.25, 0.05], "albedo_mean": [0.5, 0.25, 0.05], "residual_median": 0.123}
    n = len(v)
    return RoomLights(vertices=np.asarray(v, np.float32), faces=np.asarray(f, np.int32),
                      radiance=np.full((n, 3), 0.3, np.float32), light_tri=np.zeros(len(f), bool),
                      num_mesh_vertices=n, num_mesh_tris=len(f), summary=summary,
                      albedo=np.tile(np.float32(ALBEDO), (n, 1)))


def _rgb(path):
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    return img[..., ::-1].astype(np.int64)


def _centroid(img, rgb, tol=40):
    m = np.all(np.abs(img - np.array(rgb)) <= tol, axis=2)
    rows, cols = np.nonzero(m)
    assert m.sum() > 0, f"no pixel of colour {rgb}"
    return np.array([cols.mean(), rows.mean()]), m


@pytest.fixture(scope="module")
def known(room_run, tmp_path_factory):
    run = _copy(room_run, tmp_path_factory.mktemp("known"))
    (run / "trace" / "room").mkdir(parents=True)
    _known_lights(run).save(run / "trace" / "room" / "lights.npz")
    text = write_report(run).read_text(encoding="utf-8")
    return run, text


def test_a_light_at_a_known_place_is_drawn_there_from_above(known):
    """The room (4.02 m square, walls included) fills the orange part of the top view; the red light at
    (0.35, 0.1) is a disc centred where that square puts it, the green one at (-1.9, 0.0) left of it: seen
    from above, x to the right and y up the picture."""
    run, _ = known
    img = _rgb(run / "report" / "lighting" / "room_top.png")
    orange = (img[..., 0] > img[..., 1] + 15) & (img[..., 1] > img[..., 2] + 15) & (img[..., 0] > 60)
    rows, cols = np.nonzero(orange)
    c0, c1, r0, r1 = cols.min(), cols.max(), rows.min(), rows.max()
    assert abs((c1 - c0) - (r1 - r0)) <= 2          # a square room is square on the picture

    def expected(x, y):
        return np.array([c0 + (x + 2.01) / 4.02 * (c1 - c0), r1 - (y + 2.01) / 4.02 * (r1 - r0)])

    for centre, rgb in ((IN_VIEW, RED), (LEFT, GREEN)):
        got, _ = _centroid(img, rgb)
        assert np.linalg.norm(got - expected(*centre[:2])) < 1.5, (rgb, got, expected(*centre[:2]))
    big, small = _centroid(img, RED)[1].sum(), _centroid(img, GREEN)[1].sum()
    assert big > 1.5 * small                        # the disc's area follows the power share (0.6 vs 0.3)


def test_a_light_in_view_is_a_ring_where_the_camera_sees_it(known):
    from pipeline.lightpanel import STRIP_PX
    from pipeline.runfolder import load_scan

    run, text = known
    scan = load_scan(run, "room")
    K, T = scan.K[0], scan.T_c2w[0]
    R, t = T[:3, :3], T[:3, 3]
    x, y, z = R.T @ (np.array(IN_VIEW) - t)         # world -> camera by hand
    u, v = K[0, 0] * x / z + K[0, 2], K[1, 1] * y / z + K[1, 2]
    s = 480 / scan.width
    want = np.array([(u + 0.5) * s - 0.5, (v + 0.5) * s - 0.5 + STRIP_PX])
    img = _rgb(run / "report" / "lighting" / f"room_frame{int(scan.frame_ids[0]):06d}.png")
    assert img.shape[1] == 480 and z > 0
    got, _ = _centroid(img, RED, tol=60)
    assert np.linalg.norm(got - want) < 1.5, (got, want)


def test_a_light_outside_the_photo_is_an_arrow_at_its_border(known):
    """The green light, left of the camera's view, is an arrow whose head touches the left border; the blue
    one, behind the camera and below its eye line for a camera looking down, an arrow at the bottom. The
    emitter table says which is where."""
    from pipeline.lightpanel import STRIP_PX

    run, text = known
    img = _rgb(run / "report" / "lighting" / "room_frame000000.png")[STRIP_PX:]
    h, w = img.shape[:2]
    _, green = _centroid(img, GREEN, tol=50)
    cols = np.nonzero(green)[1]
    assert cols.max() < 60 and cols.min() < 14, (cols.min(), cols.max())
    _, blue = _centroid(img, BLUE, tol=50)
    rows = np.nonzero(blue)[0]
    assert rows.min() > h - 60 and rows.max() > h - 14, (rows.min(), rows.max(), h)
    table = text[text.index("listed emitters"):]
    row = lambda k: table[table.index(f"<td class=num>{k}</td>"):].split("</tr>")[0]  # noqa: E731
    assert "in view" in row(1) and "outside" in row(2) and "behind" in row(3)


def test_the_panel_says_what_the_fit_found(known):
    _, text = known
    section = text[text.index("<h2>Lighting</h2>"):]
    assert "3 sampled as lights: 3 lamps" in section and "12%" in section and "0.50, 0.25, 0.05" in section
    assert section.count('<a href="report/lighting/') == 3      # top view, first and last photo
    assert "Traceback" not in section and "could not be drawn" not in section


def test_same_run_same_pictures(known, tmp_path):
    run, _ = known
    before = {p.name: p.read_bytes() for p in (run / "report" / "lighting").iterdir()}
    write_report(run)
    after = {p.name: p.read_bytes() for p in (run / "report" / "lighting").iterdir()}
    assert before == after and all(len(b) > 1000 for b in after.values())


def test_without_fitted_lights_the_section_is_one_line(room_run, tmp_path):
    run = _copy(room_run, tmp_path)
    text = write_report(run).read_text(encoding="utf-8")
    section = text[text.index("<h2>Lighting</h2>"):text.index("</section>", text.index("<h2>Lighting</h2>"))]
    assert "No fitted lights yet" in section and section.count("<p") == 1
    assert not (run / "report" / "lighting").exists()
    (run / "config.toml").write_text('[run]\nseed = 0\n[trace]\nlighting = "scan"\n')
    text = write_report(run).read_text(encoding="utf-8")
    assert 'No fitted lights: trace.lighting is "scan"' in text


def test_a_fit_that_fell_back_says_why_and_still_shows_the_room(room_run, tmp_path):
    """The fit's fallback (no albedo, no emitters): the note is the result, the room is shown in the mesh's
    own colours."""
    import dataclasses

    run = _copy(room_run, tmp_path)
    rl = _known_lights(run)
    note = "no colour photos: lit by the mesh colours alone, holes at their mean radiance"
    rl = dataclasses.replace(rl, albedo=None, summary={"fitted": False, "note": note, "emitters": [],
                                                       "frames": 0, "seen_side": 1})
    (run / "trace" / "room").mkdir(parents=True)
    rl.save(run / "trace" / "room" / "lights.npz")
    text = write_report(run).read_text(encoding="utf-8")
    assert f"<td>result</td><td>not fitted: {note}</td>" in text and "0 sampled as lights" in text
    top = _rgb(run / "report" / "lighting" / "room_top.png")
    grey = np.all(top == top[..., :1], axis=2) & (top[..., 0] > 60)
    assert grey.mean() > 0.3                        # the room in its (grey) radiance, nothing fitted over it


def test_unreadable_lights_are_one_line_and_earlier_pictures_go(known, tmp_path, capsys):
    """A damaged lights.npz: `scansynth report` still writes the page (exit 0, no traceback), the section
    says the file cannot be read, and the pictures of an earlier invocation are removed."""
    from pipeline.cli import main

    run = _copy(known[0], tmp_path)
    assert any((run / "report" / "lighting").iterdir())
    (run / "trace" / "room" / "lights.npz").write_bytes(b"not an npz")
    assert main(["report", str(run), "-q"]) == 0
    assert "Traceback" not in capsys.readouterr().err
    text = (run / "report.html").read_text(encoding="utf-8")
    assert "The fitted lights in trace/room/lights.npz cannot be read" in text
    assert not (run / "report" / "lighting").exists()


# --- a real fit: two views of a room lit by a hanging lamp (tests/pipeline/test_lightfit.py's scene) -------------

@pytest.fixture(scope="module")
def two_view_fit():
    from pipeline.trace.lightfit import FitSettings, fit_room_lights
    from tests.pipeline.test_lightfit import UP, hanging_lamp_photos, open_room

    v, f, _ = open_room()
    colors, fr = hanging_lamp_photos(v, f, (0.3, -0.2, 1.7), 400.0)
    return fit_room_lights(v, f, colors, fr[:2], up=UP, rng=np.random.default_rng(3),
                           settings=FitSettings(points=800, stride=2, cell=0.4))


def test_a_few_view_capture_draws_the_light_it_renders_with(two_view_fit):
    """Two views take white light at the camera's level (pipeline/trace/lightfit/capture.py): the panel draws
    the radiance of the lamps the tracer samples."""
    from pipeline.lightpanel import emitters_of

    rl = two_view_fit
    assert "capture_prior" in rl.summary
    nv = rl.num_mesh_vertices
    quads = rl.vertices[nv:].reshape(-1, 4, 3).astype(np.float64)    # the box's cells and the lamps, 4 corners each
    quad_rad = rl.radiance[nv:].reshape(-1, 4, 3).mean(axis=1)
    lamps = [e for e in emitters_of(rl.summary) if e.kind == "lamp"]
    assert lamps
    for e in lamps:
        j = np.argmin(np.linalg.norm(quads.mean(axis=1) - e.centre, axis=1))
        assert np.linalg.norm(quads[j].mean(axis=0) - e.centre) < 2e-3
        np.testing.assert_allclose(e.radiance, quad_rad[j], rtol=1e-2)


def test_a_real_fit_in_a_run_folder_gives_the_panel(room_run, two_view_fit, tmp_path):
    run = _copy(room_run, tmp_path)
    (run / "trace" / "room").mkdir(parents=True)
    two_view_fit.save(run / "trace" / "room" / "lights.npz")
    text = write_report(run).read_text(encoding="utf-8")
    section = text[text.index("<h2>Lighting</h2>"):]
    assert "2 views cannot pin the light" in section and "what few views cannot pin" in section
    assert "their colour (R, G, B; the largest 1)</td><td>1.00, 1.00, 1.00" in section
    pics = sorted((run / "report" / "lighting").iterdir())
    assert [p.name for p in pics] == ["room_frame000000.png", "room_frame000020.png", "room_top.png"]
    assert all(_rgb(p).std() > 5 for p in pics)
    summary = json.loads(json.dumps(two_view_fit.summary))
    assert f"{summary['num_lights']} sampled as lights" in section
