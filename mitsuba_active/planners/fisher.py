"""Fisher information (FisherRF, Jiang et al. 2024) with a diagonal approximation.

The Hessian of the photometric loss with respect to the field parameters is
approximated by the diagonal of J^T J, the sum over rays of squared
gradients of rendered colours. A candidate's expected information gain is

    score(c) = sum_p H_c[p] / (H_train[p] + lambda)

where H_train sums over the captured views. Batches are chosen greedily,
folding each pick's H_c into H_train. ``lambda`` is ``lam`` times the sum
of two means, of H_train's entries and of all candidates' entries, so the
choice does not depend on the scale of H; as H_train sums the captured
views, the damping grows with the views captured.
"""

from __future__ import annotations

import numpy as np

from ..checks import is_number, is_whole
from ..errors import UserError
from .base import Planner, PlanningState, check_batch, greedy_top, register, unseen


#: Most Hutchinson probes per scoring (each costs a backward pass over every candidate's rays).
MAX_PROBES = 64


def fisher_scores(h_candidates: np.ndarray, h_train: np.ndarray, lam: float) -> np.ndarray:
    """(C,) scores from candidate diagonals (C, P) and the training diagonal (P,)."""
    return (np.asarray(h_candidates, np.float64) / (np.asarray(h_train, np.float64)[None, :] + lam)).sum(axis=1)


def relative_lambda(h_candidates: np.ndarray, h_train: np.ndarray, lam_rel: float) -> float:
    """``lam_rel`` times (mean entry of ``h_train`` + mean entry of ``h_candidates``)."""
    scale = float(np.mean(h_train)) + float(np.mean(h_candidates))
    return lam_rel * max(scale, np.finfo(np.float64).tiny)


def greedy_fisher(h_candidates: np.ndarray, h_train: np.ndarray, allowed: np.ndarray, batch: int,
                  lam_rel: float = 0.1) -> tuple[list[int], np.ndarray]:
    """Greedy batch selection; returns the picks and the first round's scores."""
    h_train = np.array(h_train, dtype=np.float64)
    allowed = np.array(allowed, dtype=bool)
    lam = relative_lambda(h_candidates, h_train, lam_rel)
    picks, first = [], None
    for _ in range(batch):
        scores = fisher_scores(h_candidates, h_train, lam)
        first = scores if first is None else first
        pick = greedy_top(scores, allowed, 1)[0]
        picks.append(pick)
        allowed[pick] = False
        h_train += h_candidates[pick]
    return picks, first


@register
class FisherPlanner(Planner):
    """FisherRF-style planner on one field (ensemble member 0; the run trains only that one)."""

    name = "fisher"
    needs_ensemble = True
    # Member 0 alone is scored, and a member trains the same whatever the
    # ensemble size (see Ensemble), so the others would be wasted work.
    max_members = 1

    def __init__(self, lam: float = 0.1, probes: int = 2):
        # A float probes would be truncated: whole numbers only (and bool, an int too, is neither).
        if not (is_number(lam, finite=True) and lam > 0 and is_whole(probes) and 1 <= probes <= MAX_PROBES):
            raise UserError(f"fisher needs a finite number lam > 0 and a whole number probes in [1, {MAX_PROBES}], "
                            f"got lam={lam!r}, probes={probes!r}")
        self.lam, self.probes = float(lam), int(probes)

    def options(self):
        return {"lam": self.lam, "probes": self.probes}

    def select(self, state: PlanningState, batch: int):
        self.check_state(state)
        check_batch(unseen(state), batch)
        ens = state.ensemble
        origins, directions = state.candidate_rays
        seed = int(state.rng.integers(2**31))
        h_cands = np.stack([ens.fisher_diag(origins[i], directions[i], member=0, probes=self.probes, seed=seed)
                            for i in range(len(origins))]).astype(np.float32)
        captured = sorted(set(state.captured))
        h_train = h_cands[captured].sum(axis=0) if captured else np.zeros(h_cands.shape[1])
        return greedy_fisher(h_cands, h_train, unseen(state), batch, self.lam)
