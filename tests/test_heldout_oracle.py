"""benchmarks/heldout_oracle.py: picks made knowing the held-out views, and its refusals."""

import json

import numpy as np
import pytest

from benchmarks.heldout_oracle import HeldOutKMedian, forwards, k_median_over
from mitsuba_active.errors import UserError
from mitsuba_active.planners import PlanningState
from mitsuba_active.rigs import _cameras_around


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def cameras(dirs):
    return _cameras_around(np.zeros(3), 3.0, unit(dirs), (0, 1, 0), 40.0, 8, 8, 1e-3, 1e4)


def test_picks_go_where_the_held_out_views_are():
    rng = np.random.default_rng(0)
    cands = unit(rng.normal(size=(40, 3)))
    held = unit(cands[[5, 17]] + 0.01)  # held-out views beside two of the candidates
    allowed = np.ones(40, bool)
    allowed[5] = False  # already captured: the next nearest to it must do
    picks, scores = k_median_over(held, cands, [0], allowed, 2)
    assert 17 in picks and 5 not in picks and len(set(picks)) == 2
    assert scores[5] == -np.inf and np.argmax(scores) == picks[0]
    # Each pick lowers the held-out views' mean angle to their nearest capture below any other candidate's.
    nearest = lambda taken: np.arccos(np.clip(held @ cands[taken].T, -1, 1)).min(axis=1).mean()
    assert all(nearest([0, picks[0]]) <= nearest([0, k]) + 1e-12 for k in np.flatnonzero(allowed))


def test_the_planner_reads_the_scene_of_its_candidates(tmp_path):
    rng = np.random.default_rng(1)
    cams = cameras(rng.normal(size=(12, 3)))
    other = cameras(rng.normal(size=(12, 3)))
    held = forwards(cams)[[3, 8]]
    path = tmp_path / "held.json"
    path.write_text(json.dumps({"scenes": [
        {"name": "other", "candidates": forwards(other).tolist(), "heldout": forwards(other)[:2].tolist()},
        {"name": "mine", "candidates": forwards(cams).tolist(), "heldout": held.tolist()}]}))
    planner = HeldOutKMedian(heldout=str(path))
    picks, _ = planner.select(PlanningState(cams, [0]), 2)
    assert sorted(picks) == [3, 8]
    with pytest.raises(UserError, match="holds no scene with these 5 candidates"):
        planner.select(PlanningState(cams[:5], [0]), 1)
    with pytest.raises(ValueError, match="written by heldout_oracle.py"):
        HeldOutKMedian(heldout=str(tmp_path / "missing.json"))


def test_refuses_a_folder_without_runs_in_one_line(tmp_path, capsys):
    from benchmarks.heldout_oracle import main

    assert main([str(tmp_path), "--out", str(tmp_path / "held.json")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no runs under" in err and not (tmp_path / "held.json").exists()
