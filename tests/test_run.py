"""The acquisition loop: reproducibility, resume, outputs, export, and RFE's preference for the unseen."""

import dataclasses
import json
import re

import imageio.v3 as iio
import numpy as np
import pytest
from click.testing import CliRunner

from mitsuba_active.cli import main
from mitsuba_active.datasets import opengl_to_mitsuba
from mitsuba_active.errors import UserError
from mitsuba_active.export import export_transforms
from mitsuba_active.run import Run, RunConfig
from tests.conftest import tiny_source, two_sensor_xml

TINY = dict(budget=4, initial_views=2, ensemble=2, resolution=16, candidates=10, heldout=3, spp=4,
            eval_views=[2, 4], initial_steps=20, steps_per_view=10, eval_steps=30, rays_per_candidate=32,
            field=dict(batch_rays=512, n_samples=32, render_batch=1024))


@pytest.fixture(scope="module")
def source(spot_xml):
    return tiny_source(spot_xml, n_candidates=10, n_heldout=3, resolution=16)


def _run(source, out, planner="rfe", **kw):
    cfg = RunConfig(scene=str(source.scene.path), planner=planner, **{**TINY, **kw})
    return Run(source, cfg, out, progress=False, log=lambda m: None).execute()


def test_seeded_runs_are_reproducible(source, tmp_path):
    a = _run(source, tmp_path / "a", seed=5)
    b = _run(source, tmp_path / "b", seed=np.int64(5))  # a seed from np.arange is the same seed
    assert a["captured"] == b["captured"] and b["config"]["seed"] == 5
    # Multi-threaded gradient accumulation may reorder float additions: equal up to rounding.
    assert np.allclose([r["scores"] for r in a["rounds"]], [r["scores"] for r in b["rounds"]], rtol=1e-3)
    assert np.allclose([m["psnr"] for m in a["metrics"]], [m["psnr"] for m in b["metrics"]], atol=0.05)
    c = _run(source, tmp_path / "c", seed=6)
    assert c["captured"] != a["captured"] or c["metrics"] != a["metrics"]


def test_train_on_without_views(source):
    from mitsuba_active.run import make_ensemble, train_on

    ens = make_ensemble(source, RunConfig(scene=str(source.scene.path), field=TINY["field"]), 1, seed=0)
    assert train_on(ens, [], 0).shape == (0,)
    with pytest.raises(ValueError, match=r"train_on: no views to train on \(5 steps asked for\)"):
        train_on(ens, [], 5)
    with pytest.raises(UserError, match="steps must be a whole number"):
        train_on(ens, [source.candidate_view(0)], -1)


def test_acquisition_steps_follow_the_schedule():
    from mitsuba_active.training import acquisition_steps

    assert acquisition_steps(0, 2, 200, 50) == 300  # the initial views
    assert acquisition_steps(2, 1, 200, 50) == 50
    assert acquisition_steps(0, 1, 200, 50) == 250  # a first pick without initial views
    assert acquisition_steps(0, 0, 200, 50) == 0
    with pytest.raises(ValueError, match="view counts must be whole numbers >= 0"):
        acquisition_steps(-1, 1, 200, 50)


@pytest.mark.parametrize("initial_views", [2, 0])
def test_a_runs_ensemble_trains_initial_steps_then_steps_per_view(source, tmp_path, initial_views):
    cfg = RunConfig(scene=str(source.scene.path), planner="rfe", **{**TINY, "initial_views": initial_views,
                                                                    "eval_views": [4]})
    run = Run(source, cfg, tmp_path / "r", progress=False, log=lambda m: None)
    run.execute()
    assert run.ensemble._step == cfg.initial_steps + cfg.steps_per_view * cfg.budget


def test_a_run_that_diverges_after_its_first_record_says_resuming_would_diverge_again(source, tmp_path,
                                                                                      monkeypatch):
    from mitsuba_active.errors import TrainingDiverged
    from mitsuba_active.field import Ensemble

    train, calls = Ensemble.train, []

    def diverges_third(self, steps, progress=False):
        calls.append(steps)
        if len(calls) == 3:
            raise TrainingDiverged("training diverged at step 40 (loss nan)")
        return train(self, steps, progress)

    monkeypatch.setattr(Ensemble, "train", diverges_third)
    with pytest.raises(TrainingDiverged, match=r"^training diverged at step 40 \(loss nan\); resumed, .*r would "
                                               "diverge again: remove it, or choose another run folder"):
        _run(source, tmp_path / "r")
    # Before the first record, the run folder goes (the command removes it) and the message stays as it is.
    calls[:] = [0, 0]
    with pytest.raises(TrainingDiverged, match=r"^training diverged at step 40 \(loss nan\)$"):
        _run(source, tmp_path / "fresh")


def test_random_picks_do_not_replay_the_initial_views(source, tmp_path):
    """The planner's stream is not the one the initial views came from: with 2
    of 10 candidates captured, ``random``'s first pick repeats one of them in
    about 20 % of seeds (it did in over half while the streams were shared)."""
    from mitsuba_active.planners import PlanningState

    repeats = 0
    for seed in range(200):
        cfg = RunConfig(scene=str(source.scene.path), planner="random", **{**TINY, "seed": seed})
        run = Run(source, cfg, tmp_path, progress=False, log=lambda m: None)
        run.env.reset(seed=seed, options={"initial_views": 2})
        picks, _ = run.planner.select(PlanningState(source.candidates, run.env.captured, rng=run.rng), 1)
        repeats += picks[0] in run.env.captured
    assert 15 <= repeats <= 65  # 40 expected by chance


def test_run_writes_its_outputs(source, tmp_path):
    rec = _run(source, tmp_path / "r")
    out = tmp_path / "r"
    assert rec["finished"] and len(rec["captured"]) == 4 and [m["views"] for m in rec["metrics"]] == [2, 4]
    assert len(rec["rounds"]) == 2 and all(len(r["scores"]) == 10 for r in rec["rounds"])
    for name in ("run.json", "metrics.csv", "psnr.png", "distance_error.png", "chosen_views.png",
                 "camera_views.png", "views/view_003.png", "views/view_003.exr", "heldout/heldout_002_pred.png",
                 "heldout/heldout_002_gt.exr", "heldout/heldout_002_variance.png"):
        assert (out / name).is_file(), name
    assert (out / "metrics.csv").read_text().splitlines()[0].startswith("views,psnr,psnr_fg,ssim,distance_error")
    assert not [p for p in out.rglob(".*")]  # no temporary files left


def test_fisher_trains_only_the_member_it_scores(source, tmp_path):
    from mitsuba_active.field import Ensemble

    rec = _run(source, tmp_path / "f", planner="fisher", ensemble=2)
    assert rec["finished"] and len(rec["captured"]) == 4
    assert Ensemble.load(str(tmp_path / "f" / rec["ensemble_file"])).n_members == 1
    # One field has no spread across members: no variance images.
    assert not list((tmp_path / "f" / "heldout").glob("*_variance.*"))


def test_interrupted_run_resumes_without_redoing_rounds(source, tmp_path, monkeypatch):
    from mitsuba_active.planners.simple import EvenPlanner

    full = _run(source, tmp_path / "full", planner="even", budget=6, eval_views=[3, 6])
    calls = {"n": 0}
    original = EvenPlanner.select

    def flaky(self, state, batch):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return original(self, state, batch)

    monkeypatch.setattr(EvenPlanner, "select", flaky)
    with pytest.raises(KeyboardInterrupt):
        _run(source, tmp_path / "cut", planner="even", budget=6, eval_views=[3, 6])
    partial = json.loads((tmp_path / "cut" / "run.json").read_text())
    assert len(partial["captured"]) == 4 and not partial["finished"]
    # A view file cut short by the interruption is written again on resume.
    damaged = tmp_path / "cut" / "views" / "view_003.png"
    damaged.write_bytes(damaged.read_bytes()[:20])
    # Started with another Mitsuba: the run goes on, and says so.
    assert partial["versions"] == full["versions"] and set(full["versions"]) >= {"mitsuba_active", "mitsuba", "drjit"}
    partial["versions"]["mitsuba"] = "0.0.1"
    (tmp_path / "cut" / "run.json").write_text(json.dumps(partial))
    calls["n"] = 10
    with pytest.warns(UserWarning, match="was started with mitsuba 0.0.1; it goes on with mitsuba "):
        resumed = _run(source, tmp_path / "cut", planner="even", budget=6, eval_views=[3, 6])
    assert resumed["resumed_with"] == [full["versions"]]
    assert calls["n"] == 12  # only the two missing rounds ran
    assert resumed["captured"] == full["captured"]
    assert [m["views"] for m in resumed["metrics"]] == [3, 6]
    assert damaged.read_bytes() == (tmp_path / "full" / "views" / "view_003.png").read_bytes()
    # Other settings in the same folder are refused, not mixed in.
    from mitsuba_active.errors import UserError

    with pytest.raises(UserError, match="other settings"):
        _run(source, tmp_path / "cut", planner="even", budget=5)


def test_a_finished_run_goes_on_to_a_larger_budget(source, tmp_path):
    """Extended, a run captures what a run made with the larger budget captures."""
    from mitsuba_active.errors import UserError

    # The initial views alone (no round, no saved ensemble), then one round more, then another.
    _run(source, tmp_path / "r", budget=2)
    short = _run(source, tmp_path / "r", budget=3)
    # Made with another Mitsuba: going on says so, as a resumed run does.
    (tmp_path / "r" / "run.json").write_text(json.dumps({**short, "versions": {**short["versions"], "mitsuba": "0"}}))
    with pytest.warns(UserWarning, match="was started with mitsuba 0; it goes on with mitsuba "):
        extended = _run(source, tmp_path / "r", budget=4)
    assert extended["resumed_with"] == [short["versions"]]
    fresh = _run(source, tmp_path / "fresh", budget=4)
    assert extended["finished"] and extended["captured"][:3] == short["captured"]
    assert extended["captured"] == fresh["captured"]
    assert np.allclose([r["scores"] for r in extended["rounds"]], [r["scores"] for r in fresh["rounds"]], rtol=1e-3)
    # It keeps its score at the earlier budget.
    assert [m["views"] for m in extended["metrics"]] == [2, 3, 4]
    assert np.isclose(extended["metrics"][-1]["psnr"], fresh["metrics"][-1]["psnr"], atol=0.05)
    assert extended["budget_changes"] == [{"from": 2, "to": 3, "views": 2}, {"from": 3, "to": 4, "views": 3}]
    assert extended["config"]["budget"] == 4
    assert extended["ensemble_file"] == "ensemble_004.npz" and not (tmp_path / "r" / "ensemble_003.npz").exists()
    assert len(list((tmp_path / "r" / "views").glob("*.png"))) == 4
    # Fewer views than it has captured cannot be taken back.
    with pytest.raises(UserError, match=r"other settings \(budget: 4 -> 3: fewer than the 4 views it has "
                                        r"captured\)"):
        _run(source, tmp_path / "r", budget=3)


def test_a_run_taken_on_after_a_short_round_says_its_rounds_differ(source, tmp_path):
    def run(budget):
        lines = []
        cfg = RunConfig(scene=str(source.scene.path), planner="even", **{**TINY, "budget": budget, "batch": 2})
        Run(source, cfg, tmp_path / "r", progress=False, log=lines.append).execute()
        return lines

    run(3)  # 2 initial views, then a round of 1
    lines = run(5)
    assert "resuming" in lines[0] and "3 of 5 views captured (the budget was 3)" in lines[0], lines
    assert lines[1] == ("note: its last round captured fewer than 2 views, so its rounds from here differ from "
                        "those of a run made with a budget of 5 from the start"), lines


def test_the_field_preset_is_part_of_a_runs_settings(source, tmp_path):
    from mitsuba_active.run import config_differences

    rec = _run(source, tmp_path / "r", planner="even", field_preset="fast")
    assert rec["config"]["field_preset"] == "fast"
    with pytest.raises(UserError, match=r"other settings \(field_preset: 'fast' -> 'default'\)"):
        _run(source, tmp_path / "r", planner="even")
    # A record from before presets trained the fast preset's field.
    old = {k: v for k, v in rec["config"].items() if k != "field_preset"}
    assert config_differences(old, rec["config"]) == []
    assert config_differences(old, {**rec["config"], "field_preset": "default"}) == [
        "field_preset: 'fast' -> 'default'"]
    with pytest.raises(UserError, match="unknown field preset 'huge'; choose one of fast, default"):
        RunConfig(scene="s.xml", field_preset="huge").validate()


def test_ensemble_size_counts_only_where_a_planner_trains_one(source, tmp_path):
    from mitsuba_active.run import config_differences

    def cfg(planner, ensemble):
        return {**TINY, "scene": "s.xml", "planner": planner, "planner_options": {}, "ensemble": ensemble}

    assert config_differences(cfg("even", 3), cfg("even", 2)) == []
    assert config_differences(cfg("fisher", 3), cfg("fisher", 1)) == []
    assert config_differences(cfg("rfe", 3), cfg("rfe", 2)) == ["ensemble: 3 -> 2"]
    # Another planner that trains none: the planner is the difference, not an ensemble of None.
    assert config_differences(cfg("rfe", 2), cfg("even", 2)) == ["planner: 'rfe' -> 'even'"]
    assert config_differences(cfg("rfe", 3), cfg("fisher", 1)) == ["ensemble: 3 -> 1", "planner: 'rfe' -> 'fisher'"]
    # A planner's defaults, given or left out, are the same run; other values are not.
    with_options = {**cfg("rfe", 2), "planner_options": {"form": "sum"}}
    assert config_differences(cfg("rfe", 2), with_options) == []
    assert config_differences(with_options, {**with_options, "planner_options": {"form": "log"}}) == [
        "planner_options: {'form': 'sum', 'bootstrap': 'none', 'min_opacity': 0.0} "
        "-> {'form': 'log', 'bootstrap': 'none', 'min_opacity': 0.0}"]
    fisher = cfg("fisher", 1)
    assert config_differences(fisher, {**fisher, "planner_options": {"lam": 0.1}}) == []
    done = _run(source, tmp_path / "e", planner="even", ensemble=3)
    assert _run(source, tmp_path / "e", planner="even", ensemble=2)["captured"] == done["captured"]


def test_export_round_trips_poses(source, tmp_path):
    rec = _run(source, tmp_path / "r", planner="coverage")
    path = export_transforms(tmp_path / "r", tmp_path / "ds")
    data = json.loads((tmp_path / "ds" / "transforms_train.json").read_text())
    assert len(data["frames"]) == 4 and data["w"] == 16 and "camera_angle_x" in data
    for frame, index in zip(data["frames"], rec["captured"]):
        assert frame["candidate"] == index
        assert np.allclose(opengl_to_mitsuba(frame["transform_matrix"]), source.candidates[index].to_world)
    gl = np.array(data["frames"][0]["transform_matrix"])
    cam = source.candidates[rec["captured"][0]]
    assert np.allclose(-gl[:3, 2], cam.forward)  # OpenGL cameras look along -Z
    assert (tmp_path / "ds" / data["frames"][0]["file_path"]).is_file()
    assert (tmp_path / "ds" / data["frames"][0]["distance_file_path"]).is_file()
    # The held-out views, with their ground truth; transforms.json holds both, split by nerfstudio's lists.
    test = json.loads((tmp_path / "ds" / "transforms_test.json").read_text())["frames"]
    assert [f["heldout"] for f in test] == [0, 1, 2]
    both = json.loads(path.read_text())
    assert both["frames"] == data["frames"] + test
    assert both["train_filenames"] == [f["file_path"] for f in data["frames"]]
    assert both["test_filenames"] == both["val_filenames"] == [f["file_path"] for f in test]
    for i, frame in enumerate(test):
        gt = source.heldout_view(i)
        assert np.allclose(opengl_to_mitsuba(frame["transform_matrix"]), gt.camera.to_world)
        assert np.abs(iio.imread(tmp_path / "ds" / frame["file_path"]) / 255 - gt.rgb).max() <= 1 / 255
        # The mask is the ground truth's hit mask, white where it sees geometry.
        assert np.array_equal(iio.imread(tmp_path / "ds" / frame["mask_path"]) > 127, gt.mask)
        assert 0 < gt.mask.mean() < 1
    # The same split reads back: the chosen views are the candidates, the held-out views held out.
    from mitsuba_active.datasets import DatasetSource

    for opened in (tmp_path / "ds", path):
        back = DatasetSource.from_path(opened)
        assert np.allclose([c.to_world for c in back.heldout], [c.to_world for c in source.heldout])
        assert np.allclose([c.to_world for c in back.candidates],
                           [source.candidates[i].to_world for i in rec["captured"]])
        assert np.allclose(back.heldout_view(1).rgb, source.heldout_view(1).rgb, atol=1 / 255)
    # An unfinished run exports what it has, and says so.
    rec_path = tmp_path / "r" / "run.json"
    rec_path.write_text(json.dumps({**rec, "finished": False}))
    with pytest.warns(UserWarning, match="unfinished run: exporting the 4 of 4 views"):
        export_transforms(tmp_path / "r", tmp_path / "ds2")
    # The scene's bounds travel with it: the export reads back with the scene's box, not an estimate.
    exported = DatasetSource.from_path(path)
    assert np.allclose(exported.bbox_min, source.bbox_min) and np.allclose(exported.bbox_max, source.bbox_max)
    # Exporting fewer views into the same folder leaves none of the earlier ones behind.
    (tmp_path / "ds" / "notes.txt").write_text("mine")
    rec_path.write_text(json.dumps({**rec, "finished": False, "captured": rec["captured"][:2],
                                    "rounds": [r for r in rec["rounds"] if r["views"] <= 2],
                                    "metrics": [m for m in rec["metrics"] if m["views"] <= 2]}))
    with pytest.warns(UserWarning, match="exporting the 2 of 4 views"):
        export_transforms(tmp_path / "r", tmp_path / "ds")
    assert sorted(p.relative_to(tmp_path / "ds").as_posix() for p in (tmp_path / "ds").rglob("view_*")) == [
        "distance/view_000.exr", "distance/view_001.exr", "images/view_000.png", "images/view_001.png",
        "masks/view_000.png", "masks/view_001.png"]
    assert (tmp_path / "ds" / "notes.txt").read_text() == "mine"


def test_an_unfinished_run_exports_held_out_views_rendered_again(source, tmp_path, monkeypatch):
    """A run that has not written its held-out ground truth: the export renders it through the scene."""
    import shutil

    monkeypatch.setenv("MITSUBA_ACTIVE_CACHE", str(tmp_path / "cache"))

    rec = _run(source, tmp_path / "r", planner="even", budget=2, eval_views=[2])
    shutil.rmtree(tmp_path / "r" / "heldout")
    (tmp_path / "r" / "run.json").write_text(json.dumps({**rec, "finished": False}))
    with pytest.warns(UserWarning, match="unfinished run"):
        export_transforms(tmp_path / "r", tmp_path / "ds")
    test = json.loads((tmp_path / "ds" / "transforms_test.json").read_text())["frames"]
    assert len(test) == len(source.heldout)
    for i, frame in enumerate(test):
        gt = source.heldout_view(i)
        assert np.abs(iio.imread(tmp_path / "ds" / frame["file_path"]) / 255 - gt.rgb).max() <= 1 / 255
        assert np.array_equal(iio.imread(tmp_path / "ds" / frame["mask_path"]) > 127, gt.mask)


def test_a_failed_export_leaves_the_earlier_one_whole(source, tmp_path, monkeypatch):
    import errno
    import shutil

    _run(source, tmp_path / "r", planner="coverage")
    export_transforms(tmp_path / "r", tmp_path / "ds")
    earlier = {p: p.read_bytes() for p in (tmp_path / "ds").rglob("*") if p.is_file()}
    views = tmp_path / "r" / "views"
    (views / "view_000.png").write_bytes((views / "view_001.png").read_bytes())  # the next export differs
    copyfile, copied = shutil.copyfile, []

    def full_disk(src, dst, **kw):
        if len(copied) == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(src), None, str(dst))
        copied.append(dst)
        return copyfile(src, dst, **kw)

    monkeypatch.setattr(shutil, "copyfile", full_disk)
    with pytest.raises(OSError) as err:
        export_transforms(tmp_path / "r", tmp_path / "ds")
    assert err.value.filename2 == str(tmp_path / "ds" / "distance" / "view_001.exr")  # the 4th copy: its final name
    assert {p: p.read_bytes() for p in (tmp_path / "ds").rglob("*") if p.is_file()} == earlier
    # A first export that fails leaves no folder.
    copied.clear()
    with pytest.raises(OSError):
        export_transforms(tmp_path / "r", tmp_path / "new" / "ds")
    assert not (tmp_path / "new").exists()


def test_export_keeps_each_cameras_field_of_view(tmp_path):
    from mitsuba_active.datasets import DatasetSource

    cfg = RunConfig(**{**TINY, "scene": str(two_sensor_xml(tmp_path)), "rig": "xml", "planner": "even",
                       "budget": 2, "initial_views": 1, "heldout": 2, "eval_views": [2]})
    source = cfg.open_source(cache_dir=False)
    Run(source, cfg, tmp_path / "r", progress=False, log=lambda m: None).execute()
    exported = DatasetSource.from_path(export_transforms(tmp_path / "r", tmp_path / "ds"))
    fovs = sorted(c.fov for c in exported.candidates)
    assert fovs == pytest.approx(sorted(c.fov for c in source.candidates), abs=1e-4) and fovs[0] != fovs[1]
    assert [c.fov for c in exported.heldout] == pytest.approx([c.fov for c in source.heldout], abs=1e-4)


def test_rfe_prefers_the_unseen_side(sphere_xml, tmp_path):
    """Train on views of one side of a ball; the far side must score higher."""
    from mitsuba_active.env import SceneSource
    from mitsuba_active.planners import PlanningState, make_planner
    from mitsuba_active.rigs import fibonacci_sphere
    from mitsuba_active.run import make_ensemble, sparse_candidate_rays, train_on
    from mitsuba_active.scene import load_scene

    scene = load_scene(sphere_xml)
    cams = fibonacci_sphere(40, [0, 0, 0], 1.8, 45.0, 24, 24)
    seen = [i for i, c in enumerate(cams) if c.position[0] > 0.9][:6]
    src = SceneSource(scene, cams, fibonacci_sphere(2, [0, 0, 0], 1.8, 45.0, 24, 24, offset=0.5), spp=4,
                      cache_dir=False)
    cfg = RunConfig(scene=str(sphere_xml), ensemble=3, field=TINY["field"])
    ens = make_ensemble(src, cfg, 3, seed=0)
    train_on(ens, [src.candidate_view(i) for i in seen], 300)
    state = PlanningState(cams, seen, ens, sparse_candidate_rays(cams, 128, 0), np.random.default_rng(0))
    picks, scores = make_planner("rfe").select(state, 1)
    x = np.array([c.position[0] for c in cams])
    assert scores[x < -0.9].mean() > 2 * scores[seen].mean()
    top5 = np.argsort(-scores)[:5]
    assert x[top5].mean() < 0, x[top5]  # the best candidates look at the far side
    assert picks[0] == top5[0] and picks[0] not in seen


def test_plan_cli_bad_inputs(spot_xml, tmp_path):
    runner = CliRunner()
    for args, needle in ([["--planner", "oracle"], "unknown planner"], [["--budget", "11"], "larger than"],
                         [["--resolution", "0"], "resolution"], [["--eval-views", "a,b"], "eval-views"],
                         [["--ensemble", "1", "--budget", "5"], "at least 2 members"],
                         [["--planner", "fisher", "--planner-option", "probes=0"], "probes in [1, 64]"],
                         [["--planner", "fisher", "--planner-option", "probes=1000"], "probes in [1, 64]"],
                         [["--planner", "fisher", "--planner-option", "lam=inf"], "finite number lam > 0"],
                         [["--planner-option", "form"], "NAME=VALUE"],
                         [["--planner", "even", "--planner-option", "lam=1"], "unknown option lam (it takes none)"],
                         [["--planner", "fisher", "--planner-option", "lam=abc"], "finite number lam > 0"],
                         [["--heldout", "0"], "held-out view"],
                         [["--planner", "even", "--score", "log"], "--score applies to the rfe planner only"],
                         [["--downscale", "2"], "--downscale applies to datasets"]):
        res = runner.invoke(main, ["plan", str(spot_xml), "--candidates", "10", "--out", str(tmp_path / "o"),
                                   *args])
        assert res.exit_code == 2 and needle in res.output and "Traceback" not in res.output, res.output
        assert not (tmp_path / "o").exists()


def test_plan_suggests_the_distance_loss_for_rooms(spot_xml, shared_data, tmp_path):
    from mitsuba_active.run import INTERIOR_DISTANCE_WEIGHT

    # A budget above the candidate count stops the run before anything is rendered.
    cbox = shared_data / "mitsuba" / "cbox" / "cbox.xml"
    hint = f"try --distance-weight {INTERIOR_DISTANCE_WEIGHT:g}"
    stop = ["--candidates", "4", "--budget", "5", "--out", str(tmp_path / "o")]
    runs = {(cbox, "0"): True, (cbox, "10"): False, (spot_xml, "0"): False}
    for (xml, weight), hinted in runs.items():
        res = CliRunner().invoke(main, ["plan", str(xml), "--distance-weight", weight, *stop])
        assert res.exit_code == 2 and "larger than" in res.output, res.output
        assert (hint in res.output) is hinted, res.output


def test_resume_refuses_a_changed_scene(source, tmp_path, spot_xml):
    from mitsuba_active.errors import UserError

    _run(source, tmp_path / "r", planner="even", budget=3, eval_views=[3])
    rec = json.loads((tmp_path / "r" / "run.json").read_text())
    content_hash = rec["content_hash"]
    rec["finished"], rec["content_hash"] = False, "another scene"
    (tmp_path / "r" / "run.json").write_text(json.dumps(rec))
    with pytest.raises(UserError, match="changed"):
        _run(source, tmp_path / "r", planner="even", budget=3, eval_views=[3])
    # Other held-out views would make the metrics of the two sittings incomparable.
    rec["content_hash"] = content_hash
    (tmp_path / "r" / "run.json").write_text(json.dumps({**rec, "heldout": rec["heldout"][:1]}))
    with pytest.raises(UserError, match="changed"):
        _run(source, tmp_path / "r", planner="even", budget=3, eval_views=[3])
    # A record edited by hand, naming a view the scene has no candidate for.
    not_indices = r"its captured views are not indices of its 10 candidates"
    not_a_list = "its captured is NoneType, not list"
    edited = "its rounds did not pick the views it lists as captured"
    for captured, why in (([0, 99], not_indices), ([0, "1"], not_indices), (None, not_a_list),
                          (rec["captured"][:-1], edited), ([*rec["captured"][:-1], (rec["captured"][-1] + 1) % 10],
                                                          edited)):
        (tmp_path / "r" / "run.json").write_text(json.dumps({**rec, "captured": captured}))
        with pytest.raises(UserError, match=rf"run.json is damaged \({why}\); remove it to start over"):
            _run(source, tmp_path / "r", planner="even", budget=3, eval_views=[3])
    # A finished run short of its budget would pair its views on disk with other poses.
    finished = {**rec, "finished": True, "captured": rec["captured"][:-1], "rounds": rec["rounds"][:-1]}
    (tmp_path / "r" / "run.json").write_text(json.dumps(finished))
    with pytest.raises(UserError, match=r"run.json is damaged \(it is finished with 2 captured views, but its "
                                        r"budget is 3\)"):
        _run(source, tmp_path / "r", planner="even", budget=3, eval_views=[3])
    # An ensemble file outside the run folder: the run would load it, then remove it.
    (tmp_path / "victim.npz").write_bytes(b"keep me")
    not_own = r"its ensemble_file .* is not one of the run's ensemble_NNN.npz files"
    for name, why in (("../victim.npz", not_own), ("views", not_own), (3, "its ensemble_file is int, not str")):
        (tmp_path / "r" / "run.json").write_text(json.dumps({**rec, "ensemble_file": name}))
        with pytest.raises(UserError, match=rf"run.json is damaged \({why}\)"):
            _run(source, tmp_path / "r", planner="even", budget=3, eval_views=[3])
    assert (tmp_path / "victim.npz").read_bytes() == b"keep me"
    # Other candidates in the scene are not a damaged record, and are refused as such.
    (tmp_path / "r" / "run.json").write_text(json.dumps(rec))
    fewer = tiny_source(spot_xml, n_candidates=6, n_heldout=3, resolution=16)
    with pytest.raises(UserError, match=r"other settings \(candidates: 10 -> 6\)"):
        _run(fewer, tmp_path / "r", planner="even", budget=3, eval_views=[3], candidates=6)


def test_plan_command_end_to_end(spot_xml, tmp_path):
    out = tmp_path / "cli"
    args = ["plan", str(spot_xml), "--budget", "3", "--initial-views", "1", "--candidates", "6", "--heldout", "2",
            "--resolution", "16", "--spp", "2", "--eval-views", "3,2", "--steps-per-view", "5", "--eval-steps", "20",
            "--rays-per-candidate", "16", "--quiet", "--out", str(out)]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "held-out PSNR by views captured: 2: " in res.output and ", 3: " in res.output
    rec = json.loads((out / "run.json").read_text())
    assert rec["finished"] and len(rec["captured"]) == 3
    assert rec["ensemble_file"] == "ensemble_003.npz" and (out / "ensemble_003.npz").is_file()
    assert not (out / "ensemble_002.npz").exists()
    res = CliRunner().invoke(main, ["export", str(out)])
    assert res.exit_code == 0 and (out / "export" / "transforms.json").is_file()
    # The same counts in another order are the same run; other settings are named.
    res = CliRunner().invoke(main, [*args, "--eval-views", "2,3,3"])
    assert res.exit_code == 0 and "already complete" in res.output, res.output
    # ... also against a record that kept the order it was given in.
    rec = json.loads((out / "run.json").read_text())
    (out / "run.json").write_text(json.dumps({**rec, "config": {**rec["config"], "eval_views": [3, 2]}}))
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0 and "already complete" in res.output, res.output
    res = CliRunner().invoke(main, [*args, "--budget", "2", "--seed", "5"])
    assert res.exit_code == 2 and ("other settings (budget: 3 -> 2: fewer than the 3 views it has captured; "
                                   "seed: 0 -> 5)") in res.output, res.output
    # A larger budget takes the run on from the views it has.
    res = CliRunner().invoke(main, [*args, "--budget", "4", "--quiet"])
    assert res.exit_code == 0 and "resuming" in res.output and "(the budget was 3)" in res.output, res.output
    rec = json.loads((out / "run.json").read_text())
    assert rec["finished"] and len(rec["captured"]) == 4 and [m["views"] for m in rec["metrics"]] == [2, 3, 4]


def test_plan_takes_a_mesh(shared_data, tmp_path):
    out = tmp_path / "m"
    args = ["plan", str(shared_data / "meshes" / "suzanne.obj"), "--planner", "even", "--budget", "2",
            "--initial-views", "1", "--candidates", "4", "--heldout", "1", "--resolution", "8", "--spp", "1",
            "--eval-views", "2", "--eval-steps", "10", "--quiet", "--out", str(out)]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    def no_nan(name):
        raise AssertionError(f"run.json holds {name}, which strict JSON readers refuse")

    rec = json.loads((out / "run.json").read_text(), parse_constant=no_nan)
    assert rec["finished"] and rec["config"]["scene"] == str(out / "scene" / "suzanne.xml")
    assert rec["metrics"][0]["ssim"] is None  # 8x8 pixels: too small for SSIM
    assert (out / "scene" / "suzanne.xml").is_file()
    # The same command again finds the finished run (authoring anew changes nothing).
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0 and "already complete" in res.output, res.output


def test_a_config_that_does_not_describe_its_source_is_refused(source, sphere_xml, tmp_path):
    from mitsuba_active.errors import UserError

    for changed, named in (({"resolution": 64}, "resolution=64 (the source's: 16)"),
                           ({"spp": 64, "heldout": 5}, "heldout=5 (the source's: 3); spp=64 (the source's: 4)"),
                           ({"scene": str(sphere_xml)}, f"scene={str(sphere_xml)!r}")):
        cfg = RunConfig(**{**TINY, "scene": str(source.scene.path), **changed})
        with pytest.raises(UserError, match="do not describe its view source: " + re.escape(named)):
            Run(source, cfg, tmp_path / "r")
    # The settings' own source is theirs; a scene given as a Path is recorded as text.
    cfg = RunConfig(**{**TINY, "scene": source.scene.path})
    assert isinstance(cfg.scene, str)
    own = Run(cfg.open_source(cache_dir=False), cfg, tmp_path / "r").source
    assert [c.to_dict() for c in own.candidates] == [c.to_dict() for c in source.candidates]


def test_plan_runs_a_planner_of_ones_own(spot_xml, tmp_path, monkeypatch):
    from tests.test_planners import PLANNER_FILE

    (tmp_path / "mine.py").write_text(PLANNER_FILE)
    monkeypatch.chdir(tmp_path)
    args = ["plan", str(spot_xml), "--planner", "mine.py:Last", "--planner-option", "offset=1", "--budget", "3",
            "--candidates", "6", "--heldout", "2", "--resolution", "16", "--spp", "2", "--eval-views", "3",
            "--eval-steps", "20", "--quiet"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    out = tmp_path / "runs" / "spot-mine.py_Last-seed0"
    rec = json.loads((out / "run.json").read_text())
    assert rec["finished"] and rec["captured"][2] == max(set(range(6)) - set(rec["captured"][:2]))
    assert rec["config"]["planner"] == f"{tmp_path / 'mine.py'}:Last" and rec["planner_options"] == {"offset": 1}
    # Edited code is another planner: its run is not resumed or counted as done.
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0 and "already complete" in res.output, res.output
    # The same code elsewhere (a moved or copied project) is the same planner.
    (tmp_path / "moved").mkdir()
    (tmp_path / "moved" / "mine.py").write_text(PLANNER_FILE)
    moved = [*args[:3], "moved/mine.py:Last", *args[4:], "--out", str(out)]
    res = CliRunner().invoke(main, moved)
    assert res.exit_code == 0 and "already complete" in res.output, res.output
    (tmp_path / "mine.py").write_text(PLANNER_FILE.replace("self.offset\n", "self.offset + 1\n"))
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 2 and "another version of the planner's code (mine.py:Last)" in res.output, res.output


def test_a_planner_fixed_before_it_chose_a_view_starts_the_run_over(spot_xml, tmp_path, monkeypatch):
    from tests.test_planners import PLANNER_FILE

    broken = PLANNER_FILE.replace("return greedy_top(scores, unseen(state), batch), scores", "return [99], None")
    (tmp_path / "mine.py").write_text(broken)
    monkeypatch.chdir(tmp_path)
    args = ["plan", str(spot_xml), "--planner", "mine.py:Last", "--budget", "3", "--candidates", "6", "--heldout",
            "2", "--resolution", "16", "--spp", "2", "--eval-views", "3", "--eval-steps", "20", "--quiet",
            "--out", "r"]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 2 and "the mine.py:Last planner picked [99]" in res.output, res.output
    assert json.loads((tmp_path / "r" / "run.json").read_text())["rounds"] == []
    (tmp_path / "mine.py").write_text(PLANNER_FILE)
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0 and "the planner's code changed before it chose a view: r starts over" in res.output
    rec = json.loads((tmp_path / "r" / "run.json").read_text())
    assert rec["finished"] and len(rec["rounds"]) == 1
    assert rec["captured"][2] == max(set(range(6)) - set(rec["captured"][:2]))
    # Once it has chosen views, other code is refused.
    (tmp_path / "mine.py").write_text(broken)
    res = CliRunner().invoke(main, [*args, "--budget", "4"])
    assert res.exit_code == 2 and "another version of the planner's code" in res.output, res.output


def test_run_json_is_standard_json_when_scores_are_not_finite(source, tmp_path):
    """JSON has no inf or NaN (other readers than Python's refuse them): such scores are written as null."""
    (tmp_path / "masked.py").write_text('''
import numpy as np
from mitsuba_active.planners import Planner, greedy_top, unseen


class Masked(Planner):
    def select(self, state, batch):
        scores = np.where(unseen(state), np.arange(len(state.candidates), dtype=float), -np.inf)
        scores[0] = np.nan
        return greedy_top(scores, unseen(state), batch), scores
''')
    _run(source, tmp_path / "r", planner=f"{tmp_path / 'masked.py'}:Masked", seed=1)

    def refuse(name):
        raise ValueError(f"{name} in run.json")

    rec = json.loads((tmp_path / "r" / "run.json").read_text(), parse_constant=refuse)
    scores = rec["rounds"][0]["scores"]
    assert scores[0] is None and [s is None for s in scores[1:]] == [i in rec["captured"][:2] for i in range(1, 10)]


def test_a_run_notes_once_when_its_evaluation_field_is_not_clearly_above_the_background(source, sphere_xml,
                                                                                        tmp_path):
    """A field trained one step scores no better than the background colour alone:
    its held-out scores then measure the training, and the run says so once."""
    from mitsuba_active.training import FLOOR_MARGIN_DB, at_floor, evaluation_note, fit_too_short

    def run(src, out, eval_steps):
        lines = []
        cfg = RunConfig(scene=str(src.scene.path), planner="even", **{**TINY, "eval_steps": eval_steps})
        rec = Run(src, cfg, out, progress=False, log=lines.append).execute()
        return rec, [ln for ln in lines if ln.startswith("note:")]

    short, notes = run(source, tmp_path / "short", 1)
    assert all(m["psnr_fg"] < m["floor_psnr_fg"] + FLOOR_MARGIN_DB for m in short["metrics"])
    assert all(at_floor(m) and fit_too_short(m) for m in short["metrics"]) and len(notes) == 1, notes
    assert re.fullmatch(r"note: at 2 views the evaluation field's held-out foreground PSNR is \d+\.\d dB, not 3 dB "
                        r"above the background colour alone's \(\d+\.\d dB\): its scores cannot tell views apart; "
                        r"raise eval_steps \(RunConfig.eval_steps, plan --eval-steps; default 1500\)", notes[0]), notes
    # A ball looks alike from everywhere: a field of its views soon learns what the held-out ones see.
    ball = tiny_source(sphere_xml, n_candidates=10, n_heldout=3, resolution=16)
    trained, notes = run(ball, tmp_path / "trained", 100)
    assert all(m["psnr_fg"] > m["floor_psnr_fg"] + FLOOR_MARGIN_DB for m in trained["metrics"]) and notes == []
    # A field that fits its own views but not the held-out ones: its views are what it lacks.
    assert evaluation_note({"views": 4, "psnr_fg": 18.0, "floor_psnr_fg": 16.0, "psnr": 23.0, "floor_psnr": 21.0,
                            "fit_psnr": 40.0, "fit_start_psnr": 10.0}, 7, 1500).endswith(
        "cannot tell views apart; it fits its own training views to 40.0 dB, so they show too little of what the "
        "held-out views see")
    # A field above the floor that barely fits its own views, and a record from before floors.
    stalled = {"views": 4, "fit_psnr": 21.0, "fit_start_psnr": 20.0}
    assert fit_too_short(stalled) and not at_floor(stalled) and not fit_too_short({"fit_psnr": 5.0})
    assert evaluation_note(stalled, 7, 1500) == (
        "note: the evaluation field fits its own 4 training views to only 21.0 dB after 7 steps (from 20.0 dB at "
        "first): its held-out scores say more about the training than about the views; raise eval_steps "
        "(RunConfig.eval_steps, plan --eval-steps; default 1500)")
    # Without a foreground to score, the whole images are compared with the floor.
    assert evaluation_note({"views": 2, "psnr": 21.0, "psnr_fg": None, "floor_psnr": 20.0}, 7, 1500) == (
        "note: at 2 views the evaluation field's held-out PSNR is 21.0 dB, not 3 dB above the background colour "
        "alone's (20.0 dB): its scores cannot tell views apart")
    assert evaluation_note({"views": 2, "psnr": 24.0, "psnr_fg": 14.0, "floor_psnr": 23.0, "floor_psnr_fg": 8.0},
                           7, 1500) is None


def test_a_run_records_the_foreground_psnr_and_the_floor_and_resumes_a_record_without(source, tmp_path):
    import csv

    out = tmp_path / "r"
    rec = _run(source, out, planner="even", eval_views=[2, 4, 6])
    for m in rec["metrics"]:
        # The background is exact where the views see none: the floor is lower on the foreground.
        assert 0 < m["floor_psnr_fg"] < m["floor_psnr"] and 0 < m["psnr_fg"] < 100
    rows = list(csv.DictReader((out / "metrics.csv").open()))
    assert [float(r["psnr_fg"]) for r in rows] == pytest.approx([m["psnr_fg"] for m in rec["metrics"]], abs=1e-4)
    assert all(r["floor_psnr"] and r["floor_psnr_fg"] for r in rows)
    page = (out / "report.html").read_text()
    assert "foreground PSNR (dB)" in page and "background alone: PSNR (dB)" in page
    assert (out / "psnr_fg.png").is_file()
    # A record from before the foreground PSNR goes on to a larger budget: its scores stay as they were.
    for m in rec["metrics"]:
        for key in ("psnr_fg", "floor_psnr", "floor_psnr_fg"):
            del m[key]
    (out / "run.json").write_text(json.dumps(rec))
    lines = []
    cfg = RunConfig(scene=str(source.scene.path), planner="even", **{**TINY, "eval_views": [2, 4, 6], "budget": 6})
    longer = Run(source, cfg, out, progress=False, log=lines.append).execute()
    assert [("psnr_fg" in m, m["views"]) for m in longer["metrics"]] == [(False, 2), (False, 4), (True, 6)]
    assert [r["psnr_fg"] == "" for r in csv.DictReader((out / "metrics.csv").open())] == [True, True, False]
    assert any(ln.startswith("    6 views: PSNR ") and ", foreground PSNR " in ln for ln in lines), lines


def test_a_run_folder_refuses_a_source_with_other_cameras(source, tmp_path):
    """Same scene and settings, other cameras (a source with cameras of the caller's own): named as such."""
    from mitsuba_active.env import SceneSource

    _run(source, tmp_path / "run", planner="even", budget=2, eval_views=[2])
    turned = [dataclasses.replace(c, fov=c.fov + 1.0) for c in source.candidates]
    other = SceneSource(source.scene, turned, source.heldout, spp=TINY["spp"], cache_dir=False)
    with pytest.raises(UserError, match="holds a run whose candidate or held-out cameras are not the view source's;"):
        _run(other, tmp_path / "run", planner="even", budget=2, eval_views=[2])
    # A run of an earlier version, whose rigs placed cameras otherwise, says so.
    record = json.loads((tmp_path / "run" / "run.json").read_text())
    record["versions"]["mitsuba_active"] = "0.0.1"
    (tmp_path / "run" / "run.json").write_text(json.dumps(record))
    with pytest.raises(UserError, match="cameras are not the view source's \\(it was made with mitsuba-active 0.0.1, "
                                        "whose rigs place cameras otherwise"):
        _run(other, tmp_path / "run", planner="even", budget=2, eval_views=[2])


def test_the_evaluation_field_trains_on_views_in_candidate_order(source, tmp_path, monkeypatch):
    """The same views captured in another order give the same evaluation (not only to rounding)."""
    import mitsuba_active.run.runner as runner_module

    trained_on, evaluate = [], runner_module.evaluate

    def recording(src, views, cfg, progress=False):
        trained_on.append([next(i for i, c in enumerate(src.candidates) if c is v.camera) for v in views])
        return evaluate(src, views, cfg, progress)

    monkeypatch.setattr(runner_module, "evaluate", recording)
    rec = _run(source, tmp_path / "run", planner="even", seed=1)
    assert rec["captured"] != sorted(rec["captured"])  # captured out of candidate order
    assert trained_on == [sorted(rec["captured"][:2]), sorted(rec["captured"])]
