"""The example scripts run end to end at tiny settings."""

import json
import subprocess
import sys

import pytest

from tests.conftest import REPO


def _run(script, *args):
    proc = subprocess.run([sys.executable, str(REPO / "examples" / script), "--tiny", *args], capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


def test_custom_scene_example(tmp_path):
    out = _run("custom_scene.py", "--out", str(tmp_path / "c"))
    assert "PSNR" in out
    rec = json.loads((tmp_path / "c" / "run" / "run.json").read_text())
    assert rec["finished"] and len(rec["captured"]) == 4
    assert (tmp_path / "c" / "scene" / "custom.xml").is_file()


@pytest.mark.parametrize("planner", ["rfe", "variational", "even"])
def test_planning_loop_example(planner):
    out = _run("planning_loop.py", "--planner", planner)
    last = out.strip().splitlines()[-1]
    captured = json.loads(last.split("captured ")[1].split(";")[0])
    assert last.startswith(f"{planner}: captured") and "held-out PSNR" in last
    assert len(captured) == 4 and len(set(captured)) == 4  # 2 initial views, then 2 distinct picks
    scored = planner != "even"
    assert out.count("views: captured candidate") == 2 and ("best of 12" in out) == scored
    # A scoring planner's field disagrees with itself about what it has not seen: the best score is not 0.
    best = [float(line.split("(score ")[1].split(",")[0]) for line in out.splitlines() if "(score " in line]
    assert len(best) == (2 if scored else 0) and all(b > 0 for b in best), out


def test_compare_planners_example(tmp_path):
    mine = f"{REPO / 'examples' / 'custom_planner.py'}:NoveltyWeightedVariance"
    out = _run("compare_planners.py", "--out", str(tmp_path / "p"), "--planners", "rfe", "even", mine)
    assert "\nrfe " in out and "\neven " in out and "\ncustom_planner.py:NoveltyWeightedVariance 2v:" in out
    assert (tmp_path / "p" / "psnr.png").is_file()
    assert json.loads((tmp_path / "p" / "custom_planner.py_NoveltyWeightedVariance" / "run.json").read_text())[
        "finished"]


def test_the_example_planner_weighs_variance_by_novelty():
    from types import SimpleNamespace

    import numpy as np

    from mitsuba_active.rigs import fibonacci_sphere
    from mitsuba_active.errors import UserError
    from mitsuba_active.planners import PlanningState, make_planner

    cands = fibonacci_sphere(12, [0, 0, 0], 2.0, 40.0, 8, 8)
    variance = np.linspace(1.0, 2.0, 12)  # the last candidate is the most uncertain

    def predict(o, d):  # each candidate's 4 rays share its variance
        return {"rgb_var": np.repeat(variance, 4)[:, None].repeat(3, 1) / 12.0}

    state = PlanningState(cands, [0], ensemble=SimpleNamespace(n_members=2, predict=predict),
                          candidate_rays=(np.zeros((12, 4, 3)), np.zeros((12, 4, 3))))
    ref = f"{REPO / 'examples' / 'custom_planner.py'}:NoveltyWeightedVariance"
    picks, scores = make_planner(ref, power=0.0).select(state, 1)
    assert picks == [11] and np.allclose(scores, variance)  # RFE's sum of variances
    forward = np.stack([c.forward for c in cands])
    opposite = int(np.argmin(forward @ forward[0]))
    picks, _ = make_planner(ref, power=50.0).select(state, 1)
    assert picks == [opposite] != [11]  # the direction farthest from the captured one
    # Its option, given as text on a command line, gets the example's own message.
    with pytest.raises(UserError, match=r"power must be a number >= 0, got 'abc' \(it takes power\)"):
        make_planner(ref, power="abc")
