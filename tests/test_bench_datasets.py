"""Suites of captured datasets: a ``dataset = "..."`` scene runs as ``plan`` runs that dataset."""

import json

import pytest
from click.testing import CliRunner

from mitsuba_active.bench import load_suite, plan_jobs, run_suite
from mitsuba_active.cli import main
from mitsuba_active.errors import UserError
from tests.test_datasets import write_dataset

#: Tiny run settings, for ``bench --set`` (the suite itself sets none).
TINY = ["candidates=8", "heldout=2", "resolution=4", "budget=4", "initial_views=2", "eval_views=[2, 4]",
        "initial_steps=10", "steps_per_view=5", "eval_steps=3", "rays_per_candidate=16", "field.batch_rays=256",
        "field.n_samples=16", "field.render_batch=1024"]
SMALL = {"budget": 4, "candidates": 8, "heldout": 2, "resolution": 4}


@pytest.fixture()
def dataset_suite(tmp_path):
    """A suite of one captured dataset (10 frames of 8x8 pixels, 2 of them its test split) beside it,
    with the sphere rig of the bundled suite's defaults."""
    write_dataset(tmp_path / "capture", n=10, size=(8, 8), form="blender")
    path = tmp_path / "s.toml"
    path.write_text('planners = ["even"]\n[defaults]\nrig = "sphere"\nspp = 4\n[[scenes]]\ndataset = "capture"\n')
    return path


def test_a_dataset_scene_runs_as_plan_runs_it_and_a_changed_dataset_is_refused(dataset_suite, tmp_path):
    out = tmp_path / "out"
    sets = [a for item in TINY for a in ("--set", item)]
    res = CliRunner().invoke(main, ["bench", str(dataset_suite), "--out", str(out), "--workers", "1", "--quiet",
                                    *sets])
    assert res.exit_code == 0, res.output
    rec = json.loads((out / "runs" / "capture" / "even-seed0" / "run.json").read_text())
    # Its own cameras and test split; the images shrunk to the resolution (8 px by 2); the sphere rig
    # and samples per pixel of the rendered scenes do not apply.
    assert rec["finished"] and len(rec["candidates"]) == 8 and len(rec["heldout"]) == 2
    assert rec["candidates"][0]["width"] == 4 and rec["config"]["downscale"] is None
    assert rec["heldout_files"] == ["images/f_008.png", "images/f_009.png"]
    assert (rec["config"]["rig"], rec["config"]["fov"], rec["config"]["spp"]) == ("auto", None, 64)
    assert rec["config"]["scene"] == str(tmp_path / "capture")
    assert "| capture @4 |" in (out / "report" / "table_psnr.md").read_text()
    # Run again, the finished run is kept; with other poses in its transforms file, the folder is refused.
    res = CliRunner().invoke(main, ["bench", str(dataset_suite), "--out", str(out), "--quiet", *sets])
    assert res.exit_code == 0 and "1 of the suite's 1 runs finished earlier" in res.output
    train = tmp_path / "capture" / "transforms_train.json"
    meta = json.loads(train.read_text())
    meta["frames"][0]["transform_matrix"][0][3] += 0.5
    train.write_text(json.dumps(meta))
    stamp = (out / "runs" / "capture" / "even-seed0" / "run.json").stat().st_mtime_ns
    for report_only in (False, True):
        with pytest.raises(UserError, match="holds a run of scene 'capture' made with another version of it"):
            run_suite(dataset_suite, out, "quick", progress=False, report_only=report_only, overrides=SMALL)
    assert (out / "runs" / "capture" / "even-seed0" / "run.json").stat().st_mtime_ns == stamp


def test_a_datasets_jobs_read_its_frames_before_anything_runs(dataset_suite, tmp_path):
    suite = load_suite(dataset_suite)
    assert [(s.name, s.kind, s.path) for s in suite.scenes] == [("capture", "dataset", tmp_path / "capture")]
    jobs = plan_jobs(suite, tmp_path / "out", "quick", overrides={**SMALL, "downscale": 2})
    assert jobs[0].content_hash is not None and jobs[0].config["downscale"] == 2
    # A budget beyond its 8 training frames, views it cannot render, or a folder whose
    # transforms file is gone: one line naming the scene, and nothing written.
    for overrides, message in (
            ({"budget": 9}, "scene 'capture': the view budget \\(9\\) is larger than the number of candidate "
                            "views \\(8\\)"),
            ({"embodiment": "drone", "along_the_way": 0.5}, "scene 'capture': along_the_way renders new poses"),
            ({"downscale": 9}, "scene 'capture': .*too small for downscale 9")):
        with pytest.raises(UserError, match=message):
            plan_jobs(suite, tmp_path / "bad", "quick", overrides={**SMALL, **overrides})
    (tmp_path / "capture" / "transforms_train.json").rename(tmp_path / "elsewhere.json")
    with pytest.raises(UserError, match="scene 'capture': .*holds neither transforms_train.json"):
        plan_jobs(suite, tmp_path / "bad", "quick", overrides=SMALL)
    assert not (tmp_path / "bad").exists()
    # A report of what is there reads no frames: the runs of a dataset that is gone have no content hash.
    assert plan_jobs(suite, tmp_path / "bad", "quick", author=False, overrides=SMALL)[0].content_hash is None


def test_a_dataset_named_by_its_transforms_file_is_named_by_its_folder(tmp_path):
    write_dataset(tmp_path / "capture", n=6, size=(8, 8))
    (tmp_path / "s.toml").write_text("[[scenes]]\ndataset = 'capture/transforms.json'\n")
    scene = load_suite(tmp_path / "s.toml").scenes[0]
    assert (scene.name, scene.path) == ("capture", tmp_path / "capture" / "transforms.json")


@pytest.mark.parametrize("entry, message", [
    ("dataset = 'capture'\ncolor = [1, 0, 0]", "scene 'capture': color dress a mesh; a dataset's images are as "
                                               "they were captured"),
    ("dataset = 'capture'\nrig = 'sphere'\nspp = 4", "scene 'capture': rig, spp apply to rendered scenes"),
    ("dataset = 'nowhere'", "scene 'nowhere': dataset = 'nowhere' is no dataset: .*nowhere does not exist"),
    ("dataset = 'capture/images/f_000.png'", "is no dataset: expected a transforms .json file or a folder "
                                             ".* is another file"),
    ("dataset = 'capture'\nmesh = 'x.obj'", "scene #1 needs exactly one of 'mesh', 'xml' or 'dataset'"),
])
def test_bad_dataset_scenes_are_one_line(tmp_path, entry, message):
    write_dataset(tmp_path / "capture", n=6, size=(8, 8))
    (tmp_path / "s.toml").write_text(f"[[scenes]]\n{entry}\n")
    with pytest.raises(UserError, match=message):
        load_suite(tmp_path / "s.toml")


def test_a_ray_suite_refuses_a_colmap_project_before_anything_starts(tmp_path):
    (tmp_path / "project" / "sparse" / "0").mkdir(parents=True)
    (tmp_path / "s.toml").write_text('planners = ["even"]\n[[scenes]]\ndataset = "project"\n')
    with pytest.raises(UserError, match="scene 'project' is a COLMAP project, which runs with local workers only"):
        run_suite(tmp_path / "s.toml", tmp_path / "out", "quick", progress=False, executor="ray")
    assert not (tmp_path / "out").exists()


def test_the_files_of_a_dataset_are_its_transforms_images_and_depth_maps(tmp_path):
    from mitsuba_active.bench.jobs import dataset_files

    write_dataset(tmp_path / "capture", n=4, size=(8, 8), missing=(1,),
                  frame_extra={0: {"depth_file_path": "images/d_000.png"}, 2: {"depth_file_path": "none.png"}})
    (tmp_path / "capture" / "images" / "d_000.png").write_bytes((tmp_path / "capture" / "images" /
                                                                  "f_000.png").read_bytes())
    (tmp_path / "capture" / "unrelated.txt").write_text("")
    names = [str(tmp_path / "capture" / n) for n in ("images/d_000.png", "images/f_000.png", "images/f_002.png",
                                                     "images/f_003.png", "transforms.json")]
    assert dataset_files(tmp_path / "capture") == names
    assert dataset_files(tmp_path / "capture" / "transforms.json") == names
    (tmp_path / "project" / "sparse" / "0").mkdir(parents=True)
    assert dataset_files(tmp_path / "project") is None


def test_the_bundled_suite_holds_mic_as_a_dataset():
    from tests.conftest import REPO

    suite = load_suite(REPO / "benchmarks" / "suites" / "shared.toml")
    mic = next(s for s in suite.scenes if s.name == "mic")
    assert mic.kind == "dataset" and (mic.path / "transforms_train.json").is_file()
    assert mic.run_options == {} and mic.scene_options == {}
