"""What a smaller largest gap buys: a covering of the candidates planned for the whole budget.

    mitsuba-active bench benchmarks/suites/shared.toml --profile full --workers 2 \\
        --set "eval_views=[10,20]" --planners benchmarks/planned_cover.py:PlannedCover \\
        --seeds 0,1,2 --out bench/planned-cover
    python benchmarks/view_angles.py bench/planned-cover bench/shared-full --exclude cbox,mic

``coverage`` picks, one view at a time, the candidate farthest from every captured
view (greedy k-center). ``PlannedCover`` plans all of the run's views each round
(:func:`mitsuba_active.planners.covering.planned_cover`: ``coverage``'s picks up to the
budget, then swaps that lower the largest gap) and captures the planned view farthest
from every captured one. Its largest gap at the budget is smaller than ``coverage``'s,
so the suite measures whether a smaller gap alone scores higher.
"""

from __future__ import annotations

import numpy as np

from mitsuba_active.errors import UserError
from mitsuba_active.planners import Planner, PlanningState, check_batch, unseen
from mitsuba_active.planners.covering import direction_angles, nearest_angles, planned_mask


class PlannedCover(Planner):
    """The planned view farthest from every captured one (a measurement, beside ``coverage``)."""

    def select(self, state: PlanningState, batch: int):
        allowed = unseen(state)
        check_batch(allowed, batch)
        between = direction_angles(state.candidates)
        taken = list(dict.fromkeys(int(i) for i in state.captured))
        picks, first = [], None
        for _ in range(batch):
            planned = planned_mask(state, picks)
            if planned is None:
                raise UserError("PlannedCover needs the run's budget, and views left to plan within it")
            nearest = nearest_angles(between, taken)
            first = nearest if first is None else first
            pick = int(np.argmax(np.where(planned, nearest, -1.0)))
            picks.append(pick)
            taken.append(pick)
        return picks, first
