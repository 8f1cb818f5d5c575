"""The statistics of a suite's finished runs: per cell over seeds, and per planner over scenes."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from ..metrics import iqm, standard_error
from ..run import RunConfig
from .jobs import Job, finished_record

#: View counts of the tables, as in the seed paper, when every run evaluates them.
TABLE_VIEWS = (10, 20)
#: Planners that the scene-mean table measures every other planner against.
BASELINES = ("random", "even")
#: Differences up to this (dB, or points of the metric) are ties, not wins:
#: planners that captured the same views differ by rounding alone.
TIE = 1e-6
#: Metrics of the tables: title, and whether higher values are better.
METRICS = {"psnr": ("Photometric held-out PSNR (dB)", True),
           "psnr_fg": ("Foreground held-out PSNR (dB)", True),
           "distance_error": ("Distance error (%)", False)}


def collect(jobs: list[Job]) -> dict:
    """scene -> planner -> list of finished run records (one per seed)."""
    out: dict = {}
    for job in jobs:
        rec = finished_record(job)
        if rec is not None:
            out.setdefault(job.scene, {}).setdefault(job.planner, []).append(rec)
    return out


def unreported_seeds(jobs: list[Job]) -> list[int]:
    """Seeds of runs in the jobs' folders that finished with the jobs' settings
    (but their seed) and that the jobs leave out: a suite run with
    ``--seeds 0,1`` reported without them."""
    asked = {job.seed for job in jobs}
    found = set()
    groups = {}  # one job of each scene and planner: its seeds' folders lie side by side
    for job in jobs:
        folder = Path(job.out)
        groups.setdefault((folder.parent, folder.name[:folder.name.rindex("-seed") + len("-seed")]), job)
    for (parent, stem), job in groups.items():
        for other in parent.glob(f"{stem}*"):
            tail = other.name[len(stem):]
            if not tail.isdigit() or int(tail) in asked or int(tail) in found:
                continue
            seed = int(tail)
            twin = replace(job, seed=seed, out=str(other), config={**job.config, "seed": seed})
            if finished_record(twin) is not None:
                found.add(seed)
    return sorted(found)


def metric_at(rec: dict, metric: str, views: int, at_end: bool = False):
    """A run's ``metric`` at ``views`` captured (None: not evaluated there); ``at_end``: at its
    last evaluation where its travel or time budget stopped it before ``views``."""
    stopped = rec.get("stopped")
    if at_end and isinstance(stopped, dict) and isinstance(stopped.get("views"), int) and stopped["views"] < views:
        views = stopped["views"]
    for m in rec["metrics"]:
        if m["views"] == views and m.get(metric) is not None:
            return m[metric]
    return None


def usable(value) -> bool:
    """Whether a seed's value counts in a table: a finite number (a NaN PSNR, from a dataset image
    with NaN pixels, or an infinite one, from a perfect view, counts as missing), in every cell and margin alike."""
    return value is not None and bool(np.isfinite(value))


def summarize(values) -> dict:
    vals = [v for v in values if usable(v)]
    return {"iqm": iqm(vals) if vals else None, "se": standard_error(vals) if vals else None, "n": len(vals)}


def travel_budgeted(jobs: list[Job]) -> bool:
    """Whether the suite's runs have a travel or time budget: its tables' last column is then
    the metric where the budget ends (a run it stops early, at its last view)."""
    return any(j.config.get("travel_budget") is not None or j.config.get("time_budget") is not None for j in jobs)


def table_views(jobs: list[Job]) -> tuple:
    """The view counts the tables report: :data:`TABLE_VIEWS` when every job
    evaluates them and none more, else the largest count every job evaluates and the one
    nearest half of it, the larger of two as near (a suite with another budget
    or other counts: of 2, 4 and 6 views, 4 and 6), but not the initial views
    (where every planner has the same views)."""
    common = set.intersection(*[set(RunConfig(**j.config).report_counts()) for j in jobs]) if jobs else set()
    if not common or (set(TABLE_VIEWS) <= common and max(common) == max(TABLE_VIEWS)):
        return TABLE_VIEWS
    last = max(common)
    initial = max(int(j.config.get("initial_views", 0)) for j in jobs)
    rest = sorted((v for v in common - {last} if v > initial), key=lambda v: (abs(v - last / 2), -v))
    return (rest[0], last) if rest else (last,)


def scene_means(summary: dict, scenes, planners, metric: str) -> dict:
    """Each planner over the scenes where every planner with results has a value at every table view.

    A planner without any such scene yet (a suite still running) is left out
    of that condition and gets no means. Returns ``{planner: {"scenes": n,
    "seeds": the distinct seed counts of its cells, "mean@V": mean of the
    cells' IQMs, "vs_B@V": mean difference to baseline B, "wins_vs_B@V":
    scenes where the planner is better than B, "compared_vs_B@V": scenes
    compared}}`` for each table view V and each baseline of :data:`BASELINES`
    with results (better: higher, or lower for errors, by more than :data:`TIE`).

    A difference on a scene is paired: the two planners' interquartile means
    over the seeds both have (cells' ``per_seed``), so that a planner missing
    a seed (a suite still running) is not compared with its baseline's other
    seeds; a scene where they share no seed is not compared.
    """
    cells = {(c["scene"], c["planner"]): c for c in summary["cells"]}
    views = tuple(summary.get("table_views", TABLE_VIEWS))

    def value(s, p, v):
        c = cells.get((s, p))
        return None if c is None else c[f"{metric}@{v}"]["iqm"]

    def paired(s, p, b, v):
        """(p's, b's) value on scene s over the seeds both have, or None."""
        key, cp, cb = f"{metric}@{v}", cells[(s, p)], cells[(s, b)]
        common = [k for k in cp["per_seed"] if k in cb["per_seed"]
                  and usable(cp["per_seed"][k].get(key)) and usable(cb["per_seed"][k].get(key))]
        if not common:
            return None
        return tuple(iqm([c["per_seed"][k][key] for k in common]) for c in (cp, cb))

    def has_all(s, p):
        return all(value(s, p, v) is not None for v in views)

    present = [p for p in planners if any(has_all(s, p) for s in scenes)]
    complete = [s for s in scenes if present and all(has_all(s, p) for p in present)]
    higher_is_better = METRICS[metric][1]
    rows = {}
    for p in planners:
        used = complete if p in present else []
        row = {"scenes": len(used), "seeds": sorted({cells[(s, p)].get("seeds") for s in used} - {None})}
        for v in views:
            row[f"mean@{v}"] = float(np.mean([value(s, p, v) for s in used])) if used else None
            for b in BASELINES:
                if b == p or b not in present or not used:
                    continue
                pairs = [pair for s in used if (pair := paired(s, p, b, v)) is not None]
                diff = [a - c for a, c in pairs]
                row[f"vs_{b}@{v}"] = float(np.mean(diff)) if diff else None
                row[f"wins_vs_{b}@{v}"] = int(sum((d > TIE) if higher_is_better else (d < -TIE) for d in diff))
                row[f"compared_vs_{b}@{v}"] = len(diff)
        rows[p] = row
    return rows
