"""Coverings of the candidates' viewing directions, planned for a budget of views.

``coverage`` adds, one view at a time, the candidate farthest from every
captured view. A run that knows its budget can plan all of its views at
once instead: :func:`planned_cover` starts from those farthest picks and
swaps planned views while a swap lowers the *largest gap*, the largest angle
from a candidate's direction to its nearest planned one. A planner that
captures only planned views ends with a largest gap no wider than the plan's.
"""

from __future__ import annotations

import numpy as np


def direction_angles(cameras) -> np.ndarray:
    """(C, C) float64 angles (radians) between the viewing directions of ``cameras`` (C of them)."""
    forward = np.stack([c.forward for c in cameras]).astype(np.float64)
    return np.arccos(np.clip(forward @ forward.T, -1.0, 1.0))


def nearest_angles(between: np.ndarray, taken: list) -> np.ndarray:
    """(C,) float: each candidate's angle to the nearest of ``taken`` (zeros where none is):
    ``coverage``'s score, given ``between`` as for :func:`planned_cover`."""
    return between[:, taken].min(axis=1) if len(taken) else np.zeros(len(between))


def planned_cover(between: np.ndarray, fixed: list, n: int, allowed: np.ndarray) -> list[int]:
    """``n`` candidates, ``fixed`` first, whose largest gap local search has lowered.

    Args:
        between: (C, C) float angles (radians) between the candidates' directions.
        fixed: indices the set keeps (the views captured so far); repeats count once.
        n: size of the set, at least that of ``fixed``.
        allowed: (C,) bool, the candidates that may join it.

    Returns:
        The set's indices: ``fixed`` (without repeats), then the planned ones.
        Ties go to the lower mean gap, then to the lower index.
    """
    fixed = list(dict.fromkeys(int(i) for i in fixed))
    free = np.asarray(allowed, dtype=bool).copy()
    free[fixed] = False
    if n < len(fixed) or n - len(fixed) > int(np.count_nonzero(free)):
        raise ValueError(f"planned_cover: cannot plan {n} views around {len(fixed)} fixed ones "
                         f"with {int(np.count_nonzero(free))} others allowed")
    planned = list(fixed)
    while len(planned) < n:  # coverage's picks to start from
        pick = int(np.argmax(np.where(free, nearest_angles(between, planned), -1.0)))
        planned.append(pick)
        free[pick] = False
    nearest = nearest_angles(between, planned)  # with nothing planned there is no slot to swap
    best = (nearest.max(), nearest.mean())
    lowered = True
    while lowered:
        lowered = False
        for slot in range(len(fixed), n):
            rest = planned[:slot] + planned[slot + 1:]
            # (C judged, C swapped in): each candidate's nearest angle with each one in the slot.
            nearest = np.minimum(between[:, rest].min(axis=1)[:, None], between) if rest else between
            largest = np.where(free, nearest.max(axis=0), np.inf)
            mean = nearest.mean(axis=0)
            c = int(np.lexsort((mean, largest))[0])
            # A largest gap within 1e-9 of the best counts as the same (rounding differs by column order).
            if largest[c] < best[0] - 1e-9 or (abs(largest[c] - best[0]) <= 1e-9 and mean[c] < best[1] - 1e-9):
                free[planned[slot]], free[c] = True, False
                planned[slot], best, lowered = c, (largest[c], mean[c]), True
    return planned


def planned_mask(state, picks: list) -> np.ndarray | None:
    """(C,) bool: the views of a covering planned for ``state.budget`` that are
    neither captured nor among ``picks``, within reach; None where the budget is
    unknown (``state.budget`` None) or spent."""
    if state.budget is None:
        return None
    taken = list(dict.fromkeys([*state.captured, *picks]))
    allowed = np.ones(len(state.candidates), dtype=bool)
    allowed[taken] = False
    allowed[list(state.out_of_reach)] = False
    n = min(int(state.budget), len(taken) + int(np.count_nonzero(allowed)))
    if n <= len(taken):  # the budget is spent, or nothing is left to plan
        return None
    mask = np.zeros(len(state.candidates), dtype=bool)
    mask[planned_cover(direction_angles(state.candidates), taken, n, allowed)[len(taken):]] = True
    return mask
