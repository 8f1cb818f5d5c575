"""Baselines that need no model: random, even, coverage."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .base import Planner, PlanningState, check_batch, greedy_top, register, unseen


@register
class RandomPlanner(Planner):
    """Uniform sampling *with* replacement (a view may be captured twice), as in the seed paper."""

    name = "random"

    def select(self, state: PlanningState, batch: int):
        if state.out_of_reach:
            within = np.setdiff1d(np.arange(len(state.candidates)), list(state.out_of_reach))
            return [int(i) for i in state.rng.choice(within, size=batch)], None
        return [int(i) for i in state.rng.integers(0, len(state.candidates), size=batch)], None


@register
class EvenPlanner(Planner):
    """Uniform sampling *without* replacement: never repeats a view."""

    name = "even"

    def select(self, state: PlanningState, batch: int):
        # Random scores ranked among unseen views = a uniform draw without replacement.
        return greedy_top(state.rng.random(len(state.candidates)), unseen(state), batch), None


@register
class CoveragePlanner(Planner):
    """Farthest-point selection over viewing directions (geometry only).

    The score of a candidate is the angle (radians) between its viewing
    direction and the closest direction captured so far; picks are greedy.
    """

    name = "coverage"

    def select(self, state: PlanningState, batch: int):
        check_batch(unseen(state), batch)
        dirs = np.stack([c.forward for c in state.candidates])
        taken = list(state.captured)
        picks, first_scores = [], None
        for _ in range(batch):
            if taken:
                cos = np.clip(dirs @ dirs[taken].T, -1.0, 1.0)
                scores = np.arccos(cos.max(axis=1))
            else:
                scores = np.zeros(len(dirs))
            first_scores = scores if first_scores is None else first_scores
            allowed = unseen(replace(state, captured=taken))
            pick = greedy_top(scores, allowed, 1)[0]
            picks.append(pick)
            taken.append(pick)
        return picks, first_scores
