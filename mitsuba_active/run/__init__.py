"""Planning runs: settings, the acquisition loop and its resumption.

- :mod:`.config`: :class:`RunConfig`, a run's settings, and the fields and
  view source they describe;
- :mod:`.resume`: whether a run folder can be resumed (:func:`resume_obstacles`);
- :mod:`.runner`: :class:`Run`, the loop, which writes the folder.

The evaluation protocol the runs score with is :mod:`mitsuba_active.protocol`; the
record (run.json, its format and its checked reader) is :mod:`mitsuba_active.record`,
outside this package so that reading a run loads nothing of running one.
"""

from ..protocol import loss_psnr
from ..record import ENSEMBLE_FILE, RECORD_PARTS, REQUIRED_PARTS, RUN_FORMAT, json_default, read_record
from ..training import sparse_candidate_rays, train_on
from .config import INTERIOR_DISTANCE_WEIGHT, RunConfig, default_out_dir, field_config, source_field_config
from .resume import (conflicting_settings, config_changes, config_differences, ends_short_of_a_batch,
                     other_planner_code, other_settings, read_resumable_record, resume_obstacles, same_config,
                     undone_unless_resumable)
from .runner import Run, evaluate, make_ensemble, source_differences, write_metrics_csv

__all__ = ["ENSEMBLE_FILE", "INTERIOR_DISTANCE_WEIGHT", "RECORD_PARTS", "REQUIRED_PARTS", "RUN_FORMAT", "Run",
           "RunConfig", "config_changes", "config_differences", "conflicting_settings", "default_out_dir",
           "ends_short_of_a_batch", "evaluate", "field_config", "json_default", "loss_psnr", "make_ensemble",
           "other_planner_code", "other_settings", "read_record", "read_resumable_record", "resume_obstacles",
           "same_config", "source_differences", "source_field_config", "sparse_candidate_rays", "train_on",
           "undone_unless_resumable", "write_metrics_csv"]
