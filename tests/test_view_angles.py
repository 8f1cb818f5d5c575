"""benchmarks/view_angles.py: its picks by direction alone, and its refusals."""

import json
import subprocess
import sys

import numpy as np

from benchmarks.view_angles import farthest_picks, k_median_over, k_median_picks, largest_gap, mean_nearest
from mitsuba_active.rigs import _cameras_around
from tests.conftest import REPO


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_k_median_takes_the_crowd_where_farthest_takes_the_lone_view():
    rng = np.random.default_rng(0)
    crowd = unit([0, 0, 1] + 0.15 * rng.normal(size=(8, 3)))
    cands = np.concatenate([unit([[1, 0, 0]]), crowd, unit([[-1, 0, 0]])])
    cameras = _cameras_around(np.zeros(3), 3.0, cands, (0, 1, 0), 40.0, 8, 8, 1e-3, 1e4)
    assert farthest_picks(cameras, [0], 2)[1] == 9  # the lone view, farthest from +x
    pick = k_median_picks(cands, [0], 2)[1]
    assert 1 <= pick <= 8
    # Its pick lowers the candidates' mean angle to their nearest pick more than the lone one does.
    assert mean_nearest(cands, cands[[0, pick]]) < mean_nearest(cands, cands[[0, 9]])


def test_k_median_over_other_clients_skips_what_is_not_allowed():
    rng = np.random.default_rng(0)
    cands = unit(rng.normal(size=(40, 3)))
    clients = unit(cands[[5, 17]] + 0.01)  # beside two of the candidates
    allowed = np.ones(40, bool)
    allowed[5] = False  # already captured: the next nearest to it must do
    picks, scores = k_median_over(clients, cands, [0], allowed, 2)
    assert 17 in picks and 5 not in picks and len(set(picks)) == 2
    assert scores[5] == -np.inf and np.argmax(scores) == picks[0]
    # The first pick lowers the clients' mean angle to their nearest capture at least as much as any other.
    assert all(mean_nearest(clients, cands[[0, picks[0]]]) <= mean_nearest(clients, cands[[0, k]]) + 1e-9
               for k in np.flatnonzero(allowed))


def test_largest_gap_is_the_farthest_candidate_from_every_taken_direction():
    cands = unit([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [1, 1, 0]])
    assert np.isclose(largest_gap(cands, cands[[0]]), 180.0)  # -x, opposite the one taken
    assert np.isclose(largest_gap(cands, cands[[0, 2]]), 90.0)  # +y, between the two
    assert np.isclose(largest_gap(cands, cands[[0, 1, 2]]), 45.0)  # (1, 1, 0) between +x and +y
    assert np.isclose(largest_gap(cands, cands), 0.0, atol=1e-4)


def test_refuses_folders_without_runs_and_damaged_records(tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, str(REPO / "benchmarks" / "view_angles.py"), *map(str, args)],
                              capture_output=True, text=True, cwd=REPO)

    proc = run(tmp_path)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "no runs under" in proc.stderr
    record = tmp_path / "runs" / "spot" / "even-seed0" / "run.json"
    record.parent.mkdir(parents=True)
    record.write_text(json.dumps({"config": {}}))
    proc = run(tmp_path)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "is not a run record" in proc.stderr
    assert "Traceback" not in proc.stderr
