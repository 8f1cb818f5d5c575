"""The acquisition loop: one planning run in its folder, started, resumed or extended.

One run: start from ``initial_views`` random candidates, then repeatedly
let the planner choose ``batch`` views, capture them, and (for model-based
planners) continue training the ensemble on all views so far (warm start),
until ``budget`` views are captured. At each reported view count the
evaluation protocol (:mod:`mitsuba_active.protocol`) scores the views so far.

A run writes everything into one folder and keeps ``run.json`` current
after every round, so an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import copy
import csv
import json
import math
import time
import warnings
from dataclasses import asdict
from functools import partial
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from tqdm import tqdm

from .. import __version__
from ..cameras import Camera, look_at
from ..continuous import PoseSampler, RigSurface, choose_fresh
from ..datasets import DatasetSource
from ..embodiments import make_embodiment
from ..env import ActiveViewEnv, SceneSource
from ..errors import FolderError, TrainingDiverged, UserError
from ..groundtruth import View
from ..imageio_utils import atomic_write, colorize, folder_lock, srgb_to_linear, write_exr, write_png
from ..metrics import DECIMALS, fixed
from ..planners import PlanningState, make_planner
from ..planners.base import planner_digest, planner_label, planner_rng, unseen
from ..protocol import evaluate_views, new_field
from ..record import ALONG_THE_WAY, CONTINUOUS, RUN_FORMAT, along_the_way_views, json_default
from ..report import contact_sheet, plot_metrics, plot_views
from ..rigs import generated_rig, room_for_camera
from ..training import (acquisition_steps, evaluation_note, has_distances, predict_view, scores_line,
                        sparse_candidate_rays, train_on)
from ..travel import Journey, diameter_of, stops_along
from ..travelplots import plot_travel
from ..upright import snapped_up
from ..webpage import REPORT_FILE, write_run_page
from .config import RunConfig, source_field_config
from .resume import ends_short_of_a_batch, read_resumable_record, resume_obstacles, other_settings


def make_ensemble(source, cfg: RunConfig, n_members: int, seed: int, planner: bool = True, make_field=None):
    """The planner's ensemble (``planner=True``) or an evaluation field, configured from ``cfg``.

    ``make_field``: the planner's :meth:`~mitsuba_active.planners.Planner.make_field`
    (the field it scores with), else an :class:`~mitsuba_active.field.Ensemble`.
    """
    return new_field(source, source_field_config(source, cfg, planner), n_members, seed, make_field)


def evaluate(source, views: list[View], cfg: RunConfig, progress: bool = False) -> tuple[dict, list[dict]]:
    """:func:`~mitsuba_active.protocol.evaluate_views` with the run's evaluation field:
    ``cfg``'s field settings, its seed (offset from the planner's) and ``eval_steps``."""
    config = source_field_config(source, cfg, planner=False)
    return evaluate_views(source, views, config, seed=cfg.seed + 7919, steps=cfg.eval_steps, progress=progress)


def source_differences(source, cfg: RunConfig) -> list[str]:
    """Environment settings of ``cfg`` that a scene source was not made with,
    as ``"name=value (the source's: value)"``: the scene, image width, view
    counts and samples per pixel. Not ``rig`` and ``fov``, so that a source
    with cameras of the caller's own can run (run.json records the cameras
    themselves). A dataset opened by ``DatasetSource.from_path`` must have the
    frames and image size that ``cfg.open_source()`` gives; one built from
    frames of the caller's own is not checked."""
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
        if cfg.along_the_way is not None or cfg.candidates_mode == "continuous":
            source = self._own_source(source, cfg)
        self.source, self.cfg, self.out = source, cfg, Path(out_dir)
        self.progress, self.log, self.notes = progress, log, tuple(notes)
        self.planner = make_planner(cfg.planner, **cfg.planner_options)
        self.planner_digest = planner_digest(cfg.planner)  # of the code just loaded
        self.planner.check_ensemble_size(cfg.ensemble)
        source_field_config(source, cfg)  # field options are checked before anything is written
        self.env = ActiveViewEnv(source, cfg.budget, allow_repeats=True)  # the random planner repeats views
        embodiment = make_embodiment(cfg.embodiment, getattr(source, "scene", None), cfg.speed, cfg.turning_radius)
        self.journey = Journey(embodiment, cfg, [c.to_world[:3, 3] for c in source.candidates],
                               diameter_of(source.bbox_min, source.bbox_max), [c.forward for c in source.candidates])
        self.sampler = None
        if cfg.candidates_mode == "continuous":
            # A room's cameras see most from its walls: nearer its centre they see less of it.
            room = generated_rig(source.scene, cfg.rig) == "interior"
            free = partial(room_for_camera, source.scene) if room else source.scene.free_space
            self.sampler = PoseSampler(RigSurface(source.candidates, source.scene.up), self.journey.embodiment,
                                       source.heldout, free, 1.0 if room else cfg.nearest)
        self.rng = planner_rng(cfg.seed)
        self.record = None
        self.ensemble = None
        self._warned_fit = False
        self._budget_was = None  # the budget of the run in the folder, where this one differs

    @staticmethod
    def _own_source(source, cfg: RunConfig):
        """A copy of a scene source whose candidate list the run may add cameras to; UserError for a
        source that cannot render new poses."""
        flag = "--along-the-way" if cfg.along_the_way is not None else "--candidates-mode continuous"
        if not isinstance(source, SceneSource):
            raise UserError(f"{flag} renders new poses, which only a scene can; {source.name} is a dataset "
                            "of captured frames")
        mine = copy.copy(source)
        mine.candidates = list(source.candidates)
        return mine

    def _add_camera(self, camera, kind: str, record: bool = True) -> int:
        """Make ``camera`` a candidate of the run (``kind``: why it was added); its index."""
        index = self.env.add_candidate(camera)
        self.journey.add(camera.position, camera.forward)
        if record:
            self.record.setdefault("added", []).append({"camera": camera.to_dict(), "kind": kind})
        return index

    # -- persistence --------------------------------------------------------
    @property
    def record_path(self) -> Path:
        return self.out / "run.json"

    @property
    def versions(self) -> dict:
        """The versions this run is made with: the package's, Mitsuba's, Dr.Jit's and the variant."""
        return {"mitsuba_active": __version__, "mitsuba": mi.__version__, "drjit": dr.__version__,
                "variant": mi.variant()}

    def _config_dict(self) -> dict:
        return json.loads(json.dumps(asdict(self.cfg), default=json_default))

    def _load_or_start(self) -> bool:
        """Load an unfinished run from the folder; True when resuming."""
        if self.record_path.is_file():
            rec = read_resumable_record(self.record_path)
            found = resume_obstacles(rec, self._config_dict(), self._content_hash(), self.planner_digest,
                                     cameras=([c.to_dict() for c in self.source.candidates],
                                              [c.to_dict() for c in self.source.heldout]))
            if "settings" in found:
                raise other_settings(self.out, found["settings"], "choose another run folder")
            if "content" in found:
                raise FolderError(self.out, "holds a run of a scene or dataset that has changed since; choose "
                                            "another run folder")
            if "cameras" in found:
                made_with = rec.get("versions", {}).get("mitsuba_active")
                now = self.versions["mitsuba_active"]
                why = (f" (it was made with mitsuba-active {made_with}, whose rigs place cameras otherwise than "
                       f"{now}'s)" if made_with not in (None, now) else "")
                raise FolderError(self.out, f"holds a run whose candidate or held-out cameras are not the view "
                                            f"source's{why}; choose another run folder")
            captured = rec["captured"]
            if "planner" in found:
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
            tmp.write_text(json.dumps(self.record, indent=1, default=json_default))

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
            for added in self.record.get("added", ()):  # the cameras it added, at the indices it gave them
                self._add_camera(Camera.from_dict(added["camera"]), added["kind"], record=False)
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

        state = PlanningState(self.source.candidates, self.env.captured, None, None, self.rng,
                              budget=cfg.budget if self.sampler is None else None)
        if cfg.embodiment != "teleport" and self.sampler is None:  # a pool pose too near the geometry is no pick
            state.out_of_reach = set(np.flatnonzero(~self.journey.embodiment.reachable(self.journey.positions)))
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
                train_on(self.ensemble, self.env.views,
                         acquisition_steps(0, len(self.env.views), cfg.initial_steps, cfg.steps_per_view), self.progress)
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
            if self.sampler is None and np.count_nonzero(unseen(state)) < b:
                self._stop(len(self.env.captured), f"the {cfg.embodiment} can reach no candidate left")
                continue
            t0 = time.perf_counter()
            if self.sampler is not None:
                picks, scores = self._select_continuous(state, b)
            else:
                if state.candidate_rays is not None and len(state.candidate_rays[0]) != len(state.candidates):
                    state.candidate_rays = sparse_candidate_rays(state.candidates, cfg.rays_per_candidate,
                                                                 cfg.seed + 1)  # with the cameras added
                picks, scores = self.planner.checked_select(state, b)
                picks = self.journey.weigh(picks, scores, unseen(state))
            t_select = time.perf_counter() - t0
            picks = self._travel_to(picks, state.out_of_reach)
            if not picks:
                continue
            t1 = time.perf_counter()
            if self.ensemble is not None:
                train_on(self.ensemble, self.env.views,
                         acquisition_steps(len(self.env.captured) - len(picks), len(picks), cfg.initial_steps,
                                           cfg.steps_per_view))
            self.record["captured"] = list(self.env.captured)
            self.record["rounds"].append({
                "views": len(self.env.captured), "picks": [int(i) for i in picks],
                "poses": [self.source.candidates[int(i)].to_world.tolist() for i in picks],
                # JSON has no inf or NaN: a score that is not finite is written as null.
                # Continuous rounds score poses that are not the run's cameras: none are kept.
                "scores": None if scores is None or self.sampler is not None else
                [float(s) if math.isfinite(s) else None for s in scores],
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

    # -- continuous candidates ---------------------------------------------------
    def _select_continuous(self, state: PlanningState, batch: int) -> tuple[list[int], np.ndarray | None]:
        """The round's picks (run indices) among fresh poses (:func:`~mitsuba_active.continuous.choose_fresh`);
        the poses chosen are added to the run."""
        rng = np.random.default_rng([self.cfg.seed, len(self.record["rounds"]), 1])  # the same on resume
        owners = list(dict.fromkeys(self.env.captured))  # distinct captured views, in order
        chosen, scores = choose_fresh(self.planner, self.journey, self.sampler, state, owners,
                                      [self.source.candidates[i] for i in owners], batch, rng, self.cfg)
        if chosen is None:
            self._stop(len(self.env.captured), f"the {self.cfg.embodiment} can reach no pose on the rig")
            return [], None
        return [c if isinstance(c, int) else self._add_camera(c, CONTINUOUS) for c in chosen], scores

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

    def _travel_to(self, picks: list[int], out_of_reach: set) -> list[int]:
        """Capture ``picks`` in order while they fit the travel budgets; returns those captured. A pick
        with no route from here joins ``out_of_reach`` and is passed over, unless it was there already."""
        done = []
        for i in picks:
            route, why = self.journey.fits(i)
            if not route.found and i not in out_of_reach:
                out_of_reach.add(i)
                continue
            if why:
                self._stop(len(self.env.captured), why)
                break
            if self.cfg.along_the_way is not None:
                route, seen = self._along_the_way(route)
                done += seen
            self.env.step(i)
            self.journey.advance(i, route)
            self._save_view(len(self.env.captured) - 1, self.env.views[-1])
            done.append(i)
        self.record["travel"] = self.journey.legs
        return done

    def _along_the_way(self, route) -> tuple:
        """Capture the views along ``route`` that the budgets leave room for besides its end
        (:func:`~mitsuba_active.travel.stops_along`); returns the rest of the route and their indices."""
        cfg, done = self.cfg, []
        room = cfg.budget - len(self.env.captured) - 1  # the route's end is captured too
        if cfg.time_budget is not None and cfg.capture_time > 0:
            spare = cfg.time_budget * (1 + 1e-9) - self.journey.time - route.time - cfg.capture_time
            room = min(room, int(spare // cfg.capture_time))
        stops, rest = stops_along(route, cfg.along_the_way, cfg.speed, room)
        ref, scene = self.source.candidates[0], self.source.scene
        for piece in stops:
            cam = Camera(look_at(piece.points[-1], scene.center, scene.up), ref.fov, ref.width, ref.height,
                         ref.near, ref.far)
            j = self._add_camera(cam, ALONG_THE_WAY)
            self.env.step(j)
            self.journey.advance(j, piece)
            self._save_view(len(self.env.captured) - 1, self.env.views[-1])
            done.append(j)
        return rest, done

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
                   title=f"{self.source.name}: {label}, {n} view{'' if n == 1 else 's'}",
                   routes=[np.asarray(leg["route"]) if leg.get("route") else None for leg in self.journey.legs],
                   along=along_the_way_views(self.record))
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
