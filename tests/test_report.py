import re

import imageio.v3 as iio
import numpy as np
import pytest

from mitsuba_active.report import plot_views
from mitsuba_active.rigs import fibonacci_sphere
from mitsuba_active.upright import snapped_up, up_vertical
from tests.conftest import tiny_source


@pytest.mark.parametrize("up", [(0, 1, 0), (0, 0, 1), (1, 0, 0), (0, -1, 0)])
def test_up_is_drawn_vertically_in_a_right_handed_frame(up):
    basis = up_vertical(np.eye(3), up)  # rows: the images of the world axes
    assert np.allclose(up_vertical([up], up), [[0, 0, 1]])
    assert np.allclose(basis @ basis.T, np.eye(3)) and np.linalg.det(basis) == pytest.approx(1.0)


@pytest.mark.parametrize("up", [(0, 0, 1), (0, -1, 0), (1, 0, 0)])
def test_the_up_axis_of_a_camera_rig(up):
    assert np.array_equal(snapped_up(fibonacci_sphere(20, (0, 0, 0), 2.0, up=up)), up)
    assert np.array_equal(snapped_up([]), (0, 1, 0))


def test_camera_plot_of_a_run_with_repeats(tmp_path):
    cams = fibonacci_sphere(12, (0, 0, 0), 2.0)
    path = plot_views(cams[:10], [3, 3, 7, 0], cams[10:], [-0.5] * 3, [0.5] * 3, tmp_path / "views.png",
                      up=(0, 0, 1), initial=2, title="t")
    image = iio.imread(path)
    assert image.ndim == 3 and image.shape[0] > 100 and image.std() > 0
    # Without held-out views or captures (a run that has not chosen anything yet).
    assert plot_views(cams, [], [], [-0.5] * 3, [0.5] * 3, tmp_path / "empty.png").is_file()


def test_metric_plots_draw_the_foreground_psnr_and_the_background_alone(tmp_path, monkeypatch):
    import mitsuba_active.report as report

    drawn, save = {}, report._save

    def keep_lines(fig, path):
        drawn[path.name] = [(line.get_label(), list(line.get_ydata())) for line in fig.axes[0].get_lines()]
        return save(fig, path)

    monkeypatch.setattr(report, "_save", keep_lines)
    new = [{"views": v, "psnr": 20.0 + v, "psnr_fg": 10.0 + v, "floor_psnr": 19.0, "floor_psnr_fg": 8.0,
            "ssim": None, "distance_error": 5.0} for v in (2, 4)]
    old = [{"views": v, "psnr": 21.0, "ssim": None, "distance_error": None} for v in (2, 4)]  # from before floors
    written = report.plot_metrics({"old": old, "new": new}, tmp_path)
    assert sorted(p.name for p in written) == ["distance_error.png", "psnr.png", "psnr_fg.png"]
    assert drawn["psnr.png"] == [("old", [21.0, 21.0]), ("new", [22.0, 24.0]), ("background alone", [19.0, 19.0])]
    assert drawn["psnr_fg.png"] == [("new", [12.0, 14.0]), ("background alone", [8.0, 8.0])]
    assert [label for label, _ in drawn["distance_error.png"]] == ["new"]


def test_atomic_write_leaves_the_file_whole_or_absent(tmp_path):
    import os

    from mitsuba_active.imageio_utils import atomic_write

    target = tmp_path / "a" / "out.json"
    with pytest.raises(KeyboardInterrupt):
        with atomic_write(target) as tmp:
            tmp.write_text("half")
            raise KeyboardInterrupt
    assert not target.exists() and list((tmp_path / "a").iterdir()) == []
    with atomic_write(target) as tmp:
        tmp.write_text("whole")
    assert target.read_text() == "whole" and list((tmp_path / "a").iterdir()) == [target]
    mask = os.umask(0)
    os.umask(mask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~mask  # the usual permissions, not a temp file's 0600


def test_a_replaced_folder_is_whole_before_and_after(tmp_path):
    from mitsuba_active.imageio_utils import replaced_folder

    target = tmp_path / "report"
    target.mkdir()
    (target / "old.md").write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with replaced_folder(target) as folder:
            (folder / "new.md").write_text("half")
            raise KeyboardInterrupt
    assert [p.name for p in tmp_path.iterdir()] == ["report"] and [p.name for p in target.iterdir()] == ["old.md"]
    with replaced_folder(target) as folder:
        (folder / "new.md").write_text("new")
    assert [p.name for p in tmp_path.iterdir()] == ["report"] and [p.name for p in target.iterdir()] == ["new.md"]
    with replaced_folder(tmp_path / "fresh" / "report") as folder:  # a folder that was not there
        (folder / "a.md").write_text("a")
    assert (tmp_path / "fresh" / "report" / "a.md").read_text() == "a"


# -- the one-page HTML report ------------------------------------------------------------------------------------

#: A tiny rfe run: 10 candidates, 3 held-out views, 4 views captured in 2 planned rounds.
TINY_RUN = dict(planner="rfe", budget=4, initial_views=2, ensemble=2, resolution=16, candidates=10, heldout=3, spp=4,
                eval_views=[2, 4], initial_steps=20, steps_per_view=10, eval_steps=30, rays_per_candidate=32,
                field=dict(batch_rays=512, n_samples=32, render_batch=1024))

#: A page reference to anything off the page: a URL with a scheme or a protocol-relative one.
OFF_PAGE = re.compile(r"""(?:src|href)\s*=\s*["']?(?:[a-z]+:)?//|url\(\s*["']?(?:[a-z]+:)?//|@import""", re.I)

CANVAS_INK = """(() => { const c = document.querySelector('#camera-view canvas');
  const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let n = 0;
  for (let i = 0; i < d.length; i += 4)
    if (Math.abs(d[i] - 251) + Math.abs(d[i+1] - 251) + Math.abs(d[i+2] - 251) > 30) n++;
  return n / (c.width * c.height); })()"""

KINDS = "(() => { const k = {}; cameraView.objects.forEach(o => k[o.kind] = (k[o.kind] || 0) + 1); return k; })()"


@pytest.fixture(scope="module")
def browser():
    from tests.browser import Browser

    with Browser() as b:
        yield b


@pytest.fixture(scope="module")
def tiny_run(spot_xml, tmp_path_factory):
    from mitsuba_active.run import Run, RunConfig

    out = tmp_path_factory.mktemp("run") / "r"
    cfg = RunConfig(scene=str(spot_xml), **TINY_RUN)
    source = tiny_source(spot_xml, n_candidates=10, n_heldout=3, resolution=16)
    return out, Run(source, cfg, out, progress=False, log=lambda m: None).execute(), source, cfg


def test_a_run_writes_one_offline_page_that_shows_its_cameras(tiny_run, browser, tmp_path):
    out, rec, _, _ = tiny_run
    page = out / "report.html"
    text = page.read_text()
    assert not OFF_PAGE.search(text) and "<script src" not in text
    browser.open(page.as_uri())
    assert browser.evaluate(KINDS) == {"candidate": 10, "heldout": 3, "captured": 4}
    assert browser.evaluate(CANVAS_INK) > 0.002
    shot = iio.imread(browser.screenshot(tmp_path / "report.png"))
    assert shot.shape[0] > 100 and shot.std() > 10
    # Every image is on the page: 4 captured views, 3 held-out views x 3, 4 plots (PSNR, foreground PSNR,
    # SSIM, distance error).
    images = browser.evaluate("Array.from(document.images).filter(i => i.complete && i.naturalWidth > 0)"
                              ".map(i => i.src.slice(0, 11))")
    assert len(images) == 4 + 3 * 3 + 4 and set(images) == {"data:image/"}
    assert browser.evaluate("document.querySelectorAll('table.metrics tbody tr').length") == len(rec["metrics"])
    # The first round: its scores colour the candidates, and the views captured so far show.
    browser.evaluate("cameraView.setRound(0)")
    first = rec["rounds"][0]
    assert browser.evaluate(KINDS)["captured"] == first["views"]
    scores = browser.evaluate("cameraView.objects.filter(o => o.kind === 'candidate').map(o => o.score)")
    assert np.allclose(scores, first["scores"], rtol=1e-5)
    assert browser.evaluate("cameraView.objects.filter(o => o.picked).map(o => o.index)") == first["picks"]
    assert browser.errors == []


def test_a_run_finished_without_a_page_gets_one(tiny_run):
    from mitsuba_active.run import Run

    out, rec, source, cfg = tiny_run
    page = (out / "report.html").read_text()
    (out / "report.html").unlink()
    Run(source, cfg, out, progress=False, log=lambda m: None).execute()
    assert (out / "report.html").read_text() == page


def test_a_page_of_an_old_record_shows_what_it_holds_and_stays_small(browser, tmp_path):
    """A record from before bounds and rounds were kept, of 20 views at 128x128 of noise (which
    compresses worst), still gets a page, under 5 MB."""
    from mitsuba_active.webpage import write_run_page

    cams = fibonacci_sphere(120, (0, 0, 0), 2.0, width=128, height=128)
    rec = {"config": {"budget": 20, "initial_views": 2, "planner": "rfe"},
           "candidates": [c.to_dict() for c in cams[:100]],
           "heldout": [c.to_dict() for c in cams[100:]], "captured": list(range(0, 100, 5)),
           "metrics": [{"views": 20, "psnr": 20.5, "ssim": None, "distance_error": None}], "finished": True}
    rng = np.random.default_rng(0)
    for n in range(20):
        (tmp_path / "views").mkdir(exist_ok=True)
        iio.imwrite(tmp_path / "views" / f"view_{n:03d}.png", rng.integers(0, 256, (128, 128, 3), dtype=np.uint8))
        (tmp_path / "heldout").mkdir(exist_ok=True)
        for kind in ("pred", "gt", "variance"):
            iio.imwrite(tmp_path / "heldout" / f"heldout_{n:03d}_{kind}.png",
                        rng.integers(0, 256, (128, 128, 3), dtype=np.uint8))
    page = write_run_page(tmp_path, rec)
    assert page.stat().st_size <= 5 * 2**20
    browser.open(page.as_uri())
    assert browser.evaluate(KINDS) == {"candidate": 100, "heldout": 20, "captured": 20}
    assert "no planning rounds" in browser.evaluate("document.querySelector('#camera-view .controls').textContent")
    assert browser.evaluate(CANVAS_INK) > 0.002
    assert browser.errors == []


def test_a_moving_cameras_route_is_drawn_as_it_went(browser, tmp_path):
    """Each leg's recorded route (a detour around the object) is drawn, in the page and in the viewer's
    segments; a leg without one (a record from before routes were kept) is a straight line."""
    from mitsuba_active.camerascene import camera_scene
    from mitsuba_active.viewer import path_segments
    from mitsuba_active.webpage import write_run_page

    cams = fibonacci_sphere(12, (0, 0, 0), 2.0, width=16, height=16)
    captured = [0, 5, 9, 3]
    legs = [{"distance": 0.0, "time": 0.0, "route": [cams[0].position.tolist()] * 2}]
    for a, b in zip(captured[:-1], captured[1:]):
        pa, pb = np.asarray(cams[a].position), np.asarray(cams[b].position)
        detour = (pa + pb) / 2 * 3.0  # well outside the straight line
        legs.append({"distance": 1.0, "time": 1.0, "route": [pa.tolist(), detour.tolist(), pb.tolist()]})
    del legs[-1]["route"]
    rec = {"config": {"budget": 4, "initial_views": 1, "planner": "rfe"},
           "candidates": [c.to_dict() for c in cams[:10]], "heldout": [c.to_dict() for c in cams[10:]],
           "captured": captured, "travel": legs, "metrics": [], "finished": True}
    data = camera_scene(rec)
    segments = path_segments(data, len(captured))
    assert segments.shape == (2 + 2 + 1, 2, 3)
    assert np.allclose(segments[0, 1], data["routes"][1][1]) and data["routes"][3] is None
    browser.open(write_run_page(tmp_path, rec).as_uri())
    assert browser.evaluate("cameraView.routes") == 2
    assert browser.errors == []


def test_a_suite_page_opens_offline_with_its_tables_plots_and_links(browser, tmp_path):
    from mitsuba_active.webpage import write_suite_page

    run = tmp_path / "runs" / "ball" / "rfe_s0"
    run.mkdir(parents=True)
    (run / "report.html").write_text("<!DOCTYPE html><title>the run</title><p>run</p>")
    report = tmp_path / "report"
    (report / "plots" / "ball").mkdir(parents=True)
    iio.imwrite(report / "plots" / "ball" / "psnr.png", np.full((20, 30, 3), 90, np.uint8))
    tables = ["## PSNR\n\n| planner | ball @4 |\n|---|---|\n| rfe | 25.00 |\n| even | 24.00 |\n"]
    page = write_suite_page(report, report, "suite", tables, {"ball": {"rfe": [run], "even": [tmp_path / "gone"]}})
    assert not OFF_PAGE.search(page.read_text())
    browser.open(page.as_uri())
    assert browser.evaluate("document.querySelectorAll('table tbody tr').length") == 2
    assert browser.evaluate("Array.from(document.images).filter(i => i.complete && i.naturalWidth > 0).length") == 1
    links = browser.evaluate("Array.from(document.links).map(a => a.href)")
    assert len(links) == 1  # the run without a page gets no link
    browser.open(links[0])
    assert browser.evaluate("document.title") == "the run"
    assert browser.errors == []


def test_the_pages_markdown_tables():
    from mitsuba_active.webpage import markdown_tables

    page = markdown_tables("## PSNR\n\nOne seed.\n\n| planner | a @4 |\n|---|---|\n| rfe | 1.00 < 2 |\n")
    assert page == ("<h3>PSNR</h3><p>One seed.</p><table><thead><tr><th>planner</th><th>a @4</th></tr></thead>"
                    "<tbody><tr><td>rfe</td><td>1.00 &lt; 2</td></tr></tbody></table>")


# -- the viewer ---------------------------------------------------------------------------------------------------

#: The viewer page's scene tree (viser's), found through React's fibers from the page's root element.
SCENE_TREE = """(() => { const root = document.getElementById('root'); if (!root) return false;
  const key = Object.keys(root).find(k => k.startsWith('__reactContainer')); if (!key) return false;
  const stack = [root[key]];
  while (stack.length) { const f = stack.pop(); if (!f) continue; const v = f.memoizedProps && f.memoizedProps.value;
    if (v && v.useSceneTree && v.useSceneTree.getAll) { window.sceneTree = v.useSceneTree; return true; }
    if (f.child) stack.push(f.child); if (f.sibling) stack.push(f.sibling); }
  return false; })()"""

VIEWER_KINDS = """(() => { const k = {}; Object.entries(sceneTree.getAll()).forEach(([n, node]) => {
  const m = n.match(/^\\/(candidates|heldout|captured)\\/\\d+$/);
  if (m && node && node.message && node.message.type === 'CameraFrustumMessage' && node.visibility !== false)
    k[m[1]] = (k[m[1]] || 0) + 1; }); return k; })()"""


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_viewer_shows_a_run_and_follows_it(tiny_run, browser, tmp_path):
    import json
    import shutil
    import threading

    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")
    from mitsuba_active.viewer import RunViewer

    out, rec, _, _ = tiny_run
    folder = tmp_path / "run"
    shutil.copytree(out, folder)
    # The run as it was after its first round, which --follow sees grow to the whole run.
    first = {**rec, "captured": rec["captured"][:3], "rounds": rec["rounds"][:1], "finished": False,
             "metrics": [m for m in rec["metrics"] if m["views"] <= 3]}
    (folder / "run.json").write_text(json.dumps(first))
    viewer = RunViewer(folder, port=_free_port())
    stop = threading.Event()
    try:
        browser.open(f"http://127.0.0.1:{viewer.port}")
        assert browser.wait_for(SCENE_TREE)
        counts = lambda: browser.evaluate(VIEWER_KINDS)  # noqa: E731
        browser.wait_for(f"({VIEWER_KINDS}).captured === 3")
        assert counts() == {"candidates": 10, "heldout": 3, "captured": 3}
        threading.Thread(target=viewer.follow, args=(stop, 0.05), daemon=True).start()
        (folder / "run.json").write_text(json.dumps(rec))
        browser.wait_for(f"({VIEWER_KINDS}).captured === 4")
        assert counts() == {"candidates": 10, "heldout": 3, "captured": 4}
        # A click on a capture renders the planner's ensemble from it, shown as two images.
        viewer._clicked(("captured", 1))
        assert browser.wait_for("document.querySelectorAll('img').length >= 2")
        shot = iio.imread(browser.screenshot(tmp_path / "viewer.png"))
        box = browser.evaluate("(() => { const r = document.querySelector('canvas').getBoundingClientRect();"
                               " return [r.left, r.top, r.width, r.height]; })()")
        x, y, w, h = (int(v) for v in box)
        assert w > 100 and h > 100 and shot[y:y + h, x:x + w, :3].std() > 10
        assert browser.errors == []
    finally:
        stop.set()
        viewer.close()


@pytest.mark.parametrize("start", [
    "import mitsuba_active.viewer",
    # The command as a user runs it, up to its one-line error on a folder with no run.
    "from mitsuba_active.cli import main\ntry:\n    main(['view', 'no-such-run'], prog_name='mitsuba-active')\n"
    "except SystemExit as exc:\n    assert exc.code == 2, exc.code",
])
def test_the_viewer_opens_without_the_field_or_the_plots(start):
    """Drawing the cameras loads neither the field and its training nor the planners, the benchmark
    runner, trimesh, matplotlib or scipy: they come on the first click (the field) or not at all."""
    import subprocess
    import sys

    heavy = ("mitsuba_active.field", "mitsuba_active.training", "mitsuba_active.run", "mitsuba_active.webpage",
             "mitsuba_active.planners", "mitsuba_active.bench", "trimesh", "matplotlib", "scipy")
    code = f"{start}\nimport sys\nprint([m for m in {heavy!r} if m in sys.modules])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_the_viewers_thumbnails_and_colours(tmp_path):
    from matplotlib import colormaps

    from mitsuba_active.viewer import THUMBNAIL_PX, thumbnail, viridis

    colour = (200, 40, 10)
    rgba = np.tile(np.array(colour + (255,), np.uint8), (2 * THUMBNAIL_PX, 4 * THUMBNAIL_PX, 1))
    iio.imwrite(tmp_path / "v.png", rgba)
    thumb = thumbnail(tmp_path / "v.png")
    assert thumb.shape == (THUMBNAIL_PX // 2, THUMBNAIL_PX, 3) and thumb.dtype == np.uint8
    assert np.abs(thumb.astype(int) - colour).max() <= 1
    assert thumbnail(tmp_path / "missing.png") is None
    # The viewer's viridis, without matplotlib, is matplotlib's to within 5 of 255.
    for t in np.linspace(-0.1, 1.1, 121):
        want = 255 * np.asarray(colormaps["viridis"](float(np.clip(t, 0, 1)))[:3])
        assert np.abs(np.array(viridis(t)) - want).max() <= 5, t


def test_view_refuses_a_folder_without_a_run_or_without_viser(tmp_path, monkeypatch):
    import sys

    from click.testing import CliRunner

    from mitsuba_active.cli import main

    res = CliRunner().invoke(main, ["view", str(tmp_path)])
    assert res.exit_code == 2 and res.output.strip() == f"mitsuba-active: error: {tmp_path} holds no run (no run.json)"
    (tmp_path / "run.json").write_text('{"config": {}}')
    res = CliRunner().invoke(main, ["view", str(tmp_path)])
    assert res.exit_code == 2 and "is not a run record" in res.output
    monkeypatch.setitem(sys.modules, "viser", None)  # as if it were not installed
    rec = {"config": {}, "candidates": [], "heldout": [], "captured": [], "metrics": [], "finished": False}
    (tmp_path / "run.json").write_text(__import__("json").dumps(rec))
    res = CliRunner().invoke(main, ["view", str(tmp_path)])
    assert res.exit_code == 2 and res.output.strip() == ("mitsuba-active: error: the viewer needs viser: "
                                                         "pip install 'mitsuba-active[viewer]'")
