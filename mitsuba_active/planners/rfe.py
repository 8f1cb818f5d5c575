"""Radiance field ensembles (RFE): pick the views where the ensemble disagrees most."""

from __future__ import annotations

import numpy as np

from ..checks import is_number
from ..errors import UserError
from ..field import Ensemble
from ..field.bootstrap import BOOTSTRAP_KINDS
from .base import Planner, PlanningState, greedy_top, register, unseen

#: Floor for the variance inside the logarithm, so that views the ensemble
#: agrees on perfectly do not dominate the log form with -inf.
LOG_VARIANCE_FLOOR = 1e-10


def check_bootstrap(bootstrap) -> str:
    """The ensemble's resampling (:data:`~mitsuba_active.field.bootstrap.BOOTSTRAP_KINDS`), else UserError."""
    if bootstrap not in BOOTSTRAP_KINDS:
        raise UserError(f"unknown bootstrap '{bootstrap}'; use one of {', '.join(BOOTSTRAP_KINDS)}")
    return bootstrap


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

    Options:
        form: ``"sum"`` or ``"log"`` (:func:`rfe_scores`).
        bootstrap: how the members resample the captured rays
            (``Ensemble``'s ``bootstrap``: ``none``, ``rays``, ``views``).
        min_opacity: only rays whose mean opacity over the members exceeds
            this are scored (0: all rays); the others count as certain.
    """

    name = "rfe"
    needs_ensemble = True
    min_members = 2  # variance across members needs two of them

    def __init__(self, form: str = "sum", bootstrap: str = "none", min_opacity: float = 0.0):
        rfe_scores(np.zeros((1, 1, 3)), form)  # validate early
        if not (is_number(min_opacity, finite=True) and 0 <= min_opacity < 1):
            raise UserError(f"rfe needs min_opacity in [0, 1), got {min_opacity!r}")
        self.form, self.bootstrap, self.min_opacity = form, check_bootstrap(bootstrap), float(min_opacity)

    def options(self):
        return {"form": self.form, "bootstrap": self.bootstrap, "min_opacity": self.min_opacity}

    def make_field(self, bbox_min, bbox_max, n_members, config, seed):
        return Ensemble(bbox_min, bbox_max, n_members=n_members, config=config, seed=seed, bootstrap=self.bootstrap)

    def select(self, state: PlanningState, batch: int):
        self.check_state(state)
        origins, directions = state.candidate_rays
        c, r = origins.shape[:2]
        pred = state.ensemble.predict(origins.reshape(-1, 3), directions.reshape(-1, 3))
        var = pred["rgb_var"].reshape(c, r, 3)
        if self.min_opacity > 0:
            var = np.where((pred["opacity"].reshape(c, r) > self.min_opacity)[..., None], var, 0.0)
        scores = rfe_scores(var, self.form)
        return greedy_top(scores, unseen(state), batch), scores
