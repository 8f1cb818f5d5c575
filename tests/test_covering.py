"""Coverings planned for a budget (planners.covering), hybrid's ``cover`` and benchmarks/planned_cover.py."""

import numpy as np
import pytest

from benchmarks.view_angles import directions, farthest_picks, largest_gap
from mitsuba_active.errors import UserError
from mitsuba_active.planners import PlanningState, make_planner
from mitsuba_active.planners.covering import direction_angles, planned_cover, planned_mask
from mitsuba_active.rigs import _cameras_around, fibonacci_directions, fibonacci_sphere
from mitsuba_active.run import Run, RunConfig, sparse_candidate_rays
from tests.conftest import REPO, tiny_source
from tests.test_planners_hybrid import Sphere

#: The measurement's planner as a suite names it (loaded by path).
PLANNED = f"{REPO / 'benchmarks' / 'planned_cover.py'}:PlannedCover"


def cameras(dirs):
    return _cameras_around(np.zeros(3), 3.0, dirs, (0, 1, 0), 40.0, 8, 8, 1e-3, 1e4)


def test_the_planned_set_keeps_the_captured_views_and_lowers_the_largest_gap():
    dirs = fibonacci_directions(60)
    between = direction_angles(cameras(dirs))
    allowed = np.ones(60, bool)
    allowed[[5, 6]] = False
    lower = 0
    for fixed in ([0, 31], [12, 12, 40], [7]):
        planned = planned_cover(between, fixed, 12, allowed)
        assert planned[:len(set(fixed))] == list(dict.fromkeys(fixed))
        assert len(set(planned)) == 12 and not {5, 6} & set(planned)
        farthest = farthest_picks(cameras(dirs), list(dict.fromkeys(fixed)), 12)
        gap, gap_farthest = largest_gap(dirs, dirs[planned]), largest_gap(dirs, dirs[farthest])
        assert gap <= gap_farthest + 1e-9
        lower += gap < gap_farthest - 1.0
    assert lower >= 1  # local search does more than keep coverage's picks
    with pytest.raises(ValueError, match="cannot plan 1 views around 2"):
        planned_cover(between, [0, 1], 1, allowed)


def test_the_planned_views_left_are_within_reach_and_only_where_the_budget_is_known():
    cams = cameras(fibonacci_directions(30))
    assert planned_mask(PlanningState(cams, [0, 1]), []) is None
    assert planned_mask(PlanningState(cams, [0, 1, 2], budget=3), []) is None
    state = PlanningState(cams, [0, 1, 1], out_of_reach={4, 9}, budget=8)
    mask = planned_mask(state, [7])
    assert mask.sum() == 5 and not mask[[0, 1, 4, 7, 9]].any()


def test_hybrid_with_cover_picks_a_planned_view():
    cands = fibonacci_sphere(12, [0, 0, 0], 3.0, 40.0, 8, 8)
    dirs = directions(cands)
    rays = sparse_candidate_rays(cands, 64, 0)
    # The members disagree only about the side of one view next to the captured one.
    near = int(np.argsort(-(dirs @ dirs[0]))[1])
    lean = Sphere(lambda p: np.where(p @ dirs[near] > 0.9, 50.0, 0.0))
    state = PlanningState(cands, [0], lean, rays, budget=3)
    planned = planned_mask(state, [])
    plain, _ = make_planner("hybrid", cover=0).select(state, 1)
    assert not planned[plain[0]]  # the disagreement alone leads to an unplanned view
    picks, _ = make_planner("hybrid").checked_select(state, 2)  # cover=1, the default
    assert planned[picks[0]] and planned_mask(state, picks[:1])[picks[1]]
    # Without a budget, cover changes nothing.
    free = PlanningState(cands, [0], lean, rays)
    assert make_planner("hybrid").select(free, 1)[0] == make_planner("hybrid", cover=0).select(free, 1)[0]
    with pytest.raises(UserError, match="cover 0 or 1"):
        make_planner("hybrid", cover=2)


def test_a_run_tells_the_planner_its_budget(spot_xml, tmp_path):
    source = tiny_source(spot_xml, n_candidates=10, n_heldout=3, resolution=16)
    cfg = RunConfig(scene=str(source.scene.path), planner=PLANNED, budget=5, initial_views=2, resolution=16,
                    candidates=10, heldout=3, spp=4, eval_views=[5], eval_steps=30,
                    field=dict(batch_rays=512, n_samples=32, render_batch=1024))
    rec = Run(source, cfg, tmp_path / "run", progress=False, log=lambda m: None).execute()
    captured = rec["captured"]
    assert len(captured) == 5
    for k in range(2, 5):  # each pick is a view of the covering planned from the views before it
        assert planned_mask(PlanningState(source.candidates, captured[:k], budget=5), [])[captured[k]]
