"""Variational uncertainty (S-NeRF style): one stochastic field instead of an ensemble.

The run trains a :class:`~mitsuba_active.field.VariationalField`, whose raw
features are Gaussian at every point, and a candidate scores as under RFE:
the variance of its sparse rays' colours, here over the field's random
draws instead of over ensemble members. This is the seed paper's
variational-uncertainty baseline (S-NeRF*, after Shen et al. 2021), on the
same grid as the other planners.
"""

from __future__ import annotations

from ..field import VariationalField
from ..field.variational import DEFAULT_DRAWS, DEFAULT_ENTROPY_WEIGHT, DEFAULT_MAX_STD, check_options
from .base import register
from .rfe import RFEPlanner


@register
class VariationalPlanner(RFEPlanner):
    """Score every candidate by the variance of its rays' colours over a variational field's draws."""

    name = "variational"
    min_members = 1
    max_members = 1  # one field (its table has a mean and a scale slot)

    def __init__(self, form: str = "sum", draws: int | None = None, max_std: float | None = None,
                 entropy_weight: float | None = None):
        super().__init__(form)
        self.draws = DEFAULT_DRAWS if draws is None else draws
        self.max_std = DEFAULT_MAX_STD if max_std is None else max_std
        self.entropy_weight = DEFAULT_ENTROPY_WEIGHT if entropy_weight is None else entropy_weight
        check_options(self.max_std, self.entropy_weight, self.draws)
        self.draws, self.max_std, self.entropy_weight = int(self.draws), float(self.max_std), float(self.entropy_weight)

    def options(self):
        return {"form": self.form, "draws": self.draws, "max_std": self.max_std,
                "entropy_weight": self.entropy_weight}

    def check_state(self, state):
        super().check_state(state)

        # A plain ensemble of one member has no spread to score: every candidate would score 0.
        if not isinstance(state.ensemble, VariationalField):
            raise TypeError(f"the {self.name} planner scores with a VariationalField (its make_field), "
                            f"got {type(state.ensemble).__name__}")

    def make_field(self, bbox_min, bbox_max, n_members, config, seed):
        return VariationalField(bbox_min, bbox_max, config=config, seed=seed, max_std=self.max_std,
                                entropy_weight=self.entropy_weight, draws=self.draws)
