"""A planner of your own: ensemble variance, weighted by how new a viewing direction is.

Use it wherever a planner's name is taken, by reference (FILE.py:CLASS):

    mitsuba-active plan --planner examples/custom_planner.py:NoveltyWeightedVariance
    mitsuba-active plan --planner examples/custom_planner.py:NoveltyWeightedVariance --planner-option power=2
    python examples/compare_planners.py --planners examples/custom_planner.py:NoveltyWeightedVariance rfe coverage

or in a bench suite, relative to the suite file:

    planners = ["rfe", "coverage", "custom_planner.py:NoveltyWeightedVariance"]

A planner subclasses ``Planner`` and implements ``select(state, batch)``: it
returns ``batch`` candidate indices and the per-candidate scores it ranked
them by (or None). With ``needs_ensemble = True`` the run trains an ensemble
on the captured views and hands it over in ``state.ensemble``, together with
a fixed sparse set of rays per candidate (``state.candidate_rays``).
``__init__``'s keyword arguments are the planner's options
(``--planner-option NAME=VALUE``; a ``ValueError`` there is reported as a bad
option), and ``options()`` records them in run.json. Runs record a digest of
this file too: a run or suite folder is not resumed with edited code.
"""

import numpy as np

from mitsuba_active.checks import is_number
from mitsuba_active.planners import Planner, PlanningState, greedy_top, unseen
from mitsuba_active.planners.rfe import rfe_scores


class NoveltyWeightedVariance(Planner):
    """RFE's score (the ensemble's summed colour variance over a candidate's
    rays) times ``(angle / pi) ** power``, where ``angle`` is the angle (radians)
    between the candidate's viewing direction and the nearest captured one:
    ``power=0`` is RFE, larger powers lean towards the ``coverage`` planner."""

    needs_ensemble = True
    min_members = 2  # a variance across members needs two of them

    def __init__(self, power: float = 1.0):
        # A planner's options come from the command line or a suite file: check them with a clear message.
        if not is_number(power) or not power >= 0:
            raise ValueError(f"power must be a number >= 0, got {power!r}")
        self.power = float(power)

    def options(self) -> dict:
        return {"power": self.power}

    def select(self, state: PlanningState, batch: int):
        self.check_state(state)  # says what is missing when used outside a run
        origins, directions = state.candidate_rays  # (C, R, 3) each
        c, r = origins.shape[:2]
        pred = state.ensemble.predict(origins.reshape(-1, 3), directions.reshape(-1, 3))
        variance = rfe_scores(pred["rgb_var"].reshape(c, r, 3))  # (C,)
        forward = np.stack([cam.forward for cam in state.candidates])  # (C, 3) unit viewing directions
        if state.captured:
            cos = np.clip(forward @ forward[list(state.captured)].T, -1.0, 1.0)
            angle = np.arccos(cos.max(axis=1))
        else:
            angle = np.full(c, np.pi)
        scores = variance * (angle / np.pi) ** self.power
        return greedy_top(scores, unseen(state), batch), scores
