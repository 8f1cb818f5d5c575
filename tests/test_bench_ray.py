"""``bench --executor ray`` on a Ray instance of the test's own (2 CPUs), started once and stopped after."""

import json
import subprocess
import sys

import pytest
import ray

from mitsuba_active.bench import run_suite
from mitsuba_active.errors import UserError
from mitsuba_active.executors import RayOptions
from tests.test_bench import tiny_suite  # noqa: F401  (a fixture)

#: Settings whose values differ from run to run, whatever runs them.
TIMES = ("wall_seconds", "planning_seconds")


@pytest.fixture(scope="module")
def ray_instance():
    ray.init(num_cpus=2, include_dashboard=False, logging_level="error")
    yield
    ray.shutdown()


def comparable(results: dict) -> dict:
    """``results.json`` without the times of its runs."""
    return {**results, "cells": [{k: v for k, v in c.items() if k not in TIMES} for c in results["cells"]]}


def test_ray_gives_the_results_of_local_workers_and_resumes(tiny_suite, tmp_path, ray_instance):  # noqa: F811
    local, remote, back = tmp_path / "local", tmp_path / "ray", tmp_path / "driver"
    run_suite(tiny_suite, local, "quick", workers=2, planners=["even"], progress=False)
    run_suite(tiny_suite, remote, "quick", planners=["even"], progress=False, executor="ray")
    # Runs that come back to the driver (no shared storage) are written there alike.
    run_suite(tiny_suite, back, "quick", planners=["even"], progress=False, executor="ray",
              ray=RayOptions(storage="driver"))
    expected = comparable(json.loads((local / "report" / "results.json").read_text()))
    assert len(expected["cells"]) == 2
    for out in (remote, back):
        assert comparable(json.loads((out / "report" / "results.json").read_text())) == expected
        assert sorted(p.parent.name for p in out.rglob("run.json")) == ["even-seed0", "even-seed0"]
        assert not [p for p in out.rglob(".*")]
    # Resume: a finished run is not run again; a missing one is.
    stamps = {p: p.stat().st_mtime_ns for p in back.rglob("run.json")}
    gone = back / "runs" / "ball" / "even-seed0"
    for p in sorted(gone.rglob("*"), reverse=True):
        p.unlink() if p.is_file() else p.rmdir()
    gone.rmdir()
    lines = []
    run_suite(tiny_suite, back, "quick", planners=["even"], progress=False, executor="ray",
              ray=RayOptions(storage="driver"), log=lines.append)
    assert lines == ["1 of the suite's 2 runs finished earlier with these settings: kept, not run again"]
    after = {p: p.stat().st_mtime_ns for p in back.rglob("run.json")}
    assert [p for p in after if after[p] == stamps.get(p)] == [back / "runs" / "simple" / "even-seed0" / "run.json"]
    assert comparable(json.loads((back / "report" / "results.json").read_text())) == expected


#: A planner that counts its calls in a file beside it, then answers what no planner may.
FAILING = """
from pathlib import Path
from mitsuba_active.planners import Planner
class Wrong(Planner):
    def select(self, state, batch):
        with open(Path(__file__).with_name("calls"), "a") as f:
            f.write("call\\n")
        return [3]
"""

#: A planner whose first call kills its own worker process, as a lost node would end it.
DYING = """
import os, signal
from pathlib import Path
from mitsuba_active.planners.simple import EvenPlanner
class Dying(EvenPlanner):
    def select(self, state, batch):
        marker = Path(__file__).with_name("died")
        if not marker.exists():
            marker.write_text(str(os.getpid()))
            os.kill(os.getpid(), signal.SIGKILL)
        return super().select(state, batch)
"""


def test_a_run_that_raises_fails_once_and_is_not_retried(tiny_suite, tmp_path, ray_instance):  # noqa: F811
    (tmp_path / "wrong.py").write_text(FAILING)
    tiny_suite.write_text(tiny_suite.read_text().replace('["even", "rfe"]', '["wrong.py:Wrong"]'))
    with pytest.raises(UserError, match=r"the wrong.py:Wrong planner answered list"):
        run_suite(tiny_suite, tmp_path / "out", "quick", scenes=["ball"], progress=False, executor="ray",
                  ray=RayOptions(retries=3))
    assert (tmp_path / "calls").read_text() == "call\n"
    # One record, unfinished (its initial views were captured before the planner's first call).
    records = list((tmp_path / "out").rglob("run.json"))
    assert len(records) == 1 and not json.loads(records[0].read_text())["finished"]


def test_a_killed_worker_is_retried_and_the_suite_finishes(tiny_suite, tmp_path, ray_instance):  # noqa: F811
    import os

    (tmp_path / "dying.py").write_text(DYING)
    tiny_suite.write_text(tiny_suite.read_text().replace('["even", "rfe"]', '["dying.py:Dying"]'))
    out = tmp_path / "out"
    summary = run_suite(tiny_suite, out, "quick", scenes=["ball"], progress=False, executor="ray")
    killed = int((tmp_path / "died").read_text())
    assert killed != os.getpid() and summary["runs_reported"] == 1
    records = list(out.rglob("run.json"))
    assert len(records) == 1 and json.loads(records[0].read_text())["finished"]
    # With no retries, the run fails with one line that says why.
    (tmp_path / "died").unlink()
    with pytest.raises(UserError, match=r"its worker died in each of its 1 tries \(--retries 0\)"):
        run_suite(tiny_suite, tmp_path / "out2", "quick", scenes=["ball"], progress=False, executor="ray",
                  ray=RayOptions(retries=0))


@pytest.mark.parametrize("args, line", [
    (["--address", "auto"], "--address is for --executor ray"),
    (["--executor", "ray", "--workers", "2"], "--workers is for --executor local"),
    (["--executor", "ray", "--address", "127.0.0.1:9"], "no Ray cluster answers at 127.0.0.1:9"),
    (["--executor", "ray", "--address", "nowhere"], "--address takes 'auto' or HOST:PORT"),
    (["--executor", "ray", "--cpus-per-run", "0"], "--cpus-per-run must be more than 0"),
])
def test_bad_ray_options_are_one_line(tiny_suite, tmp_path, args, line):  # noqa: F811
    from click.testing import CliRunner

    from mitsuba_active.cli import main

    res = CliRunner().invoke(main, ["bench", str(tiny_suite), "--out", str(tmp_path / "out"), "--quiet", *args])
    assert res.exit_code == 2 and line in res.output and "Traceback" not in res.output, res.output
    assert not (tmp_path / "out").exists()


def test_without_ray_the_executor_names_the_extra(tiny_suite, tmp_path):  # noqa: F811
    code = ("import sys; sys.modules['ray'] = None\n"
            "from mitsuba_active.cli import main\n"
            f"main(['bench', {str(tiny_suite)!r}, '--out', {str(tmp_path / 'out')!r}, '--executor', 'ray'])")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "mitsuba-active: error: --executor ray needs Ray: pip install 'mitsuba-active[ray]'"], proc.stderr
    assert not (tmp_path / "out").exists()


def test_a_dataset_scene_runs_on_ray_as_on_local_workers(tmp_path, ray_instance):
    """Without shared storage its frames travel to the task: the same results, and the run's record
    names the dataset where the suite has it."""
    from mitsuba_active.bench import parse_overrides
    from tests.test_bench_datasets import TINY
    from tests.test_datasets import write_dataset

    write_dataset(tmp_path / "capture", n=10, size=(8, 8), form="blender")
    suite = tmp_path / "s.toml"
    suite.write_text('planners = ["even"]\n[[scenes]]\ndataset = "capture"\n')
    overrides = parse_overrides(TINY)
    local, back = tmp_path / "local", tmp_path / "driver"
    run_suite(suite, local, "quick", progress=False, overrides=overrides)
    run_suite(suite, back, "quick", progress=False, overrides=overrides, executor="ray",
              ray=RayOptions(storage="driver"))
    expected = comparable(json.loads((local / "report" / "results.json").read_text()))
    assert len(expected["cells"]) == 1
    assert comparable(json.loads((back / "report" / "results.json").read_text())) == expected
    rec = json.loads((back / "runs" / "capture" / "even-seed0" / "run.json").read_text())
    assert rec["finished"] and rec["heldout_files"] == ["images/f_008.png", "images/f_009.png"]
