"""The acquisition loop and the evaluation protocol.

One run: start from ``initial_views`` random candidates, then repeatedly
let the planner choose ``batch`` views, capture them, and (for model-based
planners) continue training the ensemble on all views so far (warm start),
until ``budget`` views are captured.

Evaluation follows the seed paper: at each reported view count a *fresh*
field, with the same architecture, seed and steps for every planner, is
trained on the views chosen so far and scored on the held-out views (PSNR,
PSNR of the foreground, SSIM, and mean relative distance error on pixels that
hit geometry), beside the PSNRs of the background colour alone.

A run writes everything into one folder and keeps ``run.json`` current
after every round, so an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import re
import time
import warnings
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from .cameras import RIG_KINDS, snapped_up
from .checks import choice_named, is_number, is_whole, unknown_choice
from .embodiments import make_embodiment
from .env import ActiveViewEnv, SceneSource
from .errors import FolderError, FolderInUse, TrainingDiverged, UserError
from .field.config import DEFAULT_PRESET, FIELD_PRESETS, LEGACY_PRESET
from .groundtruth import MAX_SPP, View
from .imageio_utils import (atomic_write, colorize, folder_lock, new_entries, remove_new, srgb_to_linear, write_exr,
                            write_png)
from .metrics import DECIMALS, fixed
from .planners import PlanningState, make_planner
from .planners.base import (is_planner_file, planner_digest, planner_folder, planner_label, planner_rng,
                             resolve_reference, unseen)
from .training import (MAX_CANDIDATE_RAYS, PLANNER_INIT_SCALE, evaluation_note, has_distances, predict_view,
                       score_views, scores_line, sparse_candidate_rays, train_on)
from .travel import TRAVEL_SETTINGS, Journey, diameter_of, travel_problems
from .webpage import REPORT_FILE, write_run_page

RUN_FORMAT = 1


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
    capture_time: float = TRAVEL_SETTINGS["capture_time"][0]
    cost_weight: float = TRAVEL_SETTINGS["cost_weight"][0]

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
        from .field.config import MAX_MEMBERS, MAX_STEPS

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
        from .datasets import open_source

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


#: Name of the planner's ensemble file in a run folder, after the views it was trained on.
ENSEMBLE_FILE = re.compile(r"ensemble_\d{3,}\.npz")


def loss_psnr(losses) -> float:
    """PSNR (dB) of a mean photometric MSE."""
    return float(-10.0 * np.log10(max(float(np.mean(losses)), 1e-10)))


#: Distance-loss weight that ``plan`` suggests for rooms seen from inside.
#: Trained on colour alone, the sparse-view field fills a room with fog;
#: with the distance maps it finds the walls (Cornell box, ``docs/results.md``).
INTERIOR_DISTANCE_WEIGHT = 10.0


def config_differences(recorded, current: dict, compare_scene: bool = True) -> list[str]:
    """The settings in which a run record's config (a dict from run.json)
    differs from ``current`` (a config dict, compared as run.json would hold
    it), as ``"name: recorded -> current"`` lines.

    Scene paths compare as resolved paths, so that a relative and an absolute
    path to one scene match. Callers that check the scene's content hash pass
    ``compare_scene=False``: the same scene may then be named by any path (a
    folder run from elsewhere, or moved). Planner files compare by their
    :func:`~mitsuba_active.planners.planner_label`, for the same reason:
    callers compare their content (:func:`~mitsuba_active.planners.base.planner_digest`).
    """
    return [f"{k}: {old!r} -> {new!r}" for k, (old, new) in config_changes(recorded, current, compare_scene).items()]


def config_changes(recorded, current: dict, compare_scene: bool = True) -> dict:
    """:func:`config_differences` as ``{name: (recorded value, current value)}``."""
    if not isinstance(recorded, dict):
        return {"config": ("missing", "present")}
    current_planner = current.get("planner")

    def normal(config):
        config = json.loads(json.dumps(config, default=_json_default))  # tuples as lists, numpy as numbers
        if isinstance(config.get("eval_views"), list):  # the same counts in any order
            config["eval_views"] = sorted(set(config["eval_views"]))
        name = config.get("planner")
        if is_planner_file(name):
            config["planner"] = planner_label(name)
            if is_planner_file(current_planner) and config["planner"] == planner_label(current_planner):
                name = current_planner  # the file as it is now, not where the record found it
        # The fields a planner actually trains: none for even (any --ensemble
        # then is the same run), one for fisher.
        try:
            planner = make_planner(name, **dict(config.get("planner_options") or {}))
        except (UserError, TypeError, ValueError):  # not a record of this tool's planners
            planner = None
        if planner is not None:  # options as the planner resolves them: defaults given or not, alike
            resolved = {**dict(config.get("planner_options") or {}), **planner.options()}
            config["planner_options"] = json.loads(json.dumps(resolved, default=_json_default))
        if planner is not None and is_whole(config.get("ensemble")):
            config["ensemble"] = planner.ensemble_size(config["ensemble"]) if planner.needs_ensemble else None
        config.setdefault("field_preset", LEGACY_PRESET)  # a record from before presets
        for name, (default, _) in TRAVEL_SETTINGS.items():  # a record from before travel ran as teleport
            config.setdefault(name, default)
        scene = config.pop("scene", None)
        if compare_scene:
            config["scene"] = str(Path(scene).resolve()) if scene else scene
        return config

    old, new = normal(recorded), normal(current)
    keys = [k for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
    if "planner" in keys and None in (old.get("ensemble"), new.get("ensemble")) and "ensemble" in keys:
        keys.remove("ensemble")  # one of the planners trains no ensemble: the planner says it all
    if "planner" in keys and "planner_options" in keys:
        keys.remove("planner_options")  # each planner's own: the planner says it all
    return {k: (old.get(k), new.get(k)) for k in keys}


#: The parts of a run record and their types (those before the line are in every record;
#: the others came later, or come with a round).
RECORD_PARTS = {"config": dict, "candidates": list, "heldout": list, "captured": list, "metrics": list,
                "finished": bool,
                # ---
                "rounds": list, "versions": dict, "rng_state": dict, "planner_options": dict, "distances": bool,
                "bbox": list, "budget_changes": list, "resumed_with": list, "ensemble_file": str,
                "candidate_files": list, "heldout_files": list, "travel": list, "stopped": dict}
REQUIRED_PARTS = ("config", "candidates", "heldout", "captured", "metrics", "finished")


def read_resumable_record(path) -> dict:
    """:func:`read_record` of a run folder's record, for going on with the run:
    a damaged one's message says how to start over."""
    try:
        return read_record(path)
    except UserError as exc:
        raise UserError(f"{exc}; remove it to start over") from None


def read_record(path) -> dict:
    """The run record in ``path`` (run.json), its parts checked, so that a
    hand-edited or damaged record is refused in one line, not deep in a
    resume, a report or an export.

    Raises:
        UserError: "PATH is damaged (what is wrong)", or not a run record.
    """
    from .cameras import Camera

    path = Path(path)
    try:
        rec = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as exc:  # not JSON, not text, or nested past Python's stack
        raise UserError(f"{path} is damaged ({exc})") from None
    if not isinstance(rec, dict) or not set(REQUIRED_PARTS) <= set(rec):
        raise UserError(f"{path} is not a run record")
    if rec.get("format", RUN_FORMAT) != RUN_FORMAT:
        raise UserError(f"{path} is a run record of format {rec['format']!r}, which this version of mitsuba-active "
                        f"does not read (it reads format {RUN_FORMAT})")

    def damaged(why: str) -> UserError:
        return UserError(f"{path} is damaged ({why})")

    for key, kind in RECORD_PARTS.items():
        if key in rec and not (isinstance(rec[key], kind) or (key == "ensemble_file" and rec[key] is None)):
            raise damaged(f"its {key} is {type(rec[key]).__name__}, not {kind.__name__}")
    for key in ("wall_seconds", "planning_seconds"):
        if key in rec and not (is_number(rec[key], finite=True) and rec[key] >= 0):
            raise damaged(f"its {key} is {rec[key]!r}, not a number of seconds")
    for key in ("candidates", "heldout"):
        try:
            for cam in rec[key]:
                Camera.from_dict(cam)
        except UserError as exc:
            raise damaged(f"one of its {key}: {exc}") from None
    for key, cams in (("candidate_files", "candidates"), ("heldout_files", "heldout")):
        files = rec.get(key)
        if files is not None and not (len(files) == len(rec[cams]) and all(isinstance(f, str) for f in files)):
            raise damaged(f"its {key} are not the file names of its {len(rec[cams])} {cams}")
    n = len(rec["candidates"])
    if not all(is_whole(i) and 0 <= i < n for i in rec["captured"]):
        raise damaged(f"its captured views are not indices of its {n} candidates")
    # Its views on disk are the captured ones in order: a list edited by hand would pair them with other poses.
    captured, budget = rec["captured"], rec["config"].get("budget")
    if rec["finished"] and is_whole(budget) and len(captured) != budget and not rec.get("stopped"):
        raise damaged(f"it is finished with {len(captured)} captured views, but its budget is {budget}")
    for r in rec.get("rounds", ()):
        views, picks = (r.get("views"), r.get("picks")) if isinstance(r, dict) else (None, None)
        if not (isinstance(picks, list) and is_whole(views) and len(picks) <= views <= len(captured)
                and captured[views - len(picks):views] == picks):
            raise damaged("its rounds did not pick the views it lists as captured")
    for m in rec["metrics"]:
        if not (isinstance(m, dict) and is_whole(m.get("views")) and is_number(m.get("psnr"))
                and all(m.get(k) is None or is_number(m[k])
                        for k in ("psnr_fg", "ssim", "distance_error", "floor_psnr", "floor_psnr_fg", "fit_psnr",
                                  "fit_start_psnr"))):
            raise damaged("an entry of its metrics is not the scores at a view count")
    counts = [m["views"] for m in rec["metrics"]]
    if counts != sorted(set(counts)) or not all(1 <= v <= len(captured) for v in counts):
        raise damaged(f"its metrics are at view counts {counts}, not once each at counts of its "
                      f"{len(captured)} captured views")
    if not all(isinstance(v, str) for v in rec.get("versions", {}).values()):
        raise damaged("its versions are not names of versions")
    ens_file = rec.get("ensemble_file")
    if ens_file is not None and not ENSEMBLE_FILE.fullmatch(ens_file):  # the run removes it when replaced
        raise damaged(f"its ensemble_file {ens_file!r} is not one of the run's ensemble_NNN.npz files")
    travel = rec.get("travel")
    # At least one entry per captured view: a run notes its travel before it lists the capture.
    if travel is not None and not (len(travel) >= len(captured) and all(
            isinstance(t, dict) and is_number(t.get("distance")) and is_number(t.get("time")) for t in travel)):
        raise damaged("its travel is not the distance and time so far at each captured view")
    bbox = rec.get("bbox")
    if bbox is not None and not (np.shape(bbox) == (2, 3) and all(is_number(v, finite=True)
                                                                   for corner in bbox for v in corner)):
        raise damaged(f"its bbox is {bbox!r}, not two corners of three numbers")
    return rec


@contextlib.contextmanager
def undone_unless_resumable(out: Path):
    """Run the block that starts (or resumes) the run in folder ``out``; should
    it fail before the run has a record to resume from (run.json), undo what it
    added: nothing half-made is left behind (a folder that was there keeps what
    it held). A folder another run is writing (FolderInUse) is left alone."""
    new = new_entries(out)
    try:
        yield
    except FolderInUse:  # what is in the folder is the other run's
        raise
    except BaseException:
        if not (out / "run.json").is_file():
            remove_new(out, *new)
        raise


def other_settings(folder, changed: list[str], advice: str) -> FolderError:
    """The error refusing ``folder``, whose run has other settings (``changed``,
    from :func:`config_differences`; the first three are named)."""
    more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
    return FolderError(folder, f"holds a run with other settings ({'; '.join(changed[:3])}{more}); {advice}")


def conflicting_settings(rec: dict, current: dict, compare_scene: bool = True) -> list[str]:
    """The settings in which a run record (a dict from run.json) differs from
    ``current`` (:func:`config_differences`), less a budget the run can go on
    to: one at least as large as the views it has captured. A finished run
    thus takes a larger budget (it is extended), an unfinished one any budget
    it has not passed."""
    changes = config_changes(rec.get("config"), current, compare_scene)
    captured, budget = rec.get("captured"), current.get("budget")
    lines = []
    for k, (old, new) in changes.items():
        line = f"{k}: {old!r} -> {new!r}"
        if k == "budget" and isinstance(captured, list) and is_whole(budget):
            if budget >= len(captured):
                continue
            line += f": fewer than the {len(captured)} views it has captured"
        lines.append(line)
    return lines


def ends_short_of_a_batch(captured: int, initial_views: int, batch: int) -> bool:
    """Whether a run that has ``captured`` views ended with a round of fewer than
    ``batch`` views (its budget cut the round short): taken on to a larger budget,
    its rounds then differ from those of a run made with that budget from the start."""
    return bool((captured - min(initial_views, captured)) % batch)


def other_planner_code(rec: dict, digest) -> bool:
    """Whether a run record was made with other code of its planner (``digest``:
    the code's now, see :func:`~mitsuba_active.planners.base.planner_digest`)
    *and* that planner chose views in it. A run that stopped before its planner
    chose a view (a planner being fixed) holds nothing of its work: it starts over."""
    return rec.get("planner_digest") != digest and bool(rec.get("rounds"))


def same_config(recorded, current: dict, compare_scene: bool = True) -> bool:
    """Whether a run record's config has the settings of ``current`` (see :func:`config_differences`)."""
    return not config_differences(recorded, current, compare_scene)


def field_config(cfg: RunConfig, planner: bool = True, width: int | None = None):
    """The :class:`~mitsuba_active.field.FieldConfig` of the planner's ensemble
    (``planner=True``) or of an evaluation field, for images ``width`` pixels
    across (None: ``cfg.resolution``); UserError on unknown options."""
    from .field import FieldConfig

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
    (``source.field_options(config)``, where it has one) under those the run sets; also UserError when
    the source cannot train such a field."""
    config = field_config(cfg, planner, width=source.candidates[0].width)
    # What the scene needs (a capture's contraction, a room's settings), under the run's own field options.
    needs = {k: v for k, v in getattr(source, "field_options", lambda _: {})(config).items() if k not in cfg.field}
    config = type(config)(**{**config.to_dict(), **needs}) if needs else config
    if config.distance_weight > 0 and not has_distances(source):
        raise UserError(f"distance_weight (--distance-weight) needs distances, and {source.name} has no depth maps "
                        "(its frames give no depth_file_path or distance_file_path)")
    return config


def make_ensemble(source, cfg: RunConfig, n_members: int, seed: int, planner: bool = True, make_field=None):
    """The planner's ensemble (``planner=True``) or an evaluation field, configured from ``cfg``.

    ``make_field``: the planner's :meth:`~mitsuba_active.planners.Planner.make_field`
    (the field it scores with), else an :class:`~mitsuba_active.field.Ensemble`.
    """
    from .field import Ensemble

    config = source_field_config(source, cfg, planner)
    make_field = make_field or Ensemble
    return make_field(source.bbox_min, source.bbox_max, n_members=n_members, config=config, seed=seed)


def evaluate(source, views: list[View], cfg: RunConfig, progress: bool = False) -> tuple[dict, list[dict]]:
    """Train a fresh evaluation field on ``views``; score it on every held-out view.

    Returns the metrics (means over held-out views, see
    :func:`~.training.score_views`; ``fit_psnr`` and ``fit_start_psnr``: the
    field's PSNR on its own training rays over the last and the first tenth of
    its training steps) and the per-view predictions.
    """
    t0 = time.perf_counter()
    field_ = make_ensemble(source, cfg, 1, seed=cfg.seed + 7919, planner=False)
    losses = train_on(field_, views, cfg.eval_steps, progress)
    # How well the field fits its own training views (the last tenth of its steps), and fitted them at first.
    tenth = max(1, len(losses) // 10)
    fit_psnr, start_psnr = loss_psnr(losses[-tenth:]), loss_psnr(losses[:tenth])
    scores, preds = score_views(field_, (source.heldout_view(i) for i in range(len(source.heldout))))
    metrics = {"views": len(views), **scores, "fit_psnr": fit_psnr, "fit_start_psnr": start_psnr,
               "eval_seconds": round(time.perf_counter() - t0, 3)}
    return metrics, preds


# ---------------------------------------------------------------------------
# The run
# ---------------------------------------------------------------------------

def source_differences(source, cfg: RunConfig) -> list[str]:
    """Environment settings of ``cfg`` that a scene source was not made with,
    as ``"name=value (the source's: value)"``: the scene, image width, view
    counts and samples per pixel. Not ``rig`` and ``fov``, so that a source
    with cameras of the caller's own can run (run.json records the cameras
    themselves). A dataset opened by ``DatasetSource.from_path`` must have the
    frames and image size that ``cfg.open_source()`` gives; one built from
    frames of the caller's own is not checked."""
    from .datasets import DatasetSource
    from .env import SceneSource

    if isinstance(source, DatasetSource):
        return _dataset_differences(source, cfg) if source.content_hash is not None else []
    if not isinstance(source, SceneSource):
        return []
    have = {"resolution": source.candidates[0].width, "heldout": len(source.heldout),
            "spp": source.groundtruth.spp}
    if cfg.rig != "xml":  # the XML's own sensors are as many as there are
        have["candidates"] = len(source.candidates)
    unlike = [f"{name}={getattr(cfg, name)!r} (the source's: {value!r})"
              for name, value in have.items() if getattr(cfg, name) != value]
    scene = Path(source.scene.path)
    if source.scene.content_hash is None:  # built in Python: no file for run.json to name
        unlike.insert(0, f"scene={cfg.scene!r} (the source's: {str(source.scene.path)!r}, built in Python, "
                         "which no file records)")
    elif not cfg.scene or Path(cfg.scene).resolve() != scene.resolve():
        unlike.insert(0, f"scene={cfg.scene!r} (the source's: {str(scene)!r})")
    return unlike


def _dataset_differences(source, cfg: RunConfig) -> list[str]:
    """:func:`source_differences` of a dataset: against the one ``cfg`` opens."""
    ref = cfg.open_source()
    if getattr(ref, "content_hash", None) != source.content_hash:  # another dataset, or a scene
        return [f"scene={cfg.scene!r} (the source's: the dataset {source.name!r})"]
    unlike = []
    if (ref.candidates[0].width, ref.candidates[0].height) != (source.candidates[0].width,
                                                               source.candidates[0].height):
        unlike.append(f"downscale={cfg.downscale!r}, resolution={cfg.resolution!r}: images of "
                      f"{ref.candidates[0].width}x{ref.candidates[0].height} pixels (the source's: "
                      f"{source.candidates[0].width}x{source.candidates[0].height})")
    for name, mine, theirs in (("candidates", ref.candidates, source.candidates),
                               ("heldout", ref.heldout, source.heldout)):
        same = len(mine) == len(theirs)
        if not same or not np.allclose([c.to_world for c in mine], [c.to_world for c in theirs], atol=1e-6):
            unlike.append(f"{name}={getattr(cfg, name)!r}: {len(mine)} frames (the source's: {len(theirs)}"
                          f"{', other ones' if same else ''})")
    return unlike


class Run:
    """One planning run in a folder; ``Run(...).execute()`` runs or resumes it.

    ``log`` takes the run's messages; ``notes`` are lines it logs once it
    has written its first record, as its rounds start.
    """

    def __init__(self, source, cfg: RunConfig, out_dir, progress: bool = True, log=print, notes=()):
        cfg.validate(len(source.candidates))
        # run.json records cfg as how the run was made: it must describe the source.
        unlike = source_differences(source, cfg)
        if unlike:
            raise UserError(f"the run's settings do not describe its view source: {'; '.join(unlike)} "
                            "(make the source with RunConfig.open_source())")
        self.source, self.cfg, self.out = source, cfg, Path(out_dir)
        self.progress, self.log, self.notes = progress, log, tuple(notes)
        self.planner = make_planner(cfg.planner, **cfg.planner_options)
        self.planner_digest = planner_digest(cfg.planner)  # of the code just loaded
        self.planner.check_ensemble_size(cfg.ensemble)
        source_field_config(source, cfg)  # field options are checked before anything is written
        self.env = ActiveViewEnv(source, cfg.budget, allow_repeats=True)  # the random planner repeats views
        self.journey = Journey(make_embodiment(cfg.embodiment, getattr(source, "scene", None), cfg.speed), cfg,
                               [c.to_world[:3, 3] for c in source.candidates],
                               diameter_of(source.bbox_min, source.bbox_max))
        self.rng = planner_rng(cfg.seed)
        self.record = None
        self.ensemble = None
        self._warned_fit = False
        self._budget_was = None  # the budget of the run in the folder, where this one differs

    # -- persistence --------------------------------------------------------
    @property
    def record_path(self) -> Path:
        return self.out / "run.json"

    @property
    def versions(self) -> dict:
        """The versions this run is made with: the package's, Mitsuba's, Dr.Jit's and the variant."""
        import drjit as dr
        import mitsuba as mi

        from . import __version__

        return {"mitsuba_active": __version__, "mitsuba": mi.__version__, "drjit": dr.__version__,
                "variant": mi.variant()}

    def _config_dict(self) -> dict:
        return json.loads(json.dumps(asdict(self.cfg), default=_json_default))

    def _load_or_start(self) -> bool:
        """Load an unfinished run from the folder; True when resuming."""
        if self.record_path.is_file():
            rec = read_resumable_record(self.record_path)
            # Scenes and datasets are compared by content, not by path; a record
            # without a digest (a dataset's, from before datasets had one) by path.
            by_content = rec.get("content_hash") is not None and self._content_hash() is not None
            changed = conflicting_settings(rec, self._config_dict(), compare_scene=not by_content)
            if changed:
                raise other_settings(self.out, changed, "choose another run folder")
            if by_content and rec["content_hash"] != self._content_hash():
                raise FolderError(self.out, "holds a run of a scene or dataset that has changed since; choose "
                                            "another run folder")
            if (rec.get("candidates") != [c.to_dict() for c in self.source.candidates]
                    or rec.get("heldout") != [c.to_dict() for c in self.source.heldout]):
                made_with = rec.get("versions", {}).get("mitsuba_active")
                now = self.versions["mitsuba_active"]
                why = (f" (it was made with mitsuba-active {made_with}, whose rigs place cameras otherwise than "
                       f"{now}'s)" if made_with not in (None, now) else "")
                raise FolderError(self.out, f"holds a run whose candidate or held-out cameras are not the view "
                                            f"source's{why}; choose another run folder")
            captured = rec["captured"]
            if other_planner_code(rec, self.planner_digest):
                raise FolderError(self.out, f"holds a run made with another version of the planner's code "
                                            f"({planner_label(self.cfg.planner)}); choose another run folder, "
                                            "or remove this one")
            if rec.get("planner_digest") != self.planner_digest:
                self.log(f"note: the planner's code changed before it chose a view: {self.out} starts over")
                return self._start()
            budget = rec["config"].get("budget")
            if budget != self.cfg.budget:  # the run goes on to (or ends at) another budget
                self._budget_was = budget
                rec.setdefault("budget_changes", []).append(
                    {"from": budget, "to": self.cfg.budget, "views": len(captured)})
                rec["config"]["budget"] = self.cfg.budget
                rec["finished"] = False  # a finished run only takes a larger budget
            now = self.versions
            started = rec.get("versions", now)  # records from before versions were kept: as now
            if started != now and not rec["finished"]:
                differ = [k for k in {**started, **now} if started.get(k) != now.get(k)]
                warnings.warn(f"{self.out} was started with " + ", ".join(f"{k} {started.get(k)}" for k in differ)
                              + "; it goes on with " + ", ".join(f"{k} {now.get(k)}" for k in differ),
                              stacklevel=2)
                rec.setdefault("resumed_with", []).append(now)
            try:  # the planner's random stream goes on where it stopped
                self.rng.bit_generator.state = rec["rng_state"]
            except (KeyError, TypeError, ValueError, OverflowError):
                raise UserError(f"{self.record_path} is damaged (its rng_state is not the state of the "
                                f"planner's random stream); remove it to start over") from None
            self.record = rec
            return True
        return self._start()

    def _start(self) -> bool:
        """A new record (False: not resuming)."""
        self.record = {"format": RUN_FORMAT, "versions": self.versions, "config": self._config_dict(),
                       "planner_options": self.planner.options(), "planner_digest": self.planner_digest,
                       "scene": self.source.name,
                       "bbox": [np.asarray(self.source.bbox_min, float).tolist(),
                                np.asarray(self.source.bbox_max, float).tolist()],
                       "candidates": [c.to_dict() for c in self.source.candidates],
                       "heldout": [c.to_dict() for c in self.source.heldout],
                       **self._frame_files(),
                       "content_hash": self._content_hash(),
                       "distances": has_distances(self.source),
                       "captured": [], "rounds": [], "metrics": [], "finished": False}
        return False

    def _frame_files(self) -> dict:
        """A dataset's image files of the candidates and held-out views (which frame each is), else nothing."""
        if getattr(self.source, "candidate_files", None) is None:
            return {}
        return {"candidate_files": list(self.source.candidate_files), "heldout_files": list(self.source.heldout_files)}

    def _exr_channels(self, view: View) -> dict:
        """A view's EXR channels: linear RGB, and its distances in Z when the
        source has any (no Z of zeros that would read as "nothing hit")."""
        channels = {"RGB": srgb_to_linear(view.rgb)}
        if has_distances(self.source):
            channels["Z"] = view.distance
        return channels

    def _content_hash(self):
        """The scene's (or the dataset's) content digest: a run folder is
        matched to it, not to the path the source was named by."""
        scene = getattr(self.source, "scene", None)
        return getattr(scene if scene is not None else self.source, "content_hash", None)

    def _add_planning_time(self, seconds: float) -> None:
        """Count time spent planning: choosing views and training the planner's ensemble
        (not rendering ground truth, evaluating or writing files)."""
        self.record["planning_seconds"] = round(self.record.get("planning_seconds", 0.0) + seconds, 4)

    def _save_record(self) -> None:
        now = time.perf_counter()
        self.record["wall_seconds"] = round(self.record.get("wall_seconds", 0.0) + now - self._clock, 3)
        self._clock = now
        self.record["rng_state"] = self.rng.bit_generator.state
        with atomic_write(self.record_path) as tmp:
            tmp.write_text(json.dumps(self.record, indent=1, default=_json_default))

    def _save_round(self) -> None:
        """Save the ensemble (if any), then run.json pointing to it, so the two always match."""
        previous = self.record.get("ensemble_file")
        if self.ensemble is not None:
            name = f"ensemble_{len(self.env.captured):03d}.npz"
            with atomic_write(self.out / name) as tmp:
                self.ensemble.save(str(tmp))
            self.record["ensemble_file"] = name
        self._save_record()
        if previous and previous != self.record["ensemble_file"]:
            (self.out / previous).unlink(missing_ok=True)

    def _save_view(self, n: int, view: View) -> None:
        stem = self.out / "views" / f"view_{n:03d}"
        write_png(stem.with_suffix(".png"), view.rgb)
        write_exr(stem.with_suffix(".exr"), self._exr_channels(view))

    # -- the loop -----------------------------------------------------------
    def execute(self) -> dict:
        """Run, resume or extend the run in the folder; returns its record.

        Raises:
            FolderInUse: another run is writing the folder now (nothing is touched).
            TrainingDiverged: a field's training diverged; once the folder holds
                a record, the message says that resuming would diverge again.
            UserError: the folder holds a run this one cannot go on from.
            OSError: the folder cannot be made or written (a file in its
                place, no permission, a full disk), as Python's file functions raise it.
        """
        self.out.mkdir(parents=True, exist_ok=True)
        with folder_lock(self.out):
            try:
                return self._execute()
            except TrainingDiverged as exc:
                if not self.record_path.is_file():
                    raise
                # Resumed, the run would train the same saved state the same way again.
                raise TrainingDiverged(f"{exc}; resumed, {self.out} would diverge again: remove it, or choose "
                                       "another run folder, to start over with other settings") from None

    def _execute(self) -> dict:
        from tqdm import tqdm

        self._clock = time.perf_counter()  # wall time accumulates across resumes
        resumed = self._load_or_start()
        cfg = self.cfg
        if self.record["finished"]:
            self.log(f"{self.out} is already complete")
            if not (self.out / REPORT_FILE).is_file():  # a run finished before runs had a page
                write_run_page(self.out, self.record)
            return self.record
        if resumed:
            self.env.reset(seed=cfg.seed, options={"initial_views": 0})
            self.env.restore(self.record["captured"])
            self.journey.restore(self.record["captured"], self.record.get("travel"))
            if self.record["captured"]:
                self.journey.embodiment.start(self.journey.positions[self.record["captured"][0]])
            # Written again from the restored views: one damaged or deleted by
            # the interruption is whole again.
            for n, v in enumerate(self.env.views):
                self._save_view(n, v)
            n = len(self.env.captured)
            self.log(f"resuming {self.out}: {n} of {cfg.budget} views captured"
                     + (f" (the budget was {self._budget_was})" if self._budget_was is not None else ""))
            if self._budget_was is not None and ends_short_of_a_batch(n, cfg.initial_views, cfg.batch):
                self.log(f"note: its last round captured fewer than {cfg.batch} views, so its rounds from here "
                         f"differ from those of a run made with a budget of {cfg.budget} from the start")
        else:
            self.env.reset(seed=cfg.seed, options={"initial_views": cfg.initial_views})
            self._travel_initial()
            self.record["captured"] = list(self.env.captured)
            for n, v in enumerate(self.env.views):
                self._save_view(n, v)

        state = PlanningState(self.source.candidates, self.env.captured, None, None, self.rng)
        if self.planner.needs_ensemble:
            state.candidate_rays = sparse_candidate_rays(self.source.candidates, cfg.rays_per_candidate,
                                                         cfg.seed + 1)
            self.ensemble = make_ensemble(self.source, cfg, self.planner.ensemble_size(cfg.ensemble), cfg.seed,
                                          make_field=self.planner.make_field)
            ens_file = self.record.get("ensemble_file")
            if resumed and ens_file and (self.out / ens_file).is_file():
                self.ensemble = type(self.ensemble).load(str(self.out / ens_file))  # the planner's kind of field
                # The rays it was trained on: its occupancy grid still holds.
                train_on(self.ensemble, self.env.views, 0, reset_occupancy=False)
            elif self.env.views:
                t0 = time.perf_counter()
                train_on(self.ensemble, self.env.views, cfg.initial_steps + cfg.steps_per_view * len(self.env.views),
                         self.progress)
                self._add_planning_time(time.perf_counter() - t0)
            state.ensemble = self.ensemble
        self._save_record()
        for note in self.notes:
            self.log(note)

        bar = tqdm(total=cfg.budget, initial=len(self.env.captured), desc=planner_label(cfg.planner), unit="view",
                   disable=not self.progress)
        while True:
            self._evaluate_due()
            if self.env.terminated or self.record.get("stopped"):
                break
            b = min(cfg.batch, cfg.budget - len(self.env.captured))
            t0 = time.perf_counter()
            picks, scores = self.planner.checked_select(state, b)
            picks = self.journey.weigh(picks, scores, unseen(state))
            t_select = time.perf_counter() - t0
            picks = self._travel_to(picks)
            if not picks:
                continue
            t1 = time.perf_counter()
            if self.ensemble is not None:
                # With no initial views the ensemble meets its first data here.
                first = cfg.initial_steps if len(self.env.captured) == len(picks) else 0
                train_on(self.ensemble, self.env.views, first + cfg.steps_per_view * b)
            self.record["captured"] = list(self.env.captured)
            self.record["rounds"].append({
                "views": len(self.env.captured), "picks": [int(i) for i in picks],
                "poses": [self.source.candidates[int(i)].to_world.tolist() for i in picks],
                # JSON has no inf or NaN: a score that is not finite is written as null.
                "scores": None if scores is None else [float(s) if math.isfinite(s) else None for s in scores],
                "select_seconds": round(t_select, 4), "train_seconds": round(time.perf_counter() - t1, 4),
                "travel": self.journey.legs[-len(picks):]})
            self._add_planning_time(t_select + time.perf_counter() - t1)
            self._save_round()
            bar.update(len(picks))
        bar.close()
        self._write_outputs()
        self.record["finished"] = True
        self._save_record()
        write_run_page(self.out, self.record)
        return self.record

    # -- travel -------------------------------------------------------------
    def _travel_initial(self) -> None:
        """Account the travel through the initial views; the first is the start pose."""
        captured = list(self.env.captured)
        if captured:
            self.journey.embodiment.start(self.journey.positions[captured[0]])
        if captured and not self.journey.embodiment.reachable(self.journey.positions[captured[0]][None])[0]:
            raise UserError(f"the start pose, candidate {captured[0]} at "
                            f"{np.round(self.journey.positions[captured[0]], 4).tolist()}, lies inside the geometry "
                            f"or too near it for the {self.cfg.embodiment}")
        for n, i in enumerate(captured):
            route, why = self.journey.fits(i)
            self.journey.advance(i, route)
            if why and not self.record.get("stopped"):  # captured already: the run stops after them
                self._stop(n + 1, f"the initial views alone pass the budgets ({why})")
        self.record["travel"] = self.journey.legs

    def _travel_to(self, picks: list[int]) -> list[int]:
        """Capture ``picks`` in order while they fit the travel budgets; returns those captured."""
        done = []
        for i in picks:
            route, why = self.journey.fits(i)
            if why:
                self._stop(len(self.env.captured), why)
                break
            self.env.step(i)
            self.journey.advance(i, route)
            self._save_view(len(self.env.captured) - 1, self.env.views[-1])
            done.append(i)
        self.record["travel"] = self.journey.legs
        return done

    def _stop(self, views: int, why: str) -> None:
        self.record["stopped"] = {"views": views, "reason": why}
        self.log(f"stopped at {views} view{'' if views == 1 else 's'}: {why}")

    def _evaluate_due(self) -> None:
        done = {m["views"] for m in self.record["metrics"]}
        n = len(self.env.captured)
        stopped = [n] if self.record.get("stopped") and n >= max(self.cfg.initial_views, 1) else []
        for count in sorted(set(self.cfg.report_counts()) | set(stopped)):
            if count <= n and count not in done:
                # In candidate order: planners that captured the same views, in any order, score the same.
                first = sorted(range(count), key=lambda i: self.env.captured[i])
                metrics, preds = evaluate(self.source, [self.env.views[i] for i in first], self.cfg)
                leg = self.journey.legs[count - 1] if len(self.journey.legs) >= count else {}
                metrics["travel_distance"], metrics["mission_time"] = leg.get("distance"), leg.get("time")
                self.record["metrics"].append(metrics)
                self.record["metrics"].sort(key=lambda m: m["views"])
                self._last_preds = preds
                self.log(f"  {count:3d} views: {scores_line(metrics)}")
                note = evaluation_note(metrics, self.cfg.eval_steps, RunConfig.eval_steps)
                if note and not self._warned_fit:
                    self._warned_fit = True  # once a run: the later evaluations train as long
                    self.log(note)
                self._save_record()

    # -- results ------------------------------------------------------------
    def _write_outputs(self) -> None:
        from .report import contact_sheet, plot_metrics, plot_views
        from .travelplots import plot_travel

        write_metrics_csv(self.out / "metrics.csv", self.record["metrics"])
        label = planner_label(self.cfg.planner)
        plot_metrics({label: self.record["metrics"]}, self.out, title=self.source.name)
        plot_travel({**self.record, "up": getattr(getattr(self.source, "scene", None), "up", None)}, self.out,
                    title=f"{self.source.name}: {label}, {self.cfg.embodiment}")
        files = self.record.get("candidate_files")  # a dataset's: its frames are known by their files
        names = [Path(files[i]).stem if files else f"cand {i}" for i in self.env.captured]
        contact_sheet([v.rgb for v in self.env.views], [f"#{n} {name}" for n, name in enumerate(names)],
                      self.out / "chosen_views.png")
        scene = getattr(self.source, "scene", None)
        # A dataset has no scene: its cameras' own up vectors tell which way is up.
        up = scene.up if scene is not None else snapped_up(self.source.candidates)
        n = len(self.env.captured)
        plot_views(self.source.candidates, self.env.captured, self.source.heldout, self.source.bbox_min,
                   self.source.bbox_max, self.out / "camera_views.png", up=up,
                   initial=min(self.cfg.initial_views, n),
                   title=f"{self.source.name}: {label}, {n} view{'' if n == 1 else 's'}")
        preds = getattr(self, "_last_preds", None)
        if preds is None:  # resumed after the last evaluation: score again to get images
            _, preds = evaluate(self.source, self.env.views, self.cfg)
        self._write_heldout(preds)

    def _write_heldout(self, preds: list[dict]) -> None:
        folder = self.out / "heldout"
        for i, pred in enumerate(preds):
            gt = self.source.heldout_view(i)
            stem = folder / f"heldout_{i:03d}"
            write_png(f"{stem}_pred.png", pred["rgb"])
            write_png(f"{stem}_gt.png", gt.rgb)
            write_exr(f"{stem}_pred.exr", {"RGB": srgb_to_linear(pred["rgb"]), "Z": pred["distance"]})
            write_exr(f"{stem}_gt.exr", self._exr_channels(gt))
            if self.ensemble is not None and self.ensemble.n_members > 1:
                ens_pred = predict_view(self.ensemble, self.source.heldout[i])
                var = ens_pred["rgb_var"].mean(axis=2)
                write_exr(f"{stem}_variance.exr", {"RGB": ens_pred["rgb_var"], "Z": ens_pred["distance_var"]})
                write_png(f"{stem}_variance.png", colorize(var, vmin=0.0))


def write_metrics_csv(path, metrics: list[dict]) -> None:
    """A run's metrics as CSV, one row per view count, each figure with its :data:`~.metrics.DECIMALS`
    (empty where a record has none)."""
    cols = ["views", "psnr", "psnr_fg", "ssim", "distance_error", "floor_psnr", "floor_psnr_fg", "fit_psnr",
            "fit_start_psnr", "eval_seconds", "travel_distance", "mission_time"]
    with atomic_write(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols, extrasaction="ignore")
        w.writeheader()
        for m in metrics:
            w.writerow({k: fixed(v, DECIMALS.get(k)) for k, v in m.items()})


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"cannot store {type(o).__name__} in run.json")


def default_out_dir(scene_path, planner: str, seed: int) -> Path:
    path = Path(scene_path)
    stem = path.stem if path.suffix else path.name
    if path.suffix == ".json":  # transforms.json / transforms_train.json: name the dataset folder
        stem = path.resolve().parent.name
    return Path("runs") / f"{stem}-{planner_folder(planner)}-seed{seed}"
