"""Fields trained on captured views: their rays, training, and scores on held-out views.

The pieces a run's acquisition loop and evaluation protocol
(:mod:`mitsuba_active.run`) and the environment's rewards
(:mod:`mitsuba_active.rewards`) train and score fields with.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from .cameras import camera_rays
from .checks import is_whole
from .errors import UserError
from .groundtruth import View
from .metrics import distance_error, psnr, ssim

#: Most sparse rays scored per candidate view (images have at most 4096x4096
#: pixels; a planner scores a sample of them).
MAX_CANDIDATE_RAYS = 65536

#: Initial feature spread of the planner's ensemble. Members differ only by
#: their initialisation, and where no training ray reaches, that is all they
#: have: a visible spread is what makes them disagree about unobserved space.
PLANNER_INIT_SCALE = 2.0


def has_distances(source) -> bool:
    """Whether a view source's views carry distances (a rendered scene's do; a dataset's need depth maps)."""
    return bool(getattr(source, "has_distance", True))


def view_rays(views: list[View]) -> dict:
    """Flat training rays of captured views: origins, directions, rgb (M,3); distance, hit, empty (M,);
    the background colour their empty pixels show, or None."""
    parts = [camera_rays(v.camera) for v in views]
    return {
        "origins": np.concatenate([o for o, _ in parts]),
        "directions": np.concatenate([d for _, d in parts]),
        "rgb": np.concatenate([v.rgb.reshape(-1, 3) for v in views]).astype(np.float32),
        "distance": np.concatenate([v.distance.reshape(-1) for v in views]).astype(np.float32),
        "hit": np.concatenate([v.mask.reshape(-1) for v in views]),
        "empty": np.concatenate([v.empty.reshape(-1) for v in views]),
        # The colour the empty pixels show, where the views know it (all alike; else None).
        "background": views[0].background if len({v.background for v in views}) == 1 else None,
    }


def sparse_candidate_rays(candidates, n_rays: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A fixed random subset of R pixel rays per candidate: origins and directions, (C, R, 3) each."""
    if not is_whole(n_rays) or not 0 < n_rays <= MAX_CANDIDATE_RAYS:
        raise UserError(f"rays per candidate must be a whole number in [1, {MAX_CANDIDATE_RAYS}], got {n_rays!r}")
    rng = np.random.default_rng(seed)
    o_all, d_all = [], []
    for cam in candidates:
        o, d = camera_rays(cam)
        idx = rng.choice(len(o), size=n_rays, replace=n_rays > len(o))
        o_all.append(o[idx])
        d_all.append(d[idx])
    return np.stack(o_all), np.stack(d_all)


def train_on(ens, views: list[View], steps: int, progress: bool = False, reset_occupancy: bool = True) -> np.ndarray:
    """Set the rays of ``views`` on ``ens`` and train it ``steps`` steps; returns the (steps,) losses.

    Without views there is nothing to set: 0 steps do nothing, more are a UserError."""
    if not views:
        if is_whole(steps) and steps == 0:
            return np.zeros(0)
        raise UserError(f"train_on: no views to train on ({steps!r} steps asked for)")
    r = view_rays(views)
    ens.set_rays(r["origins"], r["directions"], r["rgb"], r["distance"], r["hit"], reset_occupancy, r["empty"],
                 r["background"])
    return ens.train(steps, progress=progress and steps != 0)


def predict_view(ens, camera) -> dict:
    """Render a whole camera with a field or ensemble: images (H,W,3) / (H,W)."""
    o, d = camera_rays(camera)
    p = ens.predict(o, d)
    h, w = camera.height, camera.width
    return {"rgb": np.clip(p["rgb_mean"], 0, 1).reshape(h, w, 3), "rgb_var": p["rgb_var"].reshape(h, w, 3),
            "distance": p["distance_mean"].reshape(h, w), "distance_var": p["distance_var"].reshape(h, w),
            "opacity": p["opacity"].reshape(h, w)}


def score_views(field_, views: Iterable[View]) -> tuple[dict, list[dict]]:
    """Score a field on ground-truth views (the held-out ones), taken one at a time.

    Returns the means over the views, ``psnr`` (dB), ``ssim`` and
    ``distance_error`` (%; None where no view can give one: SSIM needs 11x11
    pixels, the distance error hits), and each view's :func:`predict_view`.
    """
    preds, p_list, s_list, d_list = [], [], [], []
    for gt in views:
        pred = predict_view(field_, gt.camera)
        preds.append(pred)
        p_list.append(psnr(pred["rgb"], gt.rgb))
        s_list.append(ssim(pred["rgb"], gt.rgb) if min(gt.rgb.shape[:2]) >= 11 else float("nan"))
        d_list.append(distance_error(pred["distance"], gt.distance, gt.mask))
    return {"psnr": float(np.mean(p_list)), "ssim": _mean_or_none(s_list),
            "distance_error": _mean_or_none(d_list)}, preds


def _mean_or_none(values) -> float | None:
    """Mean of the finite values, or None when every value is NaN."""
    return None if np.isnan(values).all() else float(np.nanmean(values))
