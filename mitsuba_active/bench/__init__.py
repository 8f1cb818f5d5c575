"""Benchmark suites: scenes x planners x seeds, run in parallel, reported as tables and plots.

Each (scene, planner, seed) is one :class:`~mitsuba_active.run.Run` with its
own folder and run.json, so an interrupted suite resumes where it stopped.
Unless a suite sets otherwise, every run has budget 20 and is evaluated at
5, 10, 15 and 20 views; the tables report 10 and 20 views, as the seed paper does
(other budgets: the budget and the count nearest half of it), and a table of means
over scenes gives each planner's margin over ``random`` and ``even``.

- :mod:`.suite`: the suite file, parsed and checked, and ``--set``;
- :mod:`.jobs`: its runs, planned and checked before any starts, and one run;
- :mod:`.runner`: the jobs run on an executor (:mod:`mitsuba_active.executors`), then the report;
- :mod:`.stats`: statistics over seeds and scenes;
- :mod:`.tables`: the report's tables and plots.
"""

from .jobs import PROFILES, Job, _recorded, finished_record, plan_jobs, run_job
from .runner import MAX_WORKERS_PER_CORE, run_suite
from .stats import (BASELINES, METRICS, TABLE_VIEWS, TIE, collect, metric_at, scene_means, summarize, table_views,
                    unreported_seeds, usable)
from .suite import (JOB_KEYS, SCENE_OPTIONS, SUMMARY, TABLE_KEYS, Suite, SuitePlanner, SuiteScene, load_suite,
                    parse_overrides)
from .tables import PLOTTED, SUMMARY_PLOTTED, _mean_table, _table, write_report

__all__ = ["BASELINES", "JOB_KEYS", "MAX_WORKERS_PER_CORE", "METRICS", "PLOTTED", "PROFILES", "SCENE_OPTIONS",
           "SUMMARY", "SUMMARY_PLOTTED", "Suite", "SuitePlanner", "SuiteScene", "TABLE_KEYS", "TABLE_VIEWS", "TIE",
           "Job", "collect", "finished_record", "load_suite", "metric_at", "parse_overrides", "plan_jobs", "run_job",
           "run_suite", "scene_means", "summarize", "table_views", "unreported_seeds", "usable", "write_report"]
