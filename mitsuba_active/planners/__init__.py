"""View planners behind one interface, available by name.

>>> from mitsuba_active.planners import make_planner, names
>>> names()
['coverage', 'even', 'fisher', 'hybrid', 'random', 'rfe', 'variational']

A planner of your own is a :class:`Planner` subclass, named by reference
(``my_planners.py:MyPlanner``) wherever a planner's name is taken; see
``examples/custom_planner.py``.
"""

from . import fisher, hybrid, rfe, simple, variational  # noqa: F401  (register the planners)
from .base import (REGISTRY, Planner, PlanningState, check_batch, greedy_top, make_planner, planner_folder,
                   planner_label, planner_rng, register, unseen)


def names() -> list[str]:
    return sorted(REGISTRY)


__all__ = ["Planner", "PlanningState", "make_planner", "names", "planner_label", "planner_folder", "planner_rng",
           "register", "greedy_top", "unseen", "check_batch"]
