"""Fields trained on captured views: their rays, training, and scores on held-out views.

The pieces a run's acquisition loop and evaluation protocol
(:mod:`mitsuba_active.run`) and the environment's rewards
(:mod:`mitsuba_active.rewards`) train and score fields with.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from .cameras import camera_rays, camera_valid
from .checks import is_whole
from .groundtruth import View
from .metrics import dilate, distance_error, foreground_radius, masked_psnr, psnr, ssim

#: Most sparse rays scored per candidate view (images have at most 4096x4096
#: pixels; a planner scores a sample of them).
MAX_CANDIDATE_RAYS = 65536

#: Initial feature spread of the planner's ensemble. Members differ only by
#: their initialisation, and where no training ray reaches, that is all they
#: have: a visible spread is what makes them disagree about unobserved space.
PLANNER_INIT_SCALE = 2.0

#: An evaluation field whose held-out PSNR is less than this (dB) above that
#: of the background colour alone (:func:`background_colour`) has learnt too
#: little of the scene for its scores to compare views: a run says so.
FLOOR_MARGIN_DB = 3.0
#: An evaluation field that fits its own training rays less than this (dB)
#: better at the end of its training than at its start has barely trained.
FIT_GAIN_DB = 3.0


def has_distances(source) -> bool:
    """Whether a view source's views carry distances (a rendered scene's do; a dataset's need depth maps)."""
    return bool(getattr(source, "has_distance", True))


def view_rays(views: list[View]) -> dict:
    """Flat training rays of captured views: origins, directions, rgb (M,3); distance, hit, empty (M,);
    the background colour their empty pixels show, or None. Pixels without a ray (a lens camera's,
    :func:`~mitsuba_active.cameras.camera_valid`) are left out."""
    parts = [camera_rays(v.camera) for v in views]
    keep = np.concatenate([camera_valid(v.camera) for v in views])
    rays = {
        "origins": np.concatenate([o for o, _ in parts]),
        "directions": np.concatenate([d for _, d in parts]),
        "rgb": np.concatenate([v.rgb.reshape(-1, 3) for v in views]).astype(np.float32),
        "distance": np.concatenate([v.distance.reshape(-1) for v in views]).astype(np.float32),
        "hit": np.concatenate([v.mask.reshape(-1) for v in views]),
        "empty": np.concatenate([v.empty.reshape(-1) for v in views]),
    }
    if not keep.all():
        rays = {k: a[keep] for k, a in rays.items()}
    # The colour the empty pixels show, where the views know it (all alike; else None).
    rays["background"] = views[0].background if len({v.background for v in views}) == 1 else None
    return rays


def sparse_candidate_rays(candidates, n_rays: int, seed: int | np.random.Generator,
                          same_pixels: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A fixed random subset of R pixel rays per candidate (of the pixels that have one:
    :func:`~mitsuba_active.cameras.camera_valid`): origins and directions, (C, R, 3) each.

    ``seed``: an int, or a ``numpy.random.Generator`` to draw from. ``same_pixels``: every
    candidate's rays go through the first one's pixels (candidates sharing its intrinsics), so
    that near poses differ in their rays by their views, not by their draws."""
    if not is_whole(n_rays) or not 0 < n_rays <= MAX_CANDIDATE_RAYS:
        raise ValueError(f"rays per candidate must be a whole number in [1, {MAX_CANDIDATE_RAYS}], got {n_rays!r}")
    rng = np.random.default_rng(seed)
    o_all, d_all, idx = [], [], None
    for cam in candidates:
        o, d = camera_rays(cam)
        if idx is None or not same_pixels:
            valid = camera_valid(cam)
            if valid.all():  # a pinhole's draws stay as they were
                idx = rng.choice(len(o), size=n_rays, replace=n_rays > len(o))
            else:
                pixels = np.flatnonzero(valid)
                idx = pixels[rng.choice(len(pixels), size=n_rays, replace=n_rays > len(pixels))]
        o_all.append(o[idx])
        d_all.append(d[idx])
    return np.stack(o_all), np.stack(d_all)


def acquisition_steps(views_before: int, views_added: int, initial_steps: int, steps_per_view: int) -> int:
    """Training steps a planner's ensemble takes when ``views_added`` views
    join ``views_before``: ``steps_per_view`` for each, plus ``initial_steps``
    when they are its first data (a run's initial views, or its first pick
    without them)."""
    if not (is_whole(views_before) and is_whole(views_added) and views_before >= 0 and views_added >= 0):
        raise ValueError(f"acquisition_steps: view counts must be whole numbers >= 0, got "
                         f"{views_before!r} and {views_added!r}")
    return (initial_steps if views_before == 0 and views_added else 0) + steps_per_view * views_added


def train_on(ens, views: list[View], steps: int, progress: bool = False, reset_occupancy: bool = True) -> np.ndarray:
    """Set the rays of ``views`` on ``ens`` and train it ``steps`` steps; returns the (steps,) losses.

    Without views there is nothing to set: 0 steps do nothing, more are a ValueError."""
    if not views:
        if is_whole(steps) and steps == 0:
            return np.zeros(0)
        raise ValueError(f"train_on: no views to train on ({steps!r} steps asked for)")
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


def background_colour(view: View) -> np.ndarray:
    """(3,) float64 colour in [0, 1] of the trivial prediction of a view: its known background
    (a dataset's), else the mean colour of its empty pixels (a rendered view's environment),
    else white (a view that sees geometry everywhere)."""
    if view.background is not None:
        return np.asarray(view.background, np.float64)
    empty = view.empty
    if empty.any():
        return np.asarray(view.rgb, np.float64)[empty].mean(axis=0)
    return np.ones(3)


def score_views(field_, views: Iterable[View]) -> tuple[dict, list[dict]]:
    """Score a field on ground-truth views (the held-out ones), taken one at a time.

    Returns the means over the views, ``psnr`` and ``psnr_fg`` (dB, the whole
    image and its foreground: :func:`~.metrics.foreground_psnr` of
    :attr:`View.foreground`), ``ssim`` and ``distance_error`` (%), and the same
    PSNRs of the trivial prediction, each view's :func:`background_colour`
    alone (``floor_psnr``, ``floor_psnr_fg``); None where no view can give one
    (SSIM needs 11x11 pixels, the distance error hits, the foreground PSNR
    geometry); and each view's :func:`predict_view`. A lens camera's pixels without a ray
    (:func:`~mitsuba_active.cameras.camera_valid`) are left out of the scores (SSIM, over whole
    windows, takes the ground truth there).
    """
    preds, scores = [], {k: [] for k in ("psnr", "psnr_fg", "ssim", "distance_error", "floor_psnr",
                                         "floor_psnr_fg")}
    for gt in views:
        pred = predict_view(field_, gt.camera)
        preds.append(pred)
        floor = np.broadcast_to(background_colour(gt), gt.rgb.shape)
        valid = camera_valid(gt.camera).reshape(gt.rgb.shape[:2])
        fg = dilate(gt.foreground, foreground_radius(gt.rgb.shape[1])) & valid
        rgb = np.where(valid[..., None], pred["rgb"], gt.rgb)
        scores["psnr"].append(psnr(pred["rgb"], gt.rgb) if valid.all() else masked_psnr(pred["rgb"], gt.rgb, valid))
        scores["psnr_fg"].append(masked_psnr(pred["rgb"], gt.rgb, fg))
        scores["ssim"].append(ssim(rgb, gt.rgb) if min(gt.rgb.shape[:2]) >= 11 else float("nan"))
        scores["distance_error"].append(distance_error(pred["distance"], gt.distance, gt.mask & valid))
        scores["floor_psnr"].append(psnr(floor, gt.rgb) if valid.all() else masked_psnr(floor, gt.rgb, valid))
        scores["floor_psnr_fg"].append(masked_psnr(floor, gt.rgb, fg))
    return {"psnr": float(np.mean(scores.pop("psnr"))), **{k: _mean_or_none(v) for k, v in scores.items()}}, preds


def _mean_or_none(values) -> float | None:
    """Mean of the values that are not NaN, or None when every value is NaN."""
    return None if np.isnan(values).all() else float(np.nanmean(values))


def floor_comparison(metrics: dict) -> tuple[str, float, float] | None:
    """What an evaluation's held-out scores compare with the trivial prediction on: ``("foreground
    PSNR", psnr_fg, floor_psnr_fg)`` where both are finite, else ``("PSNR", psnr, floor_psnr)``; None
    for a record from before floors, or a floor that is not finite (a view that is all background)."""
    for what, key in (("foreground PSNR", "psnr_fg"), ("PSNR", "psnr")):
        score, floor = metrics.get(key), metrics.get(f"floor_{key}")
        if score is not None and floor is not None and np.isfinite(score) and np.isfinite(floor):
            return what, float(score), float(floor)
    return None


def at_floor(metrics: dict) -> bool:
    """Whether an evaluation's field scores less than FLOOR_MARGIN_DB above the background colour alone."""
    found = floor_comparison(metrics)
    return found is not None and found[1] < found[2] + FLOOR_MARGIN_DB


def fit_too_short(metrics: dict) -> bool:
    """Whether an evaluation's field fits its own training views less than FIT_GAIN_DB better
    than at its first steps (records from before ``fit_start_psnr`` cannot tell)."""
    fit, start = metrics.get("fit_psnr"), metrics.get("fit_start_psnr")
    return fit is not None and start is not None and fit < start + FIT_GAIN_DB


def weak_evaluation(metrics: dict) -> bool:
    """Whether an evaluation's held-out scores say too little to compare views by
    (:func:`at_floor` or :func:`fit_too_short`)."""
    return at_floor(metrics) or fit_too_short(metrics)


def scores_line(metrics: dict) -> str:
    """An evaluation's held-out scores in words: PSNR, foreground PSNR, SSIM and distance error."""
    def figure(key, text):
        return "n/a" if metrics.get(key) is None else text.format(metrics[key])

    return (f"PSNR {metrics['psnr']:.2f} dB, foreground PSNR {figure('psnr_fg', '{:.2f} dB')}, "
            f"SSIM {figure('ssim', '{:.3f}')}, distance error {figure('distance_error', '{:.2f}%')}")


def evaluation_note(metrics: dict, eval_steps: int, default_steps: int) -> str | None:
    """The note a run logs on an evaluation whose field, trained ``eval_steps`` steps (the run's default:
    ``default_steps``), is not clearly above the background colour alone (:func:`at_floor`), or barely
    fit its own views (:func:`fit_too_short`); None for one that did neither."""
    advice = f"raise eval_steps (RunConfig.eval_steps, plan --eval-steps; default {default_steps})"
    short, fit = fit_too_short(metrics), metrics.get("fit_psnr")
    if at_floor(metrics):
        what, score, floor = floor_comparison(metrics)
        note = (f"note: at {metrics['views']} views the evaluation field's held-out {what} is {score:.1f} dB, not "
                f"{FLOOR_MARGIN_DB:g} dB above the background colour alone's ({floor:.1f} dB): its scores cannot "
                "tell views apart")
        if short:
            return f"{note}; {advice}"
        # A field that fits its own views has trained: its views are what it lacks.
        return note + ("" if fit is None else f"; it fits its own training views to {fit:.1f} dB, so they show "
                                              "too little of what the held-out views see")
    if short:
        return (f"note: the evaluation field fits its own {metrics['views']} training views to only "
                f"{fit:.1f} dB after {eval_steps} steps (from {metrics['fit_start_psnr']:.1f} dB "
                f"at first): its held-out scores say more about the training than about the views; {advice}")
    return None
