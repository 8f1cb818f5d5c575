"""The planner interface and the registry by name."""

from __future__ import annotations

import inspect
from dataclasses import dataclass, field

import numpy as np

from ..errors import UserError


@dataclass
class PlanningState:
    """What a planner may look at when choosing views.

    Attributes:
        candidates: the candidate :class:`~mitsuba_active.cameras.Camera` list.
        captured: indices of candidates captured so far (repeats possible).
        ensemble: the trained :class:`~mitsuba_active.field.Ensemble`, or None
            for planners that do not need one.
        candidate_rays: ``(origins, directions)``, each (C, R, 3) float32: a
            fixed sparse set of R rays per candidate.
        rng: the run's ``numpy.random.Generator``.
    """

    candidates: list
    captured: list
    ensemble: object = None
    candidate_rays: tuple | None = None
    rng: np.random.Generator = field(default_factory=np.random.default_rng)


class Planner:
    """Chooses the next views. Subclasses set ``name`` and implement :meth:`select`."""

    name = "planner"
    needs_ensemble = False
    #: Fewest ensemble members the planner can work with.
    min_members = 1
    #: Most members the planner looks at (None: all); a run trains no more.
    max_members = None

    def ensemble_size(self, requested: int) -> int:
        """Members to train for a requested ensemble size (``--ensemble``)."""
        return requested if self.max_members is None else min(requested, self.max_members)

    def check_ensemble_size(self, n_members: int) -> None:
        """UserError when an ensemble of ``n_members`` is too small for this planner."""
        if self.needs_ensemble and n_members < self.min_members:
            raise UserError(f"the {self.name} planner needs an ensemble of at least {self.min_members} members "
                            f"(--ensemble {self.min_members} or more)")

    def check_state(self, state: PlanningState) -> None:
        """UserError unless ``state`` holds what this planner scores with: for
        planners with an ensemble, the ensemble and the candidates' rays."""
        if not self.needs_ensemble:
            return
        missing = [name for name in ("ensemble", "candidate_rays") if getattr(state, name) is None]
        if missing:
            raise UserError(f"the {self.name} planner scores candidates with an ensemble over their rays; "
                            f"the PlanningState has no {' and no '.join(missing)}")
        self.check_ensemble_size(state.ensemble.n_members)

    def select(self, state: PlanningState, batch: int) -> tuple[list[int], np.ndarray | None]:
        """Return ``batch`` candidate indices and the per-candidate scores (C,) they were chosen by, or None."""
        raise NotImplementedError

    def options(self) -> dict:
        """The planner's settings, recorded in run.json."""
        return {}


def unseen(state: PlanningState) -> np.ndarray:
    """Boolean mask (C,) of candidates not captured yet."""
    mask = np.ones(len(state.candidates), dtype=bool)
    mask[list(state.captured)] = False
    return mask


def check_batch(allowed: np.ndarray, batch: int) -> None:
    """UserError when fewer than ``batch`` candidates are ``allowed`` (C,) bool."""
    n_left = int(np.count_nonzero(allowed))
    if n_left < batch:
        raise UserError(f"only {n_left} candidate views are left to choose from, asked for {batch}")


def greedy_top(scores: np.ndarray, allowed: np.ndarray, batch: int) -> list[int]:
    """Indices of the ``batch`` best allowed scores, best first (ties: lower index).

    A NaN score (a candidate the model could not score) is never picked; +inf
    ranks first.
    """
    scores = np.asarray(scores, dtype=np.float64)
    check_batch(allowed, batch)
    ok = np.flatnonzero(np.asarray(allowed, dtype=bool) & ~np.isnan(scores))
    if len(ok) < batch:
        n_left = int(np.count_nonzero(allowed))
        raise UserError(f"only {len(ok)} candidate views are left to choose from, asked for {batch} "
                        f"({n_left - len(ok)} of the {n_left} left could not be scored)")
    order = np.lexsort((ok, -scores[ok]))
    return [int(ok[i]) for i in order[:batch]]


REGISTRY: dict[str, type] = {}


def register(cls):
    """Class decorator: make a planner available by its ``name``."""
    REGISTRY[cls.name] = cls
    return cls


def make_planner(name: str, **options) -> Planner:
    """Instantiate a registered planner; unknown names and options raise UserError."""
    if name not in REGISTRY:
        raise UserError(f"unknown planner '{name}'; choose one of {', '.join(sorted(REGISTRY))}")
    try:
        return REGISTRY[name](**options)
    except (TypeError, ValueError) as exc:
        params = inspect.signature(REGISTRY[name].__init__).parameters.values()
        accepted = [q.name for q in params if q.name != "self" and q.kind == q.POSITIONAL_OR_KEYWORD]
        known = f" (it takes {', '.join(accepted)})" if accepted else " (it takes none)"
        unknown = set(options) - set(accepted)
        why = f"unknown option {', '.join(sorted(unknown))}" if unknown else str(exc)
        raise UserError(f"bad option for planner '{name}': {why}{known}") from None
