"""Rewards of the active-view environment: what a newly captured view is worth.

:class:`~mitsuba_active.env.ActiveViewEnv` takes one by name
(``reward="coverage"``, its settings as ``reward_options``) or as a
:class:`Reward` object. Each is a function of the views captured in the
episode so far (the initial views included), in the order they were
captured; its randomness comes from its own ``seed``, not the episode's.

``none``
    0; costs nothing.
``coverage``
    The fraction of the held-out views' surface points that the new view
    sees and no earlier view of the episode saw: unitless, in [0, 1], 0 for
    a view seen before; an episode's rewards sum to the fraction seen at its
    end less that of its initial views. Costs one projection of the points.
``uncertainty``
    The drop in an ensemble's colour variance over a fixed sample of the new
    view's pixel rays (as the rfe planner scores a candidate), from before to
    after the ensemble trains on the view (warm start, as a run's planner ensemble):
    squared sRGB units, in [-0.25, 0.25], positive on average. Costs
    ``steps_per_view`` training steps of ``members`` fields.
``psnr``
    The gain in held-out PSNR, in dB, of a fresh field trained on the views
    so far over that of the views before (before any view: an untrained
    field's); unbounded. Costs ``steps``
    training steps from scratch and a render of every held-out view.

``psnr`` is the evaluation protocol's score (:func:`mitsuba_active.run.evaluate`),
so it is the expensive one: every step trains a field from scratch. ``coverage``
and ``psnr`` read the held-out views' ground truth; ``coverage`` needs their
distances (a dataset needs depth maps).
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from dataclasses import fields

import numpy as np

from .cameras import camera_pixels, camera_rays
from .checks import is_whole
from .errors import UserError
from .field import Ensemble, FieldConfig
from .field.config import DEFAULT_PRESET, FIELD_PRESETS, MAX_MEMBERS, MAX_STEPS
from .groundtruth import View
from .training import (MAX_CANDIDATE_RAYS, PLANNER_INIT_SCALE, acquisition_steps, has_distances, score_views,
                       sparse_candidate_rays, train_on)

#: Most held-out surface points that ``coverage`` counts (a fixed sample of them beyond).
MAX_SURFACE_POINTS = 1 << 16
#: A point is seen where the view's distance at its pixel is within this many
#: pixel footprints of its own: a neighbouring pixel centre on a slanted surface
#: lies that far off, an occluder in front lies farther.
VISIBILITY_PIXELS = 2.0


class Reward:
    """What a captured view is worth. :meth:`bind` it to a view source once; per episode,
    :meth:`start` with the initial views, then :meth:`gain` after each capture."""

    name = "none"
    #: Whether the same views give bit-identical rewards. A reward that trains a field
    #: is equal only to ~1e-6 relative: Dr.Jit sums the gradients in parallel, in no fixed order.
    deterministic = True

    def bind(self, source) -> None:
        """Check that the reward can be computed on ``source`` (UserError if not) and keep it."""
        self.source = source

    def start(self, views: list[View]) -> None:
        """A new episode begins with ``views`` captured (possibly none)."""

    def gain(self, views: list[View]) -> float:
        """The reward for ``views[-1]``, just captured after ``views[:-1]``."""
        return 0.0

    def options(self) -> dict:
        """The reward's settings."""
        return {}


class NoReward(Reward):
    """Always 0: the evaluation protocol, not the environment, measures quality."""

    name = "none"


class CoverageReward(Reward):
    """The newly seen fraction of the surface that the held-out views see.

    The surface is the points of the held-out views' pixels that hit geometry
    (at most :data:`MAX_SURFACE_POINTS`, a fixed sample); a view sees a point
    that projects into it and is not hidden, by its distance map, behind
    something nearer (see :data:`VISIBILITY_PIXELS`).

    Args:
        seed: seeds the sample of surface points where there are more than
            :data:`MAX_SURFACE_POINTS`.
    """

    name = "coverage"

    def __init__(self, seed: int = 0):
        self.seed = _whole("seed", seed, 0, 2**31 - 1)

    def options(self):
        return {"seed": self.seed}

    def bind(self, source):
        if not has_distances(source):
            raise UserError(f"the coverage reward needs distances, and {source.name} has no depth maps "
                            "(its frames give no depth_file_path or distance_file_path)")
        super().bind(source)
        self.points = None

    def start(self, views):
        if self.points is None:
            self.points = surface_points([self.source.heldout_view(i) for i in range(len(self.source.heldout))],
                                         MAX_SURFACE_POINTS, self.seed)
        self.seen = np.zeros(len(self.points), bool)
        for view in views:
            self.seen |= seen_points(view, self.points)

    def gain(self, views):
        new = seen_points(views[-1], self.points) & ~self.seen
        self.seen |= new
        return float(np.count_nonzero(new) / max(1, len(self.points)))


def surface_points(views: list[View], limit: int, seed: int) -> np.ndarray:
    """The points (N, 3) float64, in scene units, where the views' pixel-centre rays hit,
    at most ``limit`` of them (a uniform sample without replacement beyond)."""
    parts = []
    for view in views:
        o, d = camera_rays(view.camera)
        hit = view.mask.reshape(-1).astype(bool)
        parts.append(o[hit].astype(np.float64) + d[hit].astype(np.float64) * view.distance.reshape(-1, 1)[hit])
    points = np.concatenate(parts) if parts else np.zeros((0, 3))
    if len(points) > limit:
        points = points[np.sort(np.random.default_rng(seed).choice(len(points), limit, replace=False))]
    return points


def seen_points(view: View, points: np.ndarray) -> np.ndarray:
    """(N,) bool: which of the (N, 3) ``points`` the view sees, by its camera and distance map."""
    cam = view.camera
    col, row, inside = camera_pixels(cam, points)
    r, c = row[inside].astype(int), col[inside].astype(int)
    dist = np.linalg.norm(points[inside] - cam.position, axis=1)
    footprint = dist / cam.intrinsics()[0, 0]  # one pixel's width at the point's distance
    visible = view.mask[r, c].astype(bool) & (np.abs(view.distance[r, c] - dist) <= VISIBILITY_PIXELS * footprint)
    seen = np.zeros(len(points), bool)
    seen[np.flatnonzero(inside)[visible]] = True
    return seen


class UncertaintyReward(Reward):
    """The drop in an ensemble's mean colour variance over the new view's sparse rays.

    The ensemble is a run's planner ensemble (the preset's planner field,
    :data:`~mitsuba_active.training.PLANNER_INIT_SCALE`): made afresh at each
    episode's start, trained ``initial_steps + steps_per_view`` per view on
    the initial views, then on all views so far for ``steps_per_view`` steps
    after each capture (``initial_steps`` more at the first). The variance is
    across members, of each colour channel, averaged over the view's rays;
    the reward is its value before the ensemble trains on the view (the rfe
    planner's score of the view, as a mean) less its value after.

    The new view's rays, not all candidates': over all of them the variance
    rises while the first views give the members density, and so colours to
    disagree on, where no view constrains them.

    Args:
        members: fields in the ensemble (at least 2).
        initial_steps, steps_per_view: its training, as a run's.
        rays_per_candidate: sparse rays of the new view (a fixed sample of its pixels).
        field_preset: :data:`~mitsuba_active.field.config.FIELD_PRESETS` name.
        field: :class:`~mitsuba_active.field.FieldConfig` options over the preset's.
        seed: seeds the members and the rays.
    """

    name = "uncertainty"
    deterministic = False

    def __init__(self, members: int = 2, initial_steps: int = 200, steps_per_view: int = 50,
                 rays_per_candidate: int = 256, field_preset: str = DEFAULT_PRESET, field: dict | None = None,
                 seed: int = 0):
        self.members = _whole("members", members, 2, MAX_MEMBERS)
        self.initial_steps = _whole("initial_steps", initial_steps, 0, MAX_STEPS)
        self.steps_per_view = _whole("steps_per_view", steps_per_view, 0, MAX_STEPS)
        self.rays_per_candidate = _whole("rays_per_candidate", rays_per_candidate, 1, MAX_CANDIDATE_RAYS)
        self.field_preset, self.field = _field_options(field_preset, field)
        self.seed = _whole("seed", seed, 0, 2**31 - 2)

    def options(self):
        return {"members": self.members, "initial_steps": self.initial_steps, "steps_per_view": self.steps_per_view,
                "rays_per_candidate": self.rays_per_candidate, "field_preset": self.field_preset,
                "field": dict(self.field), "seed": self.seed}

    def bind(self, source):
        super().bind(source)
        self.config = FieldConfig.preset(self.field_preset, source.candidates[0].width, planner=True,
                                         **{"init_scale": PLANNER_INIT_SCALE, **self.field})

    def start(self, views):
        self.ensemble = Ensemble(self.source.bbox_min, self.source.bbox_max, n_members=self.members,
                                 config=self.config, seed=self.seed)
        if views:
            train_on(self.ensemble, views, acquisition_steps(0, len(views), self.initial_steps, self.steps_per_view))

    def gain(self, views):
        origins, directions = sparse_candidate_rays([views[-1].camera], self.rays_per_candidate, self.seed + 1)
        rays = origins[0], directions[0]
        before = self._variance(rays)
        train_on(self.ensemble, views, acquisition_steps(len(views) - 1, 1, self.initial_steps, self.steps_per_view))
        return before - self._variance(rays)

    def _variance(self, rays) -> float:
        return float(np.mean(self.ensemble.predict(*rays)["rgb_var"]))


class PSNRReward(Reward):
    """The gain in held-out PSNR (dB) of a fresh field trained on the views so far.

    Expensive: every step trains a field from scratch for ``steps`` steps and
    renders every held-out view, as the evaluation protocol does at each of
    its view counts. The field is the preset's evaluation field; before any
    view it is untrained.

    Args:
        steps: training steps of each field (the evaluation protocol's ``eval_steps``).
        field_preset: :data:`~mitsuba_active.field.config.FIELD_PRESETS` name.
        field: :class:`~mitsuba_active.field.FieldConfig` options over the preset's.
        seed: seeds the fields.
    """

    name = "psnr"
    deterministic = False

    def __init__(self, steps: int = 1500, field_preset: str = DEFAULT_PRESET, field: dict | None = None,
                 seed: int = 0):
        self.steps = _whole("steps", steps, 1, MAX_STEPS)
        self.field_preset, self.field = _field_options(field_preset, field)
        self.seed = _whole("seed", seed, 0, 2**31 - 1)

    def options(self):
        return {"steps": self.steps, "field_preset": self.field_preset, "field": dict(self.field), "seed": self.seed}

    def bind(self, source):
        super().bind(source)
        self.config = FieldConfig.preset(self.field_preset, source.candidates[0].width, **self.field)
        self.heldout = None

    def start(self, views):
        if self.heldout is None:
            self.heldout = [self.source.heldout_view(i) for i in range(len(self.source.heldout))]
        self.psnr = self._psnr(views)

    def gain(self, views):
        before, self.psnr = self.psnr, self._psnr(views)
        return self.psnr - before

    def _psnr(self, views: list[View]) -> float:
        field_ = Ensemble(self.source.bbox_min, self.source.bbox_max, n_members=1, config=self.config,
                          seed=self.seed)
        train_on(field_, views, self.steps if views else 0)
        return score_views(field_, self.heldout)[0]["psnr"]


#: The rewards by name.
REWARDS = {cls.name: cls for cls in (NoReward, CoverageReward, UncertaintyReward, PSNRReward)}


def make_reward(name, options: Mapping | None = None) -> Reward:
    """The reward ``name`` (:data:`REWARDS`) with its settings ``options``; UserError on unknown ones."""
    if not isinstance(name, str) or name not in REWARDS:
        raise UserError(f"unknown reward {name!r}; choose one of {', '.join(map(repr, REWARDS))}")
    if options is not None and not isinstance(options, Mapping):
        raise UserError(f"reward options must be a dict of settings, not {type(options).__name__}")
    cls = REWARDS[name]
    known = [p for p in inspect.signature(cls).parameters]
    unknown = sorted(set(options or {}) - set(known), key=str)
    if unknown:
        settings = f"its settings are {', '.join(known)}" if known else "it has no settings"
        raise UserError(f"unknown option {', '.join(map(repr, unknown))} of the {name} reward; {settings}")
    return cls(**(options or {}))


def _whole(name: str, value, low: int, high: int) -> int:
    if not is_whole(value) or not low <= value <= high:
        raise UserError(f"the reward's {name} must be a whole number in [{low}, {high}], got {value!r}")
    return int(value)


def _field_options(preset, field) -> tuple[str, dict]:
    """The preset's name and the FieldConfig options over it, checked by name (their values by FieldConfig)."""
    if not isinstance(preset, str) or preset not in FIELD_PRESETS:
        raise UserError(f"unknown field preset {preset!r}; choose one of {', '.join(FIELD_PRESETS)}")
    if field is not None and not isinstance(field, Mapping):
        raise UserError(f"the reward's field options must be a dict of FieldConfig options, got {field!r}")
    known = {f.name for f in fields(FieldConfig)}
    unknown = sorted(set(field or {}) - known, key=str)
    if unknown:
        raise UserError(f"unknown field option {', '.join(map(str, unknown))}; see FieldConfig (docs/field.md) for "
                        f"the options: {', '.join(sorted(known))}")
    return preset, dict(field or {})
