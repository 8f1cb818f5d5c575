"""Radiance field ensembles (RFE): pick the views where the ensemble disagrees most."""

from __future__ import annotations

import numpy as np

from ..errors import UserError
from .base import Planner, PlanningState, greedy_top, register, unseen

#: Floor for the variance inside the logarithm, so that views the ensemble
#: agrees on perfectly do not dominate the log form with -inf.
LOG_VARIANCE_FLOOR = 1e-10


def rfe_scores(rgb_var: np.ndarray, form: str = "sum") -> np.ndarray:
    """Information gain of each candidate from per-ray colour variances.

    Args:
        rgb_var: (C, R, 3) variance across ensemble members of each of R rays'
            colour channels, for C candidates.
        form: ``"sum"`` for the sum of variances, ``"log"`` for the sum of
            log-variances (the seed paper's two forms).

    Returns:
        (C,) float64 scores; higher is more informative.
    """
    v = np.asarray(rgb_var, dtype=np.float64)
    if form == "sum":
        return v.sum(axis=(1, 2))
    if form == "log":
        return np.log(np.maximum(v, LOG_VARIANCE_FLOOR)).sum(axis=(1, 2))
    raise UserError(f"unknown RFE score form '{form}'; use 'sum' or 'log'")


@register
class RFEPlanner(Planner):
    """Score every candidate by the ensemble's photometric variance over its sparse rays.

    Batches take the B best unseen candidates.
    """

    name = "rfe"
    needs_ensemble = True
    min_members = 2  # variance across members needs two of them

    def __init__(self, form: str = "sum"):
        rfe_scores(np.zeros((1, 1, 3)), form)  # validate early
        self.form = form

    def options(self):
        return {"form": self.form}

    def select(self, state: PlanningState, batch: int):
        self.check_state(state)
        origins, directions = state.candidate_rays
        c, r = origins.shape[:2]
        pred = state.ensemble.predict(origins.reshape(-1, 3), directions.reshape(-1, 3))
        scores = rfe_scores(pred["rgb_var"].reshape(c, r, 3), self.form)
        return greedy_top(scores, unseen(state), batch), scores
