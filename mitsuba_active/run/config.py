"""A run's settings: :class:`RunConfig`, checked, and the fields and view source it describes."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from ..checks import choice_named, is_number, is_whole, unknown_choice
from ..datasets import open_source
from ..errors import UserError
from ..field import FieldConfig
from ..field.config import DEFAULT_PRESET, FIELD_PRESETS, MAX_MEMBERS, MAX_STEPS
from ..groundtruth import MAX_SPP
from ..planners.base import planner_folder, resolve_reference
from ..rigs import RIG_KINDS
from ..training import MAX_CANDIDATE_RAYS, PLANNER_INIT_SCALE, has_distances
from ..travel import TRAVEL_SETTINGS, travel_problems

@dataclass
class RunConfig:
    """Settings of one planning run (recorded in run.json).

    Attributes:
        scene: scene XML, transforms.json or dataset folder.
        planner: registered planner name, or a planner of the user's own as
            ``FILE.py:CLASS`` (the file's path is made absolute) or ``MODULE:CLASS``;
            ``planner_options`` its settings.
        budget: views captured in total (initial views included).
        initial_views: random views captured before planning starts.
        ensemble: number of fields K in the planner's ensemble.
        batch: views chosen per round.
        seed: seeds initial views, planner randomness and all fields.
        resolution, candidates, heldout, rig, fov, spp: the environment (scene sources).
        downscale: image downscale factor (dataset sources; None: automatic).
        rays_per_candidate: the sparse rays a planner scores per candidate.
        initial_steps, steps_per_view: ensemble training (steps per captured view, warm start).
        eval_views: view counts at which the evaluation field is trained and scored.
        eval_steps: training steps of each evaluation field.
        distance_weight: weight of the distance loss (0: photometric only, as in the seed paper).
        field_preset: the field's named settings (:data:`~mitsuba_active.field.config.FIELD_PRESETS`).
        field: overrides of :class:`~mitsuba_active.field.FieldConfig` options
            (e.g. ``{"n_samples": 32}``), for the planner's ensemble and the evaluation field alike.
        embodiment, travel_budget, time_budget, speed, capture_time, cost_weight: how the camera
            moves and what its travel may cost (:data:`~mitsuba_active.travel.TRAVEL_SETTINGS`).
        turning_radius: a ground base's least turning radius, scene units (0: holonomic; above
            0 it drives forward along Dubins paths, facing where its camera looks).
        along_the_way: spacing (scene units) of the views a moving camera also captures along
            each route, looking at the scene's centre (None: none).
        candidates_mode: ``pool`` (the rig's fixed candidates) or ``continuous`` (a fresh
            sample of reachable poses on the rig each round, refined around the best).
        nearest: continuous poses' least distance from the rig's centre, as a share of the rig's.
    """

    scene: str = ""
    planner: str = "rfe"
    planner_options: dict = field(default_factory=dict)
    budget: int = 20
    initial_views: int = 2
    ensemble: int = 2
    batch: int = 1
    seed: int = 0
    resolution: int = 64
    candidates: int = 100
    heldout: int = 20
    rig: str = "auto"
    fov: float | None = None
    spp: int = 64
    downscale: int | None = None
    rays_per_candidate: int = 256
    initial_steps: int = 200
    steps_per_view: int = 50
    eval_views: list = field(default_factory=lambda: [5, 10, 15, 20])
    eval_steps: int = 1500
    distance_weight: float = 0.0
    field_preset: str = DEFAULT_PRESET
    field: dict = field(default_factory=dict)
    embodiment: str = TRAVEL_SETTINGS["embodiment"][0]
    travel_budget: float | None = TRAVEL_SETTINGS["travel_budget"][0]
    time_budget: float | None = TRAVEL_SETTINGS["time_budget"][0]
    speed: float = TRAVEL_SETTINGS["speed"][0]
    turning_radius: float = TRAVEL_SETTINGS["turning_radius"][0]
    capture_time: float = TRAVEL_SETTINGS["capture_time"][0]
    cost_weight: float = TRAVEL_SETTINGS["cost_weight"][0]
    along_the_way: float | None = TRAVEL_SETTINGS["along_the_way"][0]
    candidates_mode: str = TRAVEL_SETTINGS["candidates_mode"][0]
    nearest: float = TRAVEL_SETTINGS["nearest"][0]

    def __post_init__(self):
        if isinstance(self.scene, os.PathLike):  # run.json holds it as text
            self.scene = os.fspath(self.scene)
        if isinstance(self.planner, str):  # a planner file is the same file from any folder
            self.planner = resolve_reference(self.planner)
        # Names of choices in any case, as they are spelt in run.json and folder names.
        self.rig, self.field_preset = choice_named(self.rig, RIG_KINDS), choice_named(self.field_preset, FIELD_PRESETS)
        # numpy scalars (a seed from np.arange) as Python numbers: gymnasium takes Python ints only.
        for name in self.WHOLE + self.NUMBERS + ("downscale",):
            value = getattr(self, name)
            if isinstance(value, np.generic) and (is_whole(value) or is_number(value)):
                setattr(self, name, value.item())
        if isinstance(self.eval_views, (list, tuple)):
            self.eval_views = [v.item() if isinstance(v, np.generic) and is_whole(v) else v for v in self.eval_views]

    #: Settings that are whole numbers, and those that are numbers (None: unset).
    WHOLE = ("budget", "initial_views", "ensemble", "batch", "seed", "resolution", "candidates", "heldout",
             "spp", "rays_per_candidate", "initial_steps", "steps_per_view", "eval_steps")
    NUMBERS = ("distance_weight", "fov")

    def _check_types(self) -> None:
        for name in self.WHOLE + ("downscale",):
            value = getattr(self, name)
            if not is_whole(value) and not (name == "downscale" and value is None):
                raise UserError(f"{name} must be a whole number, got {value!r}")
        for name in self.NUMBERS:
            value = getattr(self, name)
            if not is_number(value) and not (name == "fov" and value is None):
                raise UserError(f"{name} must be a number, got {value!r}")
        if not isinstance(self.eval_views, (list, tuple)) or not all(is_whole(v) and v > 0 for v in self.eval_views):
            raise UserError(f"eval_views must be a list of positive view counts, got {self.eval_views!r}")
        for name in ("planner_options", "field"):
            if not isinstance(getattr(self, name), dict):
                raise UserError(f"{name} must be a table of options, got {getattr(self, name)!r}")
        if not isinstance(self.rig, str):
            raise UserError(f"rig must be a name, got {self.rig!r}")
        if not isinstance(self.field_preset, str) or self.field_preset not in FIELD_PRESETS:
            raise UserError(unknown_choice("field preset", self.field_preset, FIELD_PRESETS))

    def validate(self, n_candidates: int | None = None) -> None:
        """UserError unless the settings make a run (types, ranges, the budget against ``n_candidates``)."""
        self._check_types()
        checks = [
            (0 <= self.seed < 2**31, f"the seed must be in [0, 2^31), got {self.seed}"),
            (self.budget > 0, f"the view budget must be positive, got {self.budget}"),
            (0 <= self.initial_views <= self.budget,
             f"initial views ({self.initial_views}) must be between 0 and the budget ({self.budget})"),
            (1 <= self.ensemble <= MAX_MEMBERS,
             f"the ensemble needs between 1 and {MAX_MEMBERS} members, got {self.ensemble}"),
            (self.batch >= 1, f"the batch must be at least 1, got {self.batch}"),
            (self.resolution > 0, f"image resolution must be positive, got {self.resolution}"),
            (0 < self.spp <= MAX_SPP, f"samples per pixel must be in [1, {MAX_SPP}], got {self.spp}"),
            (self.fov is None or 0 < self.fov < 180, f"field of view must be in (0, 180) degrees, got {self.fov}"),
            (self.rig in RIG_KINDS, unknown_choice("rig", self.rig, RIG_KINDS)),
            (self.candidates >= 1, f"at least one candidate view is needed, got {self.candidates}"),
            (self.heldout >= 1, f"at least one held-out view is needed to evaluate on, got {self.heldout}"),
            (math.isfinite(self.distance_weight) and self.distance_weight >= 0,
             f"the distance weight must be a finite number >= 0, got {self.distance_weight}"),
            (0 < self.rays_per_candidate <= MAX_CANDIDATE_RAYS,
             f"rays per candidate must be in [1, {MAX_CANDIDATE_RAYS}], got {self.rays_per_candidate}"),
            (min(self.initial_steps, self.steps_per_view) >= 0,
             f"training steps cannot be negative, got initial_steps={self.initial_steps}, "
             f"steps_per_view={self.steps_per_view}"),
            # The longest single training: the planner's ensemble's first, on up to `budget` views.
            (max(self.initial_steps + self.steps_per_view * self.budget, self.eval_steps) <= MAX_STEPS,
             f"a training may take at most {MAX_STEPS:,} steps, got initial_steps + steps_per_view x budget = "
             f"{self.initial_steps + self.steps_per_view * self.budget:,} and eval_steps = {self.eval_steps:,}"),
            (self.eval_steps > 0, f"evaluation steps must be positive, got {self.eval_steps}"),
        ]
        if n_candidates is not None:
            checks.append((self.budget <= n_candidates, f"the view budget ({self.budget}) is larger than the number "
                                                        f"of candidate views ({n_candidates})"))
        for ok, message in checks:
            if not ok:
                raise UserError(message)
        problems = travel_problems(self)
        if problems:
            raise UserError(problems[0])

    def open_source(self, cache_dir=None):
        """The view source these settings describe: :func:`~mitsuba_active.datasets.open_source`
        of ``scene`` with the environment settings (``cache_dir``: see
        :class:`~mitsuba_active.groundtruth.GroundTruth`)."""
        if not self.scene:
            raise UserError("no scene given: set RunConfig.scene to a scene XML, a transforms.json or a dataset folder")
        return open_source(self.scene, rig=self.rig, n_candidates=self.candidates, n_heldout=self.heldout,
                           resolution=self.resolution, fov=self.fov, spp=self.spp, downscale=self.downscale,
                           cache_dir=cache_dir)

    def report_counts(self) -> list[int]:
        """View counts to evaluate: the requested ones within the budget, and the budget
        itself, less those below the initial views (and 0)."""
        counts = sorted({int(v) for v in self.eval_views if 0 < int(v) <= self.budget} | {self.budget})
        return [c for c in counts if c >= max(self.initial_views, 1)]


#: Distance-loss weight that ``plan`` suggests for rooms seen from inside.
#: Trained on colour alone, the sparse-view field fills a room with fog;
#: with the distance maps it finds the walls (Cornell box, ``docs/results.md``).
INTERIOR_DISTANCE_WEIGHT = 10.0


def field_config(cfg: RunConfig, planner: bool = True, width: int | None = None):
    """The :class:`~mitsuba_active.field.FieldConfig` of the planner's ensemble
    (``planner=True``) or of an evaluation field, for images ``width`` pixels
    across (None: ``cfg.resolution``); UserError on unknown options."""
    base = {"distance_weight": cfg.distance_weight,
            **FIELD_PRESETS[cfg.field_preset].config_options(width or cfg.resolution, planner)}
    if planner:
        base["init_scale"] = PLANNER_INIT_SCALE
    known = {f.name for f in fields(FieldConfig)}
    unknown = sorted(set(cfg.field) - known)
    if unknown:
        raise UserError(f"unknown field option {', '.join(unknown)}; see FieldConfig (docs/field.md) for "
                        f"the options: {', '.join(sorted(known))}")
    if "distance_weight" in cfg.field:  # two settings of one weight, and run.json would show the other
        raise UserError("set the distance loss's weight as the run setting distance_weight (--distance-weight), "
                        "not as the field option field.distance_weight")
    return FieldConfig(**{**base, **cfg.field})


def source_field_config(source, cfg: RunConfig, planner: bool = True):
    """:func:`field_config` for the source's images, with the options the source asks for
    (``source.field_options(config, planner=planner)``, where it has one) under those the run
    sets; also UserError when the source cannot train such a field."""
    config = field_config(cfg, planner, width=source.candidates[0].width)
    # What the scene needs (a capture's contraction, a room's settings), under the run's own field options.
    asks = getattr(source, "field_options", None)
    needs = {k: v for k, v in (asks(config, planner=planner) if asks else {}).items() if k not in cfg.field}
    config = type(config)(**{**config.to_dict(), **needs}) if needs else config
    if config.distance_weight > 0 and not has_distances(source):
        raise UserError(f"distance_weight (--distance-weight) needs distances, and {source.name} has no depth maps "
                        "(its frames give no depth_file_path or distance_file_path)")
    return config


def default_out_dir(scene_path, planner: str, seed: int) -> Path:
    """The run folder ``plan`` writes unless told: ``runs/SCENE-PLANNER-seedN``."""
    path = Path(scene_path)
    stem = path.stem if path.suffix else path.name
    if path.suffix == ".json":  # transforms.json / transforms_train.json: name the dataset folder
        stem = path.resolve().parent.name
    return Path("runs") / f"{stem}-{planner_folder(planner)}-seed{seed}"
