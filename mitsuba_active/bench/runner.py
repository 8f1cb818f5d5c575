"""Running a suite: its jobs on an executor (local worker processes or Ray), then its report."""

from __future__ import annotations

import os
from pathlib import Path

from tqdm import tqdm

from ..colmap import is_colmap_project
from ..errors import UserError
from ..executors import EXECUTORS, RayOptions, prepare_ray, run_local, run_ray
from ..run import ends_short_of_a_batch
from ..transforms import TRANSFORMS_FILES
from .jobs import _recorded, finished_record, plan_jobs, run_job
from .suite import load_suite
from .tables import write_report

#: Most --workers per CPU core (each worker trains fields on its share of the cores).
MAX_WORKERS_PER_CORE = 4


def run_suite(suite_path, out_dir, profile="quick", workers=1, seeds=None, planners=None, scenes=None,
              progress=True, log=print, report_only=False, overrides=None, executor="local",
              ray: RayOptions | None = None) -> dict:
    """Run every job of a suite (resuming finished ones) and write the report; returns the summary.

    ``report_only`` runs nothing and reports the runs finished so far (safe
    while another process is still running the suite). ``overrides``
    (:func:`~.suite.parse_overrides`) change every run's settings. ``executor`` runs
    them (:data:`~mitsuba_active.executors.EXECUTORS`): ``local``, in
    ``workers`` processes; ``ray``, as Ray tasks, as ``ray`` says."""
    if executor not in EXECUTORS:
        raise ValueError(f"executor is one of {', '.join(EXECUTORS)}, got {executor!r}")
    if ray is not None and executor != "ray":
        raise ValueError("ray options are for executor='ray'")
    suite = load_suite(suite_path)
    out_dir = Path(out_dir)
    cores = os.cpu_count() or 1
    if not 1 <= workers <= MAX_WORKERS_PER_CORE * cores:
        raise UserError(f"--workers must be between 1 and {MAX_WORKERS_PER_CORE * cores} "
                        f"({MAX_WORKERS_PER_CORE} per core of this machine's {cores}), got {workers}")
    if executor == "ray" and not report_only:  # before anything is authored
        colmap = [sc.name for sc in suite.scenes if sc.kind == "dataset" and (not scenes or sc.name in scenes)
                  and is_colmap_project(sc.path) and not any((sc.path / n).is_file() for n in TRANSFORMS_FILES)]
        if colmap:  # its tasks are sent a scene's files or a transforms dataset's, not a COLMAP project's
            raise UserError(f"scene '{colmap[0]}' is a COLMAP project, which runs with local workers only "
                            "(--executor local); leave it out of a Ray run with --scenes")
        ray = ray or RayOptions()
        prepare_ray(ray)
    jobs = plan_jobs(suite, out_dir, profile, seeds, planners, scenes, author=not report_only,
                     overrides=overrides)
    if report_only:
        return write_report(suite, jobs, out_dir / "report", profile, overrides)
    kept = sum(finished_record(job) is not None for job in jobs)
    if kept:
        log(f"{kept} of the suite's {len(jobs)} runs finished earlier with these settings: kept, not run again")
    grown = [(job, rec) for job in jobs if (rec := _recorded(job)) and rec["finished"]
             and rec["config"].get("budget", job.config["budget"]) < job.config["budget"]]
    if grown:
        log(f"{len(grown)} of the suite's runs finished earlier with a smaller budget: they go on from the views "
            "they have")
        short = sum(ends_short_of_a_batch(len(rec["captured"]), job.config["initial_views"],
                                          job.config["batch"]) for job, rec in grown)
        if short:
            log(f"note: in {short} of them the last round captured fewer views than a batch, so their rounds from "
                "here differ from those of runs made with this budget from the start")
    bar = tqdm(total=len(jobs), desc=f"suite {suite.name}", unit="run", disable=not progress)
    try:
        if executor == "ray":
            bar.update(kept)
            out_dir.mkdir(parents=True, exist_ok=True)  # the folder a worker on shared storage sees
            run_ray([job for job in jobs if finished_record(job) is None], ray, bar, run_job)
        else:
            run_local(jobs, workers, bar, run_job)
    finally:
        bar.close()
    return write_report(suite, jobs, out_dir / "report", profile, overrides)
