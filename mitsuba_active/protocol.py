"""The evaluation protocol: a fresh field trained on the views chosen so far, scored on held-out views.

Evaluation follows the seed paper: at each reported view count a *fresh*
field, with the same architecture, seed and steps for every planner, is
trained on the views chosen so far and scored on the held-out views (PSNR,
PSNR of the foreground, SSIM, and mean relative distance error on pixels that
hit geometry), beside the PSNRs of the background colour alone. Everything
here takes plain values; a run's settings become them in
:mod:`mitsuba_active.run`.
"""

from __future__ import annotations

import time

import numpy as np

from .field import Ensemble, FieldConfig
from .groundtruth import View
from .training import score_views, train_on


def loss_psnr(losses) -> float:
    """PSNR (dB) of a mean photometric MSE."""
    return float(-10.0 * np.log10(max(float(np.mean(losses)), 1e-10)))


def new_field(source, config: FieldConfig, n_members: int, seed: int, make_field=None):
    """A field of ``n_members`` over the source's bounds, untrained.

    ``make_field``: a planner's :meth:`~mitsuba_active.planners.Planner.make_field`
    (the field it scores with), else an :class:`~mitsuba_active.field.Ensemble`.
    """
    make_field = make_field or Ensemble
    return make_field(source.bbox_min, source.bbox_max, n_members=n_members, config=config, seed=seed)


def evaluate_views(source, views: list[View], config: FieldConfig, seed: int, steps: int,
                   progress: bool = False) -> tuple[dict, list[dict]]:
    """Train a fresh one-member field (``config``, ``seed``) on ``views`` for
    ``steps`` steps; score it on every held-out view of ``source``.

    Returns the metrics (means over held-out views, see
    :func:`~.training.score_views`; ``fit_psnr`` and ``fit_start_psnr``: the
    field's PSNR on its own training rays over the last and the first tenth of
    its training steps; ``eval_seconds``) and the per-view predictions.
    """
    t0 = time.perf_counter()
    field_ = new_field(source, config, 1, seed)
    losses = train_on(field_, views, steps, progress)
    # How well the field fits its own training views (the last tenth of its steps), and fitted them at first.
    tenth = max(1, len(losses) // 10)
    fit_psnr, start_psnr = loss_psnr(losses[-tenth:]), loss_psnr(losses[:tenth])
    scores, preds = score_views(field_, (source.heldout_view(i) for i in range(len(source.heldout))))
    metrics = {"views": len(views), **scores, "fit_psnr": fit_psnr, "fit_start_psnr": start_psnr,
               "eval_seconds": round(time.perf_counter() - t0, 3)}
    return metrics, preds
