"""Continuous candidates' rounds: the gap kept from captured views, and refinement against noisy scores."""

import copy
from types import SimpleNamespace

import numpy as np

from mitsuba_active.continuous import PoseSampler, RigSurface, choose_fresh
from mitsuba_active.embodiments import make_embodiment
from mitsuba_active.planners.base import PlanningState, greedy_top, unseen
from mitsuba_active.rigs import fibonacci_directions
from tests.conftest import tiny_source


class Scored:
    """A planner without an ensemble whose score of a camera is ``score(positions (C, 3), rng) -> (C,)``."""

    needs_ensemble = False

    def __init__(self, score):
        self.score = score

    def checked_select(self, state, batch):
        scores = self.score(np.stack([c.position for c in state.candidates]), state.rng)
        return greedy_top(scores, unseen(state), batch), scores


class Still:
    """A journey that keeps the planner's picks."""

    weighs_travel = False

    def weigh(self, picks, scores, allowed, positions=None, views=None):
        return list(picks)


def setup(sphere_xml):
    source = tiny_source(sphere_xml, n_candidates=20, n_heldout=4, resolution=8)
    surface = RigSurface(source.candidates, source.scene.up)
    sampler = PoseSampler(surface, make_embodiment("drone", source.scene), source.heldout, source.scene.free_space)
    return source, surface, sampler


def test_fresh_and_near_poses_keep_the_pools_gap_from_captured_views(sphere_xml):
    source, surface, sampler = setup(sphere_xml)
    units = np.stack([c.position for c in source.candidates]) - surface.centre
    nearest = np.sort(surface.angles(units + surface.centre, units + surface.centre), axis=1)[:, 1]
    assert np.isclose(surface.gap, np.median(nearest))
    avoid = np.stack([c.position for c in source.candidates[:5]])
    rng = np.random.default_rng(0)
    cams = sampler.sample(rng, 40, avoid)
    pos = np.stack([c.position for c in cams])
    assert len(cams) == 40 and surface.angles(pos, avoid).min() >= surface.gap
    near = sampler.around(cams[0], rng, avoid=avoid)
    assert near and surface.angles(np.stack([c.position for c in near]), avoid).min() >= surface.gap
    # Captured views all over the surface: nearer poses rather than none.
    everywhere = surface.centre + np.linalg.norm(units[0]) * fibonacci_directions(400)
    assert sampler.sample(rng, 10, everywhere)


def run_rounds(sphere_xml, score, rounds=24):
    """Rounds of choose_fresh from two captured views; per round, whether the pick left the fresh sample,
    and its score against the best fresh score."""
    source, surface, sampler = setup(sphere_xml)
    cfg = SimpleNamespace(candidates=30, rays_per_candidate=8, seed=0)
    planner = Scored(score)
    taken = source.candidates[:2]
    state = PlanningState(list(source.candidates), [0, 1], None, None, np.random.default_rng(7))
    moved, gains = [], []
    for r in range(rounds):
        rng = np.random.default_rng([r, 1])
        offers = sampler.sample(copy.deepcopy(rng), cfg.candidates, np.stack([c.position for c in taken]))
        chosen, _ = choose_fresh(planner, Still(), sampler, state, [0, 1], taken, 1, rng, cfg)
        fresh = np.stack([c.position for c in offers])
        moved.append(not np.isclose(fresh, chosen[0].position).all(axis=1).any())
        probe = np.random.default_rng(0)
        gains.append(score(chosen[0].position[None], probe)[0] - score(fresh, probe).max())
    return np.array(moved), np.array(gains)


def test_near_poses_replace_a_pick_for_a_real_lead_not_for_noise(sphere_xml):
    # Scores of pure noise: each look's best is luck, and a near pose's lead is too.
    moved, _ = run_rounds(sphere_xml, lambda pos, rng: rng.standard_normal(len(pos)))
    assert moved.mean() < 0.35
    # Scores that rise towards one side: the near poses climb them.
    side = np.array([0.3, 0.8, -0.5])
    moved, gains = run_rounds(sphere_xml, lambda pos, rng: pos @ side)
    assert moved.mean() > 0.5 and (gains >= 0).all() and gains.max() > 0


class Near(Still):
    """A journey that weighs travel: it picks the allowed pose nearest ``here``."""

    weighs_travel = True

    def __init__(self, here):
        self.here = here

    def weigh(self, picks, scores, allowed, positions=None, views=None):
        gaps = np.where(allowed, np.linalg.norm(positions - self.here, axis=1), np.inf)
        return [int(np.argmin(gaps))]


def test_a_journey_that_weighs_travel_takes_the_first_looks_weighed_pick(sphere_xml):
    source, surface, sampler = setup(sphere_xml)
    cfg = SimpleNamespace(candidates=30, rays_per_candidate=8, seed=0)
    taken = source.candidates[:2]
    state = PlanningState(list(source.candidates), [0, 1], None, None, np.random.default_rng(7))
    side = np.array([0.3, 0.8, -0.5])  # scores that a second look would climb away from here
    here = taken[0].position
    for r in range(6):
        rng = np.random.default_rng([r, 2])
        offers = sampler.sample(copy.deepcopy(rng), cfg.candidates, np.stack([c.position for c in taken]))
        chosen, _ = choose_fresh(Scored(lambda pos, rng: pos @ side), Near(here), sampler, state, [0, 1], taken, 1,
                                 rng, cfg)
        fresh = np.stack([c.position for c in offers])
        nearest = fresh[np.argmin(np.linalg.norm(fresh - here, axis=1))]
        assert np.allclose(chosen[0].position, nearest)
