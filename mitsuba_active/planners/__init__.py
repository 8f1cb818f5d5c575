"""View planners behind one interface, available by name.

>>> from mitsuba_active.planners import make_planner, names
>>> names()
['coverage', 'even', 'fisher', 'random', 'rfe']
"""

from . import fisher, rfe, simple  # noqa: F401  (register the planners)
from .base import REGISTRY, Planner, PlanningState, make_planner


def names() -> list[str]:
    return sorted(REGISTRY)


__all__ = ["Planner", "PlanningState", "make_planner", "names"]
