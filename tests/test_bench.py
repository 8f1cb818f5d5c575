import json
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from mitsuba_active.bench import PROFILES, load_suite, plan_jobs, run_suite, unreported_seeds
from mitsuba_active.cli import main
from mitsuba_active.errors import UserError
from mitsuba_active.metrics import distance_error, iqm, psnr, ssim, standard_error
from mitsuba_active.run import RunConfig, field_config


def test_iqm_and_standard_error_by_hand():
    assert iqm([4, 1, 3, 2]) == pytest.approx(2.5)  # middle two of 1..4
    assert iqm(range(1, 9)) == pytest.approx(4.5)  # 3, 4, 5, 6
    assert iqm([1, 2, 3, 4, 100]) == pytest.approx((0.75 * 2 + 3 + 0.75 * 4) / 2.5)  # fractional edges
    assert iqm([7.0]) == 7.0
    assert iqm([1, 2, 10]) == pytest.approx((0.25 * 1 + 2 + 0.25 * 10) / 1.5)
    assert iqm([3, 5]) == pytest.approx(4.0)
    assert standard_error([1, 2, 3, 4]) == pytest.approx(np.sqrt(5 / 3) / 2)
    assert standard_error([3.0]) == 0.0


def test_image_metrics():
    a = np.full((16, 16, 3), 0.5)
    assert psnr(a, a + 0.1) == pytest.approx(20.0)
    assert ssim(a, a) == pytest.approx(1.0)
    assert ssim(a, np.random.default_rng(0).random(a.shape)) < 0.2
    d, m = np.full((4, 4), 2.0), np.zeros((4, 4), bool)
    m[0] = True
    assert distance_error(d * 1.1, d, m) == pytest.approx(10.0)
    # Shapes that numpy would broadcast into a score of something else.
    for metric, pred, target in ((psnr, a, a[..., :1]), (ssim, a, a[:, :, None, 0]), (distance_error, d, d[0])):
        with pytest.raises(ValueError, match="differ in shape"):
            metric(pred, target, *([m] if metric is distance_error else []))


def test_foreground_psnr_by_hand():
    from mitsuba_active.metrics import dilate, foreground_psnr, foreground_radius

    assert [foreground_radius(w) for w in (8, 64, 96, 128, 800)] == [1, 1, 2, 2, 12]
    fg = np.zeros((8, 8), bool)
    fg[3, 3] = fg[0, 7] = True
    grown = np.zeros((8, 8), bool)
    grown[2:5, 2:5] = True  # the 3x3 square around (3, 3)
    grown[0:2, 6:8] = True  # cut off by the image's corner
    assert (dilate(fg, 1) == grown).all() and (dilate(fg, 0) == fg).all()
    assert dilate(fg, 2).sum() == 25 + 9 - 2  # 5x5, 3x3 at the corner, 2 pixels in both
    target = np.full((8, 8, 3), 0.5)
    pred = target.copy()
    pred[2, 2] += 0.1  # next to the foreground: counts
    pred[7, 0] += 0.5  # far from it: does not
    # An 8-pixel image dilates by 1: 9 + 4 pixels of 3 channels, one pixel off by 0.1.
    mse = 3 * 0.1 ** 2 / (13 * 3)
    assert foreground_psnr(pred, target, fg) == pytest.approx(-10 * np.log10(mse))
    assert np.isnan(foreground_psnr(pred, target, np.zeros((8, 8), bool)))
    assert foreground_psnr(target, target, fg) == np.inf
    with pytest.raises(ValueError, match="mask is"):
        foreground_psnr(pred, target, fg[:4])


def _flat_view(rgb, hit, known_empty=None, background=None):
    from mitsuba_active.cameras import Camera
    from mitsuba_active.groundtruth import View

    h, w = hit.shape
    camera = Camera(np.eye(4), width=w, height=h)
    return View(np.asarray(rgb, np.float32), np.where(hit, 1.0, 0.0).astype(np.float32), hit, camera,
                known_empty, background)


def test_the_floor_is_the_background_colour_alone_by_hand():
    """A 4x4 view of one grey pixel on white: the trivial prediction is white, and scores
    the one pixel's error over the image and over its 3x3 dilated foreground."""
    from mitsuba_active.training import background_colour, score_views

    hit = np.zeros((4, 4), bool)
    hit[1, 1] = True
    rgb = np.ones((4, 4, 3))
    rgb[1, 1] = 0.5

    class Grey:  # a field that predicts 0.5 everywhere
        def predict(self, o, d):
            n = len(o)
            return {"rgb_mean": np.full((n, 3), 0.5), "rgb_var": np.zeros((n, 3)), "distance_mean": np.ones(n),
                    "distance_var": np.zeros(n), "opacity": np.ones(n)}

    for view in (_flat_view(rgb, hit), _flat_view(rgb, hit, ~hit, (1.0, 1.0, 1.0))):
        assert background_colour(view) == pytest.approx([1.0, 1.0, 1.0])
        scores, _ = score_views(Grey(), [view])
        assert scores["floor_psnr"] == pytest.approx(-10 * np.log10(0.25 / 16))
        assert scores["floor_psnr_fg"] == pytest.approx(-10 * np.log10(0.25 / 9))
        # The grey field is right on the one pixel, off by 0.5 on the other 15 (8 in the foreground's band).
        assert scores["psnr"] == pytest.approx(-10 * np.log10(0.25 * 15 / 16))
        assert scores["psnr_fg"] == pytest.approx(-10 * np.log10(0.25 * 8 / 9))
    # A rendered view's background: the mean of the pixels whose 3x3 neighbourhood misses (row 3 and column 3).
    rgb[3, :] = 0.2
    rgb[:3, 3] = 0.6
    assert background_colour(_flat_view(rgb, hit)) == pytest.approx(np.full(3, (4 * 0.2 + 3 * 0.6) / 7))
    # A view that sees geometry everywhere: white; one with no foreground has no foreground PSNR.
    assert background_colour(_flat_view(rgb, np.ones((4, 4), bool))) == pytest.approx(np.ones(3))
    scores, _ = score_views(Grey(), [_flat_view(rgb, np.zeros((4, 4), bool))])
    assert scores["psnr_fg"] is None and scores["floor_psnr_fg"] is None and scores["floor_psnr"] is not None


def test_tables_state_the_seed_count_and_mark_cells_with_fewer_seeds():
    from mitsuba_active.bench import _table

    def cell(planner, n):
        st = {"iqm": 20.0 + n, "se": 0.1, "n": n}
        return {"scene": "a", "planner": planner, "seeds": n, "wall_seconds": st,
                **{f"psnr@{v}": st for v in (10, 20)}}

    even = {"cells": [cell("rfe", 3), cell("even", 3)]}
    md, rows = _table(even, ["a"], ["rfe", "even"], "psnr", "PSNR")
    # The CSV prints each figure to its decimals (metrics.DECIMALS), not to a float's 17 digits.
    assert "over 3 seeds" in md and "(3)" not in md and rows[1] == ["rfe", "a", 10, "23.0000", "0.1000", 3]
    uneven = {"cells": [cell("rfe", 3), cell("even", 2)]}
    md, _ = _table(uneven, ["a"], ["rfe", "even"], "psnr", "PSNR")
    assert "n per cell" in md and "23.00 ± 0.10 (3)" in md and "22.00 ± 0.10 (2)" in md
    # One seed has no standard error to show.
    md, _ = _table({"cells": [cell("rfe", 1), cell("even", 1)]}, ["a"], ["rfe", "even"], "psnr", "PSNR")
    assert "One seed (no standard error), at" in md and "| 21.00 |" in md and "±" not in md


def test_tables_of_a_travel_budget_report_where_it_ends():
    from mitsuba_active.bench import _table, metric_at
    from mitsuba_active.bench.stats import travel_budgeted

    stopped = {"metrics": [{"views": 10, "psnr": 20.0}, {"views": 13, "psnr": 21.0}], "stopped": {"views": 13}}
    whole = {"metrics": [{"views": 10, "psnr": 20.0}, {"views": 20, "psnr": 23.0}]}
    assert metric_at(stopped, "psnr", 20) is None and metric_at(stopped, "psnr", 20, at_end=True) == 21.0
    assert metric_at(stopped, "psnr", 10, at_end=True) == 20.0  # a count it reached: its own
    assert metric_at(whole, "psnr", 20, at_end=True) == 23.0
    assert travel_budgeted([SimpleNamespace(config={"travel_budget": 3.0})])
    assert not travel_budgeted([SimpleNamespace(config={"travel_budget": None})])
    st = {"iqm": 21.0, "se": 0.1, "n": 3}
    cells = {"cells": [{"scene": "a", "planner": "rfe", "seeds": 3, **{f"psnr@{v}": st for v in (10, 20)}}],
             "table_views": [10, 20], "budget_end_column": 20}
    md, _ = _table(cells, ["a"], ["rfe"], "psnr", "PSNR")
    assert "| a @10 | a @end (20) |" in md and "the end of the travel budget (at most 20 views" in md


def test_scene_means_margins_and_wins_by_hand():
    from mitsuba_active.bench import _mean_table, scene_means

    def cell(scene, planner, psnr10, psnr20, err):
        values = {"psnr@10": psnr10, "psnr@20": psnr20, "distance_error@10": err, "distance_error@20": err}
        return {"scene": scene, "planner": planner, **{k: {"iqm": x} for k, x in values.items()},
                "per_seed": {"0": values}}

    summary = {"cells": [cell("a", "random", 20, 24, 5.0), cell("a", "even", 21, 25, 4.0), cell("a", "rfe", 23, 24, 6.0),
                         cell("b", "random", 30, 34, 3.0), cell("b", "even", 29, 36, 3.5), cell("b", "rfe", 30.5, 37, 2.0),
                         # A scene without every planner is left out of every mean.
                         cell("c", "rfe", 99, 99, 0.0)]}
    planners = ["random", "even", "rfe"]
    m = scene_means(summary, ["a", "b", "c"], planners, "psnr")
    assert m["rfe"]["scenes"] == 2
    assert m["rfe"]["mean@10"] == pytest.approx(26.75) and m["rfe"]["mean@20"] == pytest.approx(30.5)
    assert m["rfe"]["vs_even@10"] == pytest.approx((2 + 1.5) / 2) and m["rfe"]["wins_vs_even@10"] == 2
    assert m["rfe"]["vs_even@20"] == pytest.approx((-1 + 1) / 2) and m["rfe"]["wins_vs_even@20"] == 1
    assert m["rfe"]["vs_random@10"] == pytest.approx(1.75) and m["rfe"]["wins_vs_random@10"] == 2
    assert "vs_even@10" not in m["even"] and m["even"]["wins_vs_random@10"] == 1
    # Errors: lower is better, so rfe beats even on scene b only.
    e = scene_means(summary, ["a", "b", "c"], planners, "distance_error")
    assert e["rfe"]["vs_even@10"] == pytest.approx((2.0 - 1.5) / 2) and e["rfe"]["wins_vs_even@10"] == 1
    md = _mean_table(m, planners, "PSNR")
    assert "Mean over 2 scenes" in md and "| rfe | 26.75 | 30.50 | +1.75 (2/2) |" in md
    assert "seeds (a suite still running)" not in md
    one = scene_means(summary, ["a"], planners, "psnr")
    assert "Mean over 1 scene of each" in _mean_table(one, planners, "PSNR")


def test_scene_means_while_a_suite_is_still_running():
    from mitsuba_active.bench import _mean_table, scene_means

    def cell(scene, planner, psnr, seeds=3, psnr20="same"):
        psnr20 = psnr if psnr20 == "same" else psnr20
        return {"scene": scene, "planner": planner, "seeds": seeds, "psnr@10": {"iqm": psnr},
                "psnr@20": {"iqm": psnr20}, "per_seed": {"0": {"psnr@10": psnr, "psnr@20": psnr20}}}

    summary = {"cells": [cell("a", "even", 20), cell("a", "rfe", 21, seeds=2),
                         cell("b", "even", 30), cell("b", "rfe", 33),
                         # fisher has finished nothing yet; rfe has no 20-view result on c.
                         cell("a", "fisher", None),
                         cell("c", "even", 25), cell("c", "rfe", 26, psnr20=None)]}
    planners = ["even", "rfe", "fisher"]
    m = scene_means(summary, ["a", "b", "c"], planners, "psnr")
    assert m["rfe"]["scenes"] == 2 and m["rfe"]["vs_even@10"] == pytest.approx(2.0)
    assert m["rfe"]["seeds"] == [2, 3] and m["fisher"]["scenes"] == 0 and m["fisher"]["mean@10"] is None
    md = _mean_table(m, planners, "PSNR")
    assert "| fisher | n/a | n/a | - | - |" in md and "2 to 3 seeds" in md
    # Without a baseline there are no margin columns to explain.
    alone = scene_means(summary, ["a", "b"], ["rfe"], "psnr")
    md = _mean_table(alone, ["rfe"], "PSNR")
    assert "vs " not in md and "| rfe | 27.00 | 27.00 |" in md


def test_margins_pair_the_seeds_both_planners_have_and_ties_are_no_wins():
    from mitsuba_active.bench import _mean_table, scene_means
    from mitsuba_active.metrics import iqm

    def cell(scene, planner, per_seed):
        st = {"iqm": iqm([x for x in per_seed.values() if np.isfinite(x)])}  # as summarize() counts them
        return {"scene": scene, "planner": planner, "seeds": len(per_seed), "psnr@10": st, "psnr@20": st,
                "per_seed": {k: {"psnr@10": x, "psnr@20": x} for k, x in per_seed.items()}}

    summary = {"cells": [
        # rfe has not run seed 3 yet, where even scored high: unpaired, rfe would lead by 0.5 dB only.
        cell("a", "even", {"0": 20.0, "1": 21.0, "2": 22.0, "3": 30.0}), cell("a", "rfe", {"0": 21.0, "1": 22.0,
                                                                                            "2": 23.0}),
        # The same views, scored again: a tie.
        cell("b", "even", {"0": 10.0}), cell("b", "rfe", {"0": 10.0 + 1e-9}),
        # No seed in common: not compared.
        cell("c", "even", {"1": 5.0}), cell("c", "rfe", {"0": 6.0}),
        # A seed without a finite score (NaN: a dataset image's NaN pixels) counts as missing, as in the cells.
        cell("d", "even", {"0": 8.0, "1": 9.0}), cell("d", "rfe", {"0": float("nan"), "1": 9.0})]}
    means = scene_means(summary, ["a", "b", "c", "d"], ["even", "rfe"], "psnr")
    m = means["rfe"]
    assert m["vs_even@10"] == pytest.approx(1 / 3) and m["wins_vs_even@10"] == 1 and m["compared_vs_even@10"] == 3
    assert "+0.33 (1/3) | +0.33 (1/3) |" in _mean_table(means, ["even", "rfe"], "PSNR").split("| rfe | ")[1]


#: The views of a run record made by hand (a record's parts are checked when it is read).
def finished_views(config) -> dict:
    """The views of a finished run record with ``config``'s budget: one candidate, captured budget times."""
    from mitsuba_active.cameras import Camera, look_at

    camera = Camera(look_at([0, 0, 3], [0, 0, 0]), fov=40.0, width=8, height=8).to_dict()
    return {"candidates": [camera], "heldout": [], "captured": [0] * config["budget"]}

TINY_SUITE = """
name = "tiny"
planners = ["even", "rfe"]
[defaults]
candidates = 8
heldout = 2
resolution = 16
spp = 2
budget = 4
initial_views = 2
eval_views = [2, 4]
initial_steps = 10
steps_per_view = 5
eval_steps = 3
rays_per_candidate = 16
field = { batch_rays = 256, n_samples = 16, render_batch = 1024 }
[[scenes]]
name = "ball"
mesh = "ball.ply"
[[scenes]]
name = "simple"
xml = "{simple}"
"""


@pytest.fixture()
def tiny_suite(tmp_path, shared_data):
    import trimesh

    trimesh.creation.icosphere(subdivisions=3).export(tmp_path / "ball.ply")
    path = tmp_path / "tiny.toml"
    path.write_text(TINY_SUITE.replace("{simple}", str(shared_data / "mitsuba/simple/scene.xml")))
    return path


def test_tiny_suite_end_to_end_and_resume(tiny_suite, tmp_path, monkeypatch):
    # Tables report 10 and 20 views in real suites; this one stops at 4 (from 2 initial views), so 4.
    out = tmp_path / "out"
    summary = run_suite(tiny_suite, out, "quick", workers=1, progress=False)
    assert len(summary["cells"]) == 4 and all(c["seeds"] == 1 for c in summary["cells"])
    report = out / "report"
    table = (report / "table_psnr.md").read_text()
    assert "| rfe |" in table and "ball @4" in table and "One seed (no standard error)" in table and "±" not in table
    assert (report / "table_distance_error.csv").is_file() and (report / "results.json").is_file()
    assert "vs even @4" in (report / "table_mean.md").read_text()
    assert json.loads((report / "results.json").read_text())["mean_over_scenes"]["psnr"]["rfe"]["scenes"] == 2
    assert (report / "plots" / "ball" / "psnr.png").is_file() and (report / "plots" / "summary" / "psnr.png").is_file()
    # The foreground PSNR beside the PSNR: its own table in the same layout, its means, its plots.
    fg_table = (report / "table_psnr_fg.md").read_text()
    assert fg_table.startswith("## Foreground held-out PSNR (dB)") and "| rfe |" in fg_table and "ball @4" in fg_table
    fg_rows = (report / "table_psnr_fg.csv").read_text().splitlines()
    assert fg_rows[0] == "planner,scene,views,iqm,se,n" and len(fg_rows) == 1 + 4
    cells = {(c["scene"], c["planner"]): c for c in summary["cells"]}
    for row in fg_rows[1:]:
        planner, scene, views, value = row.split(",")[:4]
        assert float(value) == pytest.approx(cells[(scene, planner)][f"psnr_fg@{views}"]["iqm"], abs=1e-4)
    assert "## Foreground held-out PSNR (dB): mean over scenes" in (report / "table_mean.md").read_text()
    assert (report / "plots" / "ball" / "psnr_fg.png").is_file()
    assert (report / "plots" / "summary" / "psnr_fg.png").is_file()
    # The suite's page: its tables, its plots inlined, and a link to each run's page.
    page = (report / "report.html").read_text()
    links = re.findall(r'href="([^"]+)"', page)
    assert len(links) == 4 and all(link.endswith("/report.html") and (report / link).is_file() for link in links)
    assert "<th>planner</th>" in page and page.count('src="data:image/png;base64,') == len(list(report.rglob("*.png")))
    assert all(set(c["per_seed"]) == {"0"} and c["per_seed"]["0"]["psnr@4"] == c["psnr@4"]["iqm"]
               for c in summary["cells"])
    # With rfe's run of one scene missing, the summary averages the other scene alone, as
    # table_mean.md does, and each planner keeps its colour.
    import mitsuba_active.bench.tables as tables_module

    plots = []
    monkeypatch.setattr(tables_module, "plot_metrics", lambda series, out, title="", bands=None, colors=None:
                        plots.append((title, {p: [r["views"] for r in rows] for p, rows in series.items()}, colors)))
    hidden = out / "runs" / "simple" / "rfe-seed0"
    hidden.rename(tmp_path / "hidden")
    run_suite(tiny_suite, out, "quick", progress=False, report_only=True)
    (tmp_path / "hidden").rename(hidden)
    titles = [t for t, _, _ in plots]
    assert titles == ["ball", "simple", "tiny: mean over 1 scene"], titles
    assert plots[1][1] == {"even": [2, 4]} and plots[2][1] == {"even": [2, 4], "rfe": [2, 4]}
    assert all(colors == {"even": "C0", "rfe": "C1"} for _, _, colors in plots)
    monkeypatch.undo()
    # Resume: finished runs are skipped, not redone.
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("run.json")}
    calls = []
    from mitsuba_active.run import Run

    monkeypatch.setattr(Run, "execute", lambda self: calls.append(1))
    run_suite(tiny_suite, out, "quick", workers=1, progress=False)
    assert calls == [] and stamps == {p: p.stat().st_mtime_ns for p in out.rglob("run.json")}
    rec = json.loads(next(out.rglob("run.json")).read_text())
    assert rec["finished"] and rec["wall_seconds"] > 0
    # Planning time (choosing views, training the planner's ensemble) is a part of the run's.
    records = {p.parent.name: json.loads(p.read_text()) for p in out.rglob("run.json")}
    assert all(0 < r["planning_seconds"] < r["wall_seconds"] for r in records.values())
    assert "| planning (s) | wall time (s) |" in table
    # A report of what is finished, running nothing (seed 1 was never run).
    summary = run_suite(tiny_suite, out, "quick", seeds=[0, 1], progress=False, report_only=True)
    assert calls == [] and all(c["seeds"] == 1 for c in summary["cells"])
    assert summary["runs"] == 2 * summary["runs_reported"] == 2 * len(summary["cells"])
    res = CliRunner().invoke(main, ["bench", str(tiny_suite), "--out", str(out), "--seeds", "0,1", "--report-only"])
    assert res.exit_code == 0 and f"covers {len(summary['cells'])} of the suite's {summary['runs']} runs" in res.output
    # The tiny suite's 3 evaluation steps leave its fields no better than the background alone.
    assert (f"in {summary['runs_reported']} of the reported runs the evaluation field scores less than 3 dB above "
            "the background colour alone") in res.output
    # Reported with the profile's seed alone, the folder's other seed is named.
    res = CliRunner().invoke(main, ["bench", str(tiny_suite), "--out", str(out), "--seeds", "1", "--report-only"])
    assert res.exit_code == 0 and "holds finished runs of seed 0, which this report leaves out" in res.output
    assert unreported_seeds(plan_jobs(load_suite(tiny_suite), out, "quick", seeds=[0, 1], author=False)) == []
    # Runs kept across an upgrade are reported, and the mix of versions is named.
    one = next(out.rglob("run.json"))
    rec = json.loads(one.read_text())
    rec["versions"]["drjit"] = "0.0.1"
    one.write_text(json.dumps(rec))
    res = CliRunner().invoke(main, ["bench", str(tiny_suite), "--out", str(out), "--report-only"])
    assert res.exit_code == 0 and "made with 2 different versions" in res.output, res.output
    assert not list(out.rglob("*seed1*"))
    # A report of one scene replaces the earlier report whole: no plots of the other scene stay.
    run_suite(tiny_suite, out, "quick", scenes=["simple"], progress=False, report_only=True)
    assert sorted(p.name for p in (report / "plots").iterdir()) == ["simple", "summary"]
    assert "ball" not in (report / "table_psnr.md").read_text()
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []
    # With nothing finished (seed 2 alone) the report there stays as it was.
    table = (report / "table_psnr.md").read_text()
    summary = run_suite(tiny_suite, out, "quick", seeds=[2], progress=False, report_only=True)
    assert summary["cells"] == [] and (report / "table_psnr.md").read_text() == table


def test_worker_processes_show_mitsubas_warnings_as_plain_lines(tiny_suite, tmp_path, capfd):
    xml = tmp_path / "egg.xml"
    xml.write_text('<scene version="3.0.0"><emitter type="constant"/><shape type="sphere"><transform '
                   'name="to_world"><scale x="0.3" y="0.5" z="0.3"/></transform><bsdf type="diffuse"/></shape></scene>')
    tiny_suite.write_text(re.sub(r'name = "simple"\nxml = ".*"', f'name = "egg"\nxml = "{xml}"', tiny_suite.read_text()))
    capfd.readouterr()
    run_suite(tiny_suite, tmp_path / "out", "quick", workers=2, planners=["even"], scenes=["egg"], progress=False)
    out, err = capfd.readouterr()
    assert "\x1b" not in out + err and "WARN" not in out, out
    assert "mitsuba-active: warning: [Sphere] 'to_world' transform shouldn't contain non-uniform scaling!" in err


@pytest.mark.parametrize("workers", [1, 2])
def test_a_failed_run_leaves_no_folder_behind(tiny_suite, tmp_path, workers):
    from mitsuba_active.bench import parse_overrides

    # Training diverges before the run has a record to resume from (its first views are written by then).
    out = tmp_path / "out"
    with pytest.raises(UserError, match="diverged"):
        run_suite(tiny_suite, out, "quick", workers=workers, planners=["rfe"], scenes=["ball"], progress=False,
                  overrides=parse_overrides(["field.lr=1e38", "initial_steps=30"]))
    assert not list(out.glob("runs/ball/rfe-seed*"))


def test_suite_runs_in_worker_processes(tiny_suite, tmp_path):
    out = tmp_path / "out"
    summary = run_suite(tiny_suite, out, "quick", workers=2, planners=["even"], progress=False)
    assert {(c["scene"], c["planner"]) for c in summary["cells"]} == {("ball", "even"), ("simple", "even")}
    records = [json.loads(p.read_text()) for p in out.rglob("run.json")]
    assert len(records) == 2 and all(r["finished"] and len(r["captured"]) == 4 for r in records)


@pytest.mark.parametrize("text, message", [
    ("planners = ['oracle']\n[[scenes]]\nmesh='x.obj'\n", "unknown planner"),
    ("[[scenes]]\nname='a'\n", "exactly one"),
    ("[defaults]\npace = 3\n[[scenes]]\nmesh='x.obj'\n", "unknown settings"),
    # The scenes, planners and --seeds name the runs: not settings.
    ("[defaults]\nseed = 3\n[[scenes]]\nmesh='x.obj'\n", "unknown settings in \\[defaults\\]: seed"),
    ("[[scenes]]\nmesh='x.obj'\nplanner='rfe'\n", "unknown settings: planner"),
    ("[defaults]\nfield = 3\n[[scenes]]\nmesh='x.obj'\n", "'field' must be a table"),
    ("name = [", "malformed"),
    ("planer = ['rfe']\n[default]\nbudget = 4\n[[scenes]]\nmesh='x.obj'\n", "unknown keys default, planer"),
    ("planners = 'rfe'\n[[scenes]]\nmesh='x.obj'\n", "planners must be a list"),
    # A scene's name makes its folders: it may not lead out of the suite's.
    ("[[scenes]]\nname='../../escaped'\nmesh='x.obj'\n", "name '../../escaped' cannot name a scene's folders"),
    ("[[scenes]]\nname='..'\nmesh='x.obj'\n", "cannot name a scene's folders"),
    # ... nor split the CSV and Markdown tables' cells or a --scenes list, nor take the summary plots' folder.
    ("[[scenes]]\nname='ball, big'\nmesh='x.obj'\n", r"name 'ball, big' cannot name .*no '/', '\\', ',' or '\|'"),
    ("[[scenes]]\nname='a|b'\nmesh='x.obj'\n", "name 'a|b' cannot name"),
    ("[[scenes]]\nname=' '\nmesh='x.obj'\n", "name ' ' cannot name .* no space at either end"),
    ("[[scenes]]\nname='summary'\nmesh='x.obj'\n", "name 'summary' cannot name .* or 'summary'"),
    ("name = 1979-05-27\n[[scenes]]\nmesh='x.obj'\n", "name must be a text \\(the suite's title\\), got datetime"),
    ("[[scenes]]\nxml='s.xml'\ncolor=[1, 0, 0]\nfloor=true\n", "scene 's': color, floor dress a mesh; an xml scene"),
    ("defaults = 3\n[[scenes]]\nmesh='x.obj'\n", "defaults must be a table of settings"),
    ("scenes = [1, 2]\n", "scenes must be tables"),
    ("[[scenes]]\nxml = 5\n", "scene #1: xml must be a file's path, got 5"),
    ("[[scenes]]\nmesh = ['x']\n", "scene #1: mesh must be a file's path"),
    (b"name = '\xff'\n", "malformed suite file .*utf-8"),
    ("planners = []\n[[scenes]]\nmesh='x.obj'\n", "the suite has no planners"),
    ("name = " + "[" * 100_000 + "]" * 100_000 + "\n", "malformed suite file .*nested too deeply"),
])
def test_bad_suites(tmp_path, text, message):
    bad = tmp_path / "bad.toml"
    bad.write_bytes(text) if isinstance(text, bytes) else bad.write_text(text)
    with pytest.raises(UserError, match=message):
        load_suite(bad)


def test_a_scene_named_by_its_file_may_end_in_a_space(tmp_path):
    (tmp_path / "spot .obj").write_text("")
    (tmp_path / "s.toml").write_text("[[scenes]]\nmesh = 'spot .obj'\n")
    assert load_suite(tmp_path / "s.toml").scenes[0].name == "spot "


def test_a_setting_nested_past_pythons_stack_is_text():
    from mitsuba_active.checks import setting_value

    deep = "[" * 3000 + "]" * 3000
    assert setting_value(deep) == deep


def test_a_suite_file_may_start_with_a_byte_order_mark(tmp_path):
    (tmp_path / "x.obj").write_text("")
    (tmp_path / "s.toml").write_bytes("\ufeffname = 'bom'\n[[scenes]]\nmesh = 'x.obj'\n".encode("utf-8"))
    assert load_suite(tmp_path / "s.toml").name == "bom"


def test_a_suites_texture_is_named_relative_to_the_suite(tmp_path, monkeypatch):
    (tmp_path / "x.obj").write_text("")
    (tmp_path / "s.toml").write_text("[[scenes]]\nmesh = 'x.obj'\ntexture = 't.png'\n")
    monkeypatch.chdir("/")
    assert load_suite(tmp_path / "s.toml").scenes[0].scene_options["texture"] == str(tmp_path / "t.png")


def test_a_suite_folder_with_stale_or_damaged_runs_is_refused_before_anything_runs(tiny_suite, tmp_path,
                                                                                   shared_data):
    import shutil

    shutil.copytree(shared_data / "mitsuba/simple", tmp_path / "simple")
    text = tiny_suite.read_text().replace(str(shared_data / "mitsuba/simple/scene.xml"), "simple/scene.xml")
    tiny_suite.write_text(text)
    out = tmp_path / "out"
    run_suite(tiny_suite, out, "quick", planners=["even"], progress=False)
    runs = out / "runs"
    # An edited mesh scene: --report-only refuses the old runs as a run of the suite does (it left them out
    # of nothing and reported them as current).
    tiny_suite.write_text(text.replace('mesh = "ball.ply"', 'mesh = "ball.ply"\ncolor = [0.9, 0.1, 0.1]'))
    for report_only in (True, False):
        with pytest.raises(UserError, match="the runs of scene 'ball' .* were made with another version of it"):
            run_suite(tiny_suite, out, "quick", planners=["even"], progress=False, report_only=report_only)
    tiny_suite.write_text(text)
    # Other settings, an edited xml scene, and a damaged record: refused before the new seed's runs start,
    # and by --report-only, which would otherwise report a mix or leave runs out.
    from mitsuba_active.bench import parse_overrides

    xml = tmp_path / "simple" / "scene.xml"
    for report_only in (True, False):
        with pytest.raises(UserError, match="even-seed0: holds a run with other settings"):
            run_suite(tiny_suite, out, "quick", planners=["even"], seeds=[1, 0], progress=False,
                      report_only=report_only, overrides=parse_overrides(["eval_steps=25"]))
        xml.write_text(xml.read_text().replace("0.9 0.9 0.0", "0.9 0.5 0.0"))
        with pytest.raises(UserError, match="simple/even-seed0: holds a run of scene 'simple' made with another"):
            run_suite(tiny_suite, out, "quick", planners=["even"], seeds=[1, 0], progress=False,
                      report_only=report_only)
        shutil.copy(shared_data / "mitsuba/simple/scene.xml", xml)
        record = runs / "simple" / "even-seed0" / "run.json"
        kept = record.read_bytes()
        record.write_text("{")
        with pytest.raises(UserError, match="even-seed0/run.json is damaged .*; remove it to start over"):
            run_suite(tiny_suite, out, "quick", planners=["even"], seeds=[1, 0], progress=False,
                      report_only=report_only)
        record.write_bytes(kept)
    assert not list(runs.glob("*/even-seed1"))


def test_a_suite_scene_authored_anew_keeps_its_file_names_and_reports(tiny_suite, tmp_path):
    """Edited, with its runs removed, a mesh scene is authored over its own old files, so that
    --report-only, which authors it into a copy of its folder, finds the runs' scene."""
    import shutil

    out = tmp_path / "out"
    run_suite(tiny_suite, out, "quick", planners=["even"], scenes=["ball"], progress=False)
    tiny_suite.write_text(tiny_suite.read_text().replace('mesh = "ball.ply"', 'mesh = "ball.ply"\nup = "z"'))
    shutil.rmtree(out / "runs")
    run_suite(tiny_suite, out, "quick", planners=["even"], scenes=["ball"], progress=False)
    assert sorted(f.name for f in (out / "scenes" / "ball").iterdir()) == ["ball.ply", "ball.xml"]
    summary = run_suite(tiny_suite, out, "quick", planners=["even"], scenes=["ball"], progress=False,
                        report_only=True)
    assert len(summary["cells"]) == 1


def test_a_suite_scene_that_is_no_xml_file_is_refused(tmp_path, shared_data):
    import shutil

    shutil.copy(shared_data / "mitsuba/simple/scene.xml", tmp_path / "scene.txt")
    (tmp_path / "s.toml").write_text("[[scenes]]\nxml = 'scene.txt'\n")
    with pytest.raises(UserError, match="'scene.txt' is not a Mitsuba scene file"):
        load_suite(tmp_path / "s.toml")


def test_a_scene_that_cannot_load_stops_the_suite_before_anything_is_authored_or_run(tiny_suite, tmp_path):
    from mitsuba_active.bench import plan_jobs

    (tmp_path / "broken.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\n")
    (tmp_path / "missing_mesh.xml").write_text(
        '<scene version="3.0.0"><shape type="obj"><string name="filename" value="nowhere.obj"/></shape></scene>')
    for entry, message in (('mesh = "broken.ply"', "scene 'late': cannot read mesh"),
                           ('xml = "missing_mesh.xml"', "scene 'late': ")):
        suite = tmp_path / "late.toml"
        suite.write_text(tiny_suite.read_text() + f'[[scenes]]\nname = "late"\n{entry}\n')
        with pytest.raises(UserError, match=message):
            plan_jobs(load_suite(suite), tmp_path / "out", "quick")
        assert not (tmp_path / "out").exists()  # the ball scene before it was not authored either


def test_missing_suite(tmp_path):
    with pytest.raises(UserError, match="not found"):
        load_suite(tmp_path / "none.toml")


def test_jobs_merge_field_options_and_check_types(tmp_path, shared_data):
    from mitsuba_active.bench import PROFILES, plan_jobs

    path = tmp_path / "s.toml"
    xml = shared_data / "mitsuba/simple/scene.xml"
    path.write_text(f"[defaults]\nfield = {{ lr = 0.02 }}\n[[scenes]]\nxml = '{xml}'\n")
    job = plan_jobs(load_suite(path), tmp_path / "out", "quick", planners=["even"])[0]
    assert job.config["field"] == {**PROFILES["quick"]["field"], "lr": 0.02}
    path.write_text(f"[defaults]\nbudget = '20'\n[[scenes]]\nxml = '{xml}'\n")
    with pytest.raises(UserError, match="scene 'scene': budget must be a whole number, got '20'"):
        plan_jobs(load_suite(path), tmp_path / "out", "quick")
    with pytest.raises(UserError, match="no scene named nope"):
        plan_jobs(load_suite(path), tmp_path / "out", "quick", scenes=["nope"])


def test_finished_runs_count_only_with_the_jobs_settings(tmp_path, shared_data):
    from mitsuba_active.bench import collect, finished_record, plan_jobs

    path = tmp_path / "s.toml"
    path.write_text(f"[[scenes]]\nname = 'simple'\nxml = '{shared_data / 'mitsuba/simple/scene.xml'}'\n")
    job = plan_jobs(load_suite(path), tmp_path / "out", "quick", planners=["even"])[0]
    rec_path = tmp_path / "out" / "runs" / "simple" / "even-seed0" / "run.json"
    rec_path.parent.mkdir(parents=True)
    assert job.content_hash
    rec = {"finished": True, "config": job.config, "content_hash": job.content_hash, "metrics": [],
           **finished_views(job.config)}
    rec_path.write_text(json.dumps(rec))
    assert finished_record(job) is not None and collect([job]) == {"simple": {"even": [rec]}}
    # The same folder after the suite's settings changed: neither skipped nor reported.
    rec_path.write_text(json.dumps({**rec, "config": {**job.config, "budget": 12}, **finished_views({"budget": 12})}))
    assert finished_record(job) is None and collect([job]) == {}
    # ... or after the scene changed (its files, not its settings).
    rec_path.write_text(json.dumps({**rec, "content_hash": "0" * 64}))
    assert finished_record(job) is None
    # A scene named by another path is the same scene when its content is.
    rec_path.write_text(json.dumps({**rec, "config": {**job.config, "scene": "moved/scene.xml"}}))
    assert finished_record(job) is not None


def test_finished_runs_match_with_a_relative_or_absolute_folder(tmp_path, shared_data, monkeypatch):
    from mitsuba_active.bench import finished_record, plan_jobs

    import trimesh

    trimesh.creation.icosphere(subdivisions=1).export(tmp_path / "ball.ply")
    path = tmp_path / "s.toml"
    path.write_text("[[scenes]]\nname = 'ball'\nmesh = 'ball.ply'\n")
    suite = load_suite(path)
    monkeypatch.chdir(tmp_path)
    rel = plan_jobs(suite, Path("out"), "quick", planners=["even"], author=False)[0]
    absolute = plan_jobs(suite, tmp_path / "out", "quick", planners=["even"], author=False)[0]
    assert rel.config["scene"] != absolute.config["scene"]  # the mesh scene's XML lives in the folder
    rec_path = tmp_path / "out" / "runs" / "ball" / "even-seed0" / "run.json"
    rec_path.parent.mkdir(parents=True)
    rec_path.write_text(json.dumps({"finished": True, "config": rel.config, "metrics": [],
                                    **finished_views(rel.config)}))
    assert finished_record(absolute) is not None
    # Another scene file is another setting.
    other = {**rel.config, "scene": "elsewhere/ball.xml"}
    rec_path.write_text(json.dumps({"finished": True, "config": other, "metrics": [], **finished_views(other)}))
    assert finished_record(absolute) is None


def test_set_overrides_parse_as_toml_values():
    from mitsuba_active.bench import parse_overrides

    got = parse_overrides(["ensemble=4", "field.lr=0.02", "field.n_samples = 16", "eval_views=[5, 10]",
                           "planner_options.form=log", "rig=interior", "fov=40.5"])
    assert got == {"ensemble": 4, "field": {"lr": 0.02, "n_samples": 16}, "eval_views": [5, 10],
                   "planner_options": {"form": "log"}, "rig": "interior", "fov": 40.5}
    assert isinstance(got["ensemble"], int) and isinstance(got["field"]["lr"], float)
    # plan's --planner-option reads its values the same way.
    from mitsuba_active.cli.plan import _parse_options

    got = _parse_options(["form=log", "lam=.5", "probes=2", "flag=false", "angles=[10, 20]", "name=x y"])
    assert got == {"form": "log", "lam": 0.5, "probes": 2, "flag": False, "angles": [10, 20], "name": "x y"}
    assert isinstance(got["probes"], int) and got["flag"] is False


@pytest.mark.parametrize("item, message", [
    ("ensemble", "KEY=VALUE"),
    ("pace=3", "unknown setting 'pace'"),
    ("seed=1", "choose them with --seeds"),
    ("planner=rfe", "choose them with --planners"),
    ("field=3", "unknown setting 'field'"),
    ("budget.x=3", "unknown setting 'budget.x'"),
])
def test_bad_set_overrides(item, message):
    from mitsuba_active.bench import parse_overrides

    with pytest.raises(UserError, match=message):
        parse_overrides([item])


@pytest.mark.parametrize("items", [["ensemble=2", "ensemble=4"], ["field.lr=0.1", "field.lr=0.2"]])
def test_a_setting_given_twice_is_refused(items):
    from mitsuba_active.bench import parse_overrides

    with pytest.raises(UserError, match="given twice"):
        parse_overrides(items)
    assert parse_overrides(["field.lr=0.1", "planner_options.lr=0.2", "ensemble=2"])  # one each: fine
    for first in ("budget=3", "rig=interior"):  # a setting, then a table entry under its name
        with pytest.raises(UserError, match="unknown setting"):
            parse_overrides([first, first.split("=")[0] + ".x=1"])


def test_set_overrides_win_over_the_suite_and_bad_ones_write_nothing(tmp_path, shared_data):
    from mitsuba_active.bench import parse_overrides, plan_jobs

    path = tmp_path / "s.toml"
    path.write_text("[defaults]\nensemble = 3\nfield = { lr = 0.02 }\n"
                    "[[scenes]]\nname = 'ball'\nmesh = 'ball.ply'\nensemble = 5\n"
                    "planner_options = { form = 'log' }\n")
    import trimesh

    trimesh.creation.icosphere(subdivisions=1).export(tmp_path / "ball.ply")
    suite = load_suite(path)
    job = plan_jobs(suite, tmp_path / "out", "quick", planners=["rfe"],
                    overrides=parse_overrides(["ensemble=4", "field.n_samples=8"]))[0]
    assert job.config["ensemble"] == 4 and job.config["planner_options"] == {"form": "log"}
    assert job.config["field"] == {"batch_rays": 2048, "n_samples": 8, "lr": 0.02}
    assert (tmp_path / "out" / "scenes" / "ball" / "ball.xml").is_file()
    for bad, message in ((["field.lr=-1"], "lr must be > 0"), (["field.bogus=1"], "unknown field option"),
                         (["field.distance_weight=10"], "not as the field option field.distance_weight"),
                         (["planner_options.lam=2"], "unknown option lam"),
                         (["budget='x'"], "budget must be a whole number"),
                         # A suite's scenes are scenes: what `plan` refuses for one, a suite refuses too.
                         (["downscale=2"], "scene 'ball': downscale applies to datasets"),
                         (["eval_views=[0, 4]"], "eval_views must be a list of positive view counts")):
        with pytest.raises(UserError, match=message):
            plan_jobs(suite, tmp_path / "bad", "quick", planners=["rfe"], overrides=parse_overrides(bad))
        assert not (tmp_path / "bad").exists()


def test_a_seed_or_planner_named_twice_is_one_run(tmp_path, shared_data):
    from mitsuba_active.bench import plan_jobs

    path = tmp_path / "s.toml"
    path.write_text(f"planners = ['even', 'rfe', 'even']\n[[scenes]]\nxml = '{shared_data / 'mitsuba/simple/scene.xml'}'\n")
    jobs = plan_jobs(load_suite(path), tmp_path / "out", "quick", seeds=[1, 0, 1])
    assert [(j.planner, j.seed) for j in jobs] == [("even", 1), ("even", 0), ("rfe", 1), ("rfe", 0)]
    jobs = plan_jobs(load_suite(path), tmp_path / "out", "quick", planners=["rfe", "rfe"], seeds=[2, 2])
    assert [(j.planner, j.seed) for j in jobs] == [("rfe", 2)]


def test_bundled_suite_is_well_formed():
    from tests.conftest import REPO

    suite = load_suite(REPO / "benchmarks" / "suites" / "shared.toml")
    assert len([s for s in suite.scenes if s.kind == "mesh"]) >= 6
    assert {s.name for s in suite.scenes if s.kind == "xml"} == {"simple", "cbox"}
    assert all(s.path.is_dir() if s.kind == "dataset" else s.path.is_file() for s in suite.scenes)


def test_outside_suite_holds_what_the_bundled_suite_does_not():
    from tests.conftest import REPO

    bundled = load_suite(REPO / "benchmarks" / "suites" / "shared.toml")
    outside = load_suite(REPO / "benchmarks" / "suites" / "outside.toml")
    assert all(s.kind == "mesh" and s.path.is_file() for s in outside.scenes)
    seen = {(s.path, s.run_options.get("rig", "sphere")) for s in bundled.scenes}
    # Each scene is a mesh the suite leaves out, or a suite mesh under another rig.
    assert not {(s.path, s.run_options.get("rig", "sphere")) for s in outside.scenes} & seen
    assert {s.path for s in outside.scenes} - {s.path for s in bundled.scenes}


def test_interior_distance_suite_differs_only_by_the_distance_loss():
    from mitsuba_active.run import INTERIOR_DISTANCE_WEIGHT
    from tests.conftest import REPO

    # It measures the weight that `plan` suggests for rooms.
    suite = load_suite(REPO / "benchmarks" / "suites" / "interior_distance.toml")
    plain, with_distance = suite.scenes
    assert plain.path == with_distance.path and plain.path.is_file()
    assert plain.run_options == {"rig": "interior"}
    assert with_distance.run_options == {"rig": "interior", "distance_weight": INTERIOR_DISTANCE_WEIGHT}


def _spawned_workers(parent: int) -> list[int]:
    """Process ids of the multiprocessing workers that ``parent`` has spawned (Linux /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            if ppid == parent and b"spawn_main" in (entry / "cmdline").read_bytes():
                found.append(int(entry.name))
        except (OSError, ValueError, IndexError):
            continue
    return found


@pytest.mark.parametrize("when", ["starting", "running"])
def test_ctrl_c_stops_parallel_workers_cleanly(tiny_suite, tmp_path, when):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it)
    during ``bench --workers 2``, while the workers start or while they run:
    one line, exit 130, no traceback or leaked-semaphore warning, no
    temporary files (in the suite or the ground-truth cache)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out, cache = tmp_path / "out", tmp_path / "cache"
    # Long runs, so that the suite is still running when it is interrupted.
    cmd = [sys.executable, "-m", "mitsuba_active", "bench", str(tiny_suite), "--out", str(out), "--workers", "2",
           "--quiet", "--set", "steps_per_view=100000"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env={**os.environ, "MITSUBA_ACTIVE_CACHE": str(cache)})
    deadline = time.monotonic() + 120
    if when == "starting":  # as soon as both workers exist: they are still importing
        while len(_spawned_workers(proc.pid)) < 2 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.02)
        time.sleep(0.2)
    else:
        while not list(out.glob("runs/*/*/run.json")) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
        time.sleep(1.0)
    os.killpg(proc.pid, signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:  # never leave a suite running behind a failed test
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert err.strip().splitlines()[-1] == "mitsuba-active: interrupted", err
    assert "leaked" not in err and "Traceback" not in err, err
    assert not [p for p in out.rglob(".*")] and not [p for p in cache.rglob(".*")]


def test_a_changed_suite_is_refused_before_anything_is_replaced(tiny_suite, tmp_path):
    """Runs made with other scene options or settings are not mixed in: the
    suite is refused up front, and the authored scene stays as its runs saw it."""
    out = tmp_path / "out"
    run_suite(tiny_suite, out, "quick", planners=["even"], scenes=["ball"], progress=False)
    xml = next((out / "scenes").rglob("*.xml"))
    before = xml.read_bytes()
    text = tiny_suite.read_text()
    tiny_suite.write_text(text.replace('mesh = "ball.ply"', 'mesh = "ball.ply"\nfloor = true'))
    with pytest.raises(UserError, match="another version of it"):
        run_suite(tiny_suite, out, "quick", planners=["even"], scenes=["ball"], progress=False)
    assert xml.read_bytes() == before and not [p for p in out.rglob(".*")]
    tiny_suite.write_text(text.replace("eval_steps = 3", "eval_steps = 25"))
    with pytest.raises(UserError, match=r"other settings \(eval_steps: 3 -> 25\)"):
        run_suite(tiny_suite, out, "quick", planners=["even"], scenes=["ball"], progress=False)
    # Undone, the suite is the same again: its finished run counts.
    tiny_suite.write_text(text)
    assert len(run_suite(tiny_suite, out, "quick", planners=["even"], scenes=["ball"], progress=False)["cells"]) == 1
    # A larger budget is no other suite: its runs go on from the views they have.
    rec_path = next(out.rglob("run.json"))
    before = json.loads(rec_path.read_text())
    lines = []
    summary = run_suite(tiny_suite, out, "quick", planners=["even"], scenes=["ball"], progress=False,
                        overrides={"budget": 5}, log=lines.append)
    assert lines == ["1 of the suite's runs finished earlier with a smaller budget: they go on from the views "
                     "they have"]
    after = json.loads(rec_path.read_text())
    assert after["captured"][:4] == before["captured"] and len(after["captured"]) == 5 and after["finished"]
    assert summary["runs_reported"] == 1 and summary["table_views"] == [4, 5]
    for table in ("table_psnr.md", "table_mean.md"):  # a table copied elsewhere keeps the setting
        assert "Every run with --set budget=5." in (out / "report" / table).read_text()
    with pytest.raises(UserError, match=r"other settings \(budget: 5 -> 4: fewer than the 5 views it has captured\)"):
        run_suite(tiny_suite, out, "quick", planners=["even"], scenes=["ball"], progress=False)


def test_a_suite_runs_a_planner_file_beside_it_in_worker_processes(tiny_suite, tmp_path, monkeypatch):
    from mitsuba_active.bench import load_suite, plan_jobs, run_job
    from tests.test_planners import PLANNER_FILE

    (tmp_path / "mine.py").write_text(PLANNER_FILE)
    tiny_suite.write_text(tiny_suite.read_text().replace('["even", "rfe"]', '["even", "mine.py:Last"]'))
    monkeypatch.chdir(tmp_path.parent)  # the file is found beside the suite, not in the current folder
    out = tmp_path / "out"
    summary = run_suite(tiny_suite, out, "quick", workers=2, scenes=["ball"], planners=["even", "mine.py:Last"],
                        progress=False)
    assert {c["planner"] for c in summary["cells"]} == {"even", "mine.py:Last"}
    rec = json.loads((out / "runs" / "ball" / "mine.py_Last-seed0" / "run.json").read_text())
    assert rec["finished"] and rec["planner_digest"] is not None
    assert "| mine.py:Last |" in (out / "report" / "table_psnr.md").read_text()
    # Runs made with other code are refused, as runs of an edited scene are...
    (tmp_path / "mine.py").write_text(PLANNER_FILE + "\n# edited\n")
    with pytest.raises(UserError, match="holds runs made with another version of the planner's code \\(mine.py:Last"):
        run_suite(tiny_suite, out, "quick", workers=1, scenes=["ball"], progress=False)
    # ... and a suite stops when the code changes while it runs.
    jobs = plan_jobs(load_suite(tiny_suite), tmp_path / "out2", "quick", planners=["mine.py:Last"], scenes=["ball"])
    (tmp_path / "mine.py").write_text(PLANNER_FILE)
    with pytest.raises(UserError, match="changed while the suite ran"):
        run_job(jobs[0])
    assert not (tmp_path / "out2" / "runs").exists()
    # Two files whose names make one folder name would share tables and folders.
    (tmp_path / "my planner.py").write_text(PLANNER_FILE)
    (tmp_path / "my_planner.py").write_text(PLANNER_FILE)
    both = '"my planner.py:Last", "my_planner.py:Last"]'
    tiny_suite.write_text(tiny_suite.read_text().replace('"mine.py:Last"]', both))
    with pytest.raises(UserError, match="my planner.py:Last and my_planner.py:Last would share run folders"):
        run_suite(tiny_suite, tmp_path / "out3", "quick", scenes=["ball"], progress=False)
    assert not (tmp_path / "out3").exists()


def test_a_failed_job_stops_the_workers_without_tracebacks(tiny_suite, tmp_path):
    import subprocess
    import sys

    (tmp_path / "wrong.py").write_text("from mitsuba_active.planners import Planner\n"
                                      "class Wrong(Planner):\n"
                                      "    def select(self, state, batch):\n"
                                      "        return [3]\n")
    tiny_suite.write_text(tiny_suite.read_text().replace('["even", "rfe"]', '["wrong.py:Wrong"]'))
    proc = subprocess.run([sys.executable, "-m", "mitsuba_active", "bench", str(tiny_suite), "--workers", "2",
                           "--out", str(tmp_path / "out"), "--quiet"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    # Idle workers that the failure stops exit at once, not through an exception in their exit handlers.
    assert proc.stderr.strip().splitlines() == [
        "mitsuba-active: error: the wrong.py:Wrong planner answered list: select(state, batch) must return "
        "(indices, scores): 1 candidate indices (whole numbers) in [0, 8), and 8 scores or None"], proc.stderr


def test_tables_report_the_largest_view_count_and_the_one_nearest_half_of_it():
    from dataclasses import asdict

    from mitsuba_active.bench import Job, table_views
    from mitsuba_active.run import RunConfig

    def jobs(budget, counts):
        cfg = asdict(RunConfig(scene="s.xml", budget=budget, eval_views=counts))
        return [Job("s", "even", 0, "s.xml", cfg, "o")]

    assert table_views(jobs(20, [5, 10, 15, 20])) == (10, 20)
    # A suite taken on to a larger budget reports it, not 20.
    assert table_views(jobs(40, [5, 10, 15, 20, 30, 40])) == (20, 40)
    assert table_views(jobs(30, [5, 10, 15, 20])) == (15, 30)
    assert table_views(jobs(6, [2, 4, 6])) == (4, 6)  # 2 and 4 are as near 3: the later one says more
    assert table_views(jobs(9, [2, 3, 9])) == (3, 9)
    # The initial views (2) are the same for every planner: nothing to compare.
    assert table_views(jobs(4, [2, 4])) == (4,) and table_views(jobs(5, [2, 4])) == (4, 5)


def test_a_suite_run_again_says_which_runs_it_keeps(tiny_suite, tmp_path):
    out = tmp_path / "out"
    lines = []
    run_suite(tiny_suite, out, "quick", planners=["even"], scenes=["simple"], progress=False, log=lines.append)
    assert lines == []
    run_suite(tiny_suite, out, "quick", planners=["even"], scenes=["simple"], progress=False, log=lines.append)
    assert lines == ["1 of the suite's 1 runs finished earlier with these settings: kept, not run again"]


def test_a_suite_compares_variants_of_one_planner(tiny_suite, tmp_path):
    """A planners entry may be a variant with options of its own: its own
    table row and run folders, beside the planners of the suite."""
    text = tiny_suite.read_text().replace(
        'planners = ["even", "rfe"]',
        'planners = ["even", "rfe", { name = "rfe-log", planner = "rfe", options = { form = "log" } }]')
    tiny_suite.write_text(text)
    suite = load_suite(tiny_suite)
    assert [p.name for p in suite.planners] == ["even", "rfe", "rfe-log"]
    jobs = plan_jobs(suite, tmp_path / "out", "quick", scenes=["simple"], author=False)
    options = {j.planner: (j.config["planner"], j.config["planner_options"], Path(j.out).name) for j in jobs}
    assert options == {"even": ("even", {}, "even-seed0"), "rfe": ("rfe", {}, "rfe-seed0"),
                       "rfe-log": ("rfe", {"form": "log"}, "rfe-log-seed0")}
    summary = run_suite(tiny_suite, tmp_path / "out", "quick", planners=["rfe-log", "even"], scenes=["simple"],
                        progress=False)
    assert {c["planner"] for c in summary["cells"]} == {"rfe-log", "even"}
    assert "| rfe-log |" in (tmp_path / "out" / "report" / "table_psnr.md").read_text()
    rec = json.loads((tmp_path / "out" / "runs" / "simple" / "rfe-log-seed0" / "run.json").read_text())
    assert rec["planner_options"]["form"] == "log"
    # --set cannot turn a variant into another planner that keeps its name; the same value is no change.
    with pytest.raises(UserError, match=r"planner 'rfe-log' sets form = 'log' itself; --set planner_options.form = "
                                        r"'sum' would run another planner under its name"):
        plan_jobs(suite, tmp_path / "o2", "quick", planners=["rfe-log"], author=False,
                  overrides={"planner_options": {"form": "sum"}})
    assert len(plan_jobs(suite, tmp_path / "o2", "quick", planners=["rfe-log"], author=False,
                         overrides={"planner_options": {"form": "log"}})) == 2


def test_suite_planners_are_named_in_any_case(tiny_suite, tmp_path):
    variant = '{ name = "rfe-log", planner = "Rfe", options = { form = "log" } }'
    text = tiny_suite.read_text()
    tiny_suite.write_text(text.replace('planners = ["even", "rfe"]', f'planners = ["EVEN", {variant}]'))
    suite = load_suite(tiny_suite)
    assert [(p.name, p.ref) for p in suite.planners] == [("even", "even"), ("rfe-log", "rfe")]
    jobs = plan_jobs(suite, tmp_path / "o", "quick", planners=["RFE-LOG", "Random"], author=False)
    assert {j.planner for j in jobs} == {"rfe-log", "random"}
    with pytest.raises(UserError, match=re.escape("unknown planner 'rfe-lgo' (did you mean 'rfe-log'?)")):
        plan_jobs(suite, tmp_path / "o", "quick", planners=["rfe-lgo"], author=False)
    tiny_suite.write_text(tiny_suite.read_text().replace('"EVEN"', '"evn"'))
    with pytest.raises(UserError, match=re.escape("unknown planner 'evn' (did you mean 'even'?)")):
        load_suite(tiny_suite)


@pytest.mark.parametrize("entry,message", [
    ('{ name = "a/b", planner = "rfe" }', "planner variant name 'a/b'"),
    ('{ name = "x" }', "a planner variant is a table such as"),
    ('{ name = "x", planner = "rfe", options = 3 }', "a planner variant is a table such as"),
    ('{ name = "x", planner = "rfe", lr = 3 }', "a planner variant is a table such as"),
    ('3', "a planners entry is a planner's name or a table"),
    ('{ name = "even", planner = "rfe" }', "two planners are named even"),
    ('{ name = "x", planner = "nope" }', "unknown planner 'nope'"),
])
def test_bad_planner_variants_are_refused_in_one_line(tiny_suite, entry, message):
    tiny_suite.write_text(tiny_suite.read_text().replace('planners = ["even", "rfe"]', f'planners = ["even", {entry}]'))
    with pytest.raises(UserError, match=re.escape(message)):
        load_suite(tiny_suite)


def test_a_variants_options_are_checked_before_anything_runs(tiny_suite, tmp_path):
    tiny_suite.write_text(tiny_suite.read_text().replace(
        'planners = ["even", "rfe"]', 'planners = [{ name = "rfe-x", planner = "rfe", options = { lam = 1 } }]'))
    with pytest.raises(UserError, match="planner 'rfe-x': .*unknown option lam"):
        plan_jobs(load_suite(tiny_suite), tmp_path / "out", "quick")
    assert not (tmp_path / "out").exists()


def test_bench_field_sets_every_runs_preset(tiny_suite, tmp_path, monkeypatch):
    import mitsuba_active.cli.bench as cli_module

    seen = {}

    def fake_run_suite(suite, out, profile, *args, overrides=None, **kw):
        seen.update(out=out, overrides=overrides)
        return {"unreported_seeds": [], "cells": [], "runs_reported": 0, "runs": 0, "short_training": 0,
                "versions": []}

    monkeypatch.setattr(cli_module, "run_suite", fake_run_suite)
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(main, ["bench", str(tiny_suite), "--field", "fast"])
    assert res.exit_code == 0, res.output
    assert seen["overrides"] == {"field_preset": "fast"} and "fast" in str(seen["out"])
    res = CliRunner().invoke(main, ["bench", str(tiny_suite), "--field", "fast", "--set", "field_preset=default"])
    assert res.exit_code == 2 and "given twice" in res.output
    # The quick profile trains the fast preset, the full one the default.
    assert PROFILES["quick"]["field_preset"] == "fast" and "field_preset" not in PROFILES["full"]
    assert RunConfig().field_preset == "default"
    # At the full profile's resolution the default preset is the multi-level field, not fast's two grids.
    full = field_config(RunConfig(resolution=PROFILES["full"]["resolution"]), planner=False)
    assert full.n_levels > field_config(RunConfig(resolution=64), planner=False).n_levels == 2


def test_an_unknown_field_preset_is_one_line_and_writes_nothing(tiny_suite, tmp_path):
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["bench", str(tiny_suite), "--out", str(out), "--set", "field_preset=huge"])
    assert res.exit_code == 2 and not out.exists()
    assert res.output.strip().splitlines() == [
        "mitsuba-active: error: scene 'ball': unknown field preset 'huge'; choose one of fast, default"]
