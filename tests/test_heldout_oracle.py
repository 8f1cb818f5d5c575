"""benchmarks/heldout_oracle.py: picks made knowing the held-out views, and its refusals."""

import json
import subprocess
import sys

import numpy as np
import pytest

from benchmarks.view_angles import directions
from mitsuba_active.errors import UserError
from mitsuba_active.planners import PlanningState, make_planner
from mitsuba_active.rigs import _cameras_around
from tests.conftest import REPO

#: The planner as a suite names it (loaded by path, its folder on sys.path).
ORACLE = f"{REPO / 'benchmarks' / 'heldout_oracle.py'}:HeldOutKMedian"


def cameras(rng, n):
    dirs = rng.normal(size=(n, 3))
    return _cameras_around(np.zeros(3), 3.0, dirs / np.linalg.norm(dirs, axis=1, keepdims=True), (0, 1, 0),
                           40.0, 8, 8, 1e-3, 1e4)


def test_the_planner_reads_the_scene_of_its_candidates(tmp_path):
    rng = np.random.default_rng(1)
    cams, other = cameras(rng, 12), cameras(rng, 12)
    path = tmp_path / "held.json"
    path.write_text(json.dumps({"scenes": [
        {"name": "other", "candidates": directions(other).tolist(), "heldout": directions(other)[:2].tolist()},
        {"name": "mine", "candidates": directions(cams).tolist(), "heldout": directions(cams)[[3, 8]].tolist()}]}))
    planner = make_planner(ORACLE, heldout=str(path))
    picks, _ = planner.select(PlanningState(cams, [0]), 2)
    assert sorted(picks) == [3, 8]
    with pytest.raises(UserError, match="holds no scene with these 5 candidates"):
        planner.select(PlanningState(cams[:5], [0]), 1)
    with pytest.raises(UserError, match="written by heldout_oracle.py"):
        make_planner(ORACLE, heldout=str(tmp_path / "missing.json"))


def test_refuses_a_folder_without_runs_in_one_line(tmp_path):
    proc = subprocess.run([sys.executable, str(REPO / "benchmarks" / "heldout_oracle.py"), str(tmp_path),
                           "--out", str(tmp_path / "held.json")], capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "no runs under" in proc.stderr
    assert not (tmp_path / "held.json").exists()
