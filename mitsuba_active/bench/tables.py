"""A suite's report: its tables (Markdown, CSV, JSON) and plots, written whole into report/."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..imageio_utils import replaced_folder
from ..metrics import DECIMALS, fixed
from ..report import plot_metrics
from ..training import weak_evaluation
from ..webpage import REPORT_FILE, write_run_page, write_suite_page
from .jobs import Job, finished_record
from .stats import (BASELINES, METRICS, TABLE_VIEWS, collect, metric_at, scene_means, summarize, table_views,
                    travel_budgeted, unreported_seeds)
from .suite import SUMMARY, Suite

#: Metrics of the plots, and those of the summary plot over scenes.
PLOTTED = ("psnr", "psnr_fg", "ssim", "distance_error", "floor_psnr", "floor_psnr_fg")
SUMMARY_PLOTTED = ("psnr", "psnr_fg", "floor_psnr", "floor_psnr_fg")


def write_report(suite: Suite, jobs: list[Job], report_dir: Path, profile: str, overrides=None) -> dict:
    """Tables (Markdown, CSV, JSON) in the layout of the seed's Tables I and III, and plots.

    ``overrides`` (the command line's ``--set``) are recorded in ``results.json``.
    With no finished run, nothing is written (an earlier report stays)."""
    data = collect(jobs)
    scenes = [s.name for s in suite.scenes if s.name in data]
    planners = [p for p in dict.fromkeys(j.planner for j in jobs)]
    views = table_views(jobs)
    end = max(views) if travel_budgeted(jobs) else None  # the column where a travel budget ends runs
    reported = [r for by_planner in data.values() for recs in by_planner.values() for r in recs]
    summary = {"suite": suite.name, "profile": profile, "overrides": overrides or {},
               "table_views": list(views), "runs": len(jobs), "runs_reported": len(reported),
               "budget_end_column": end,
               "unreported_seeds": unreported_seeds(jobs),
               # Runs whose evaluation fields scored near the background alone, or barely fit their own views.
               "short_training": sum(any(weak_evaluation(m) for m in r["metrics"]) for r in reported),
               # Finished runs are kept across upgrades: which versions made the reported ones.
               "versions": [json.loads(v) for v in sorted({json.dumps(r.get("versions"), sort_keys=True)
                                                           for r in reported})],
               "cells": []}
    if not data:  # nothing finished: keep whatever report is there
        return summary
    for scene in scenes:
        for planner in planners:
            recs = data[scene].get(planner, [])
            cell = {"scene": scene, "planner": planner, "seeds": len(recs),
                    "wall_seconds": summarize([r.get("wall_seconds") for r in recs]),
                    "planning_seconds": summarize([r.get("planning_seconds") for r in recs])}
            for metric in METRICS:
                for v in views:
                    cell[f"{metric}@{v}"] = summarize([metric_at(r, metric, v, v == end) for r in recs])
            # Each seed's values, for comparisons over the seeds two planners share.
            cell["per_seed"] = {str(r["config"]["seed"]): {f"{metric}@{v}": metric_at(r, metric, v, v == end)
                                                          for metric in METRICS for v in views} for r in recs}
            summary["cells"].append(cell)
    # The report is written whole into a new folder that then replaces the earlier one:
    # no half-written report after an interruption, and no plots of scenes it no longer covers.
    with replaced_folder(report_dir) as folder:
        summary["mean_over_scenes"] = {metric: scene_means(summary, scenes, planners, metric) for metric in METRICS}
        tables = []
        for metric, (title, _) in METRICS.items():
            md, csv_rows = _table(summary, scenes, planners, metric, title)
            (folder / f"table_{metric}.md").write_text(md)
            (folder / f"table_{metric}.csv").write_text("\n".join(",".join(map(str, r)) for r in csv_rows) + "\n")
            tables.append(md)
        note = _overrides_note(summary["overrides"])
        tables.insert(0, "\n".join(
            _mean_table(summary["mean_over_scenes"][m], planners, *METRICS[m], views=views, note=note, end=end)
            for m in METRICS))
        (folder / "table_mean.md").write_text(tables[0])
        (folder / "results.json").write_text(json.dumps(summary, indent=1))
        # Plots: per scene, IQM over seeds with a +-SE band; and a summary over the scenes
        # that every planner with results has. A planner has one colour in every plot.
        colors = {p: f"C{i % 10}" for i, p in enumerate(planners)}
        with_results = {p for by_planner in data.values() for p in by_planner}
        shared = [s for s in scenes if with_results <= set(data[s])]
        overall: dict = {}
        for scene in scenes:
            series, bands = {}, {}
            for planner, recs in data[scene].items():
                # The counts every seed has (a run taken on to a larger budget also has its earlier one).
                counts = sorted(set.intersection(*[{m["views"] for m in r["metrics"]} for r in recs]))
                rows, lo, hi = [], {}, {}
                for c in counts:
                    row = {"views": c}
                    for metric in PLOTTED:
                        s = summarize([metric_at(r, metric, c) for r in recs])
                        row[metric] = s["iqm"]
                        if s["iqm"] is not None:
                            lo.setdefault(metric, []).append(s["iqm"] - s["se"])
                            hi.setdefault(metric, []).append(s["iqm"] + s["se"])
                    rows.append(row)
                series[planner] = rows
                bands[planner] = {m: (lo[m], hi[m]) for m in lo if len(lo[m]) == len(counts)}
                for row in rows:
                    for metric in SUMMARY_PLOTTED:
                        if row[metric] is not None and scene in shared:
                            by_count = overall.setdefault(planner, {}).setdefault(metric, {})
                            by_count.setdefault(row["views"], []).append(row[metric])
            scene_plots = folder / "plots" / scene
            scene_plots.mkdir(parents=True, exist_ok=True)
            plot_metrics(series, scene_plots, title=scene, bands=bands, colors=colors)
        # A point of the summary is a mean over all of its scenes, never over some.
        mean_series = {}
        for p, by_metric in overall.items():
            points: dict = {}
            for metric, by_count in by_metric.items():
                for v, x in by_count.items():
                    if len(x) == len(shared):
                        points.setdefault(v, {"views": v})[metric] = float(np.mean(x))
            mean_series[p] = [points[v] for v in sorted(points)]
        if any(mean_series.values()):
            (folder / "plots" / SUMMARY).mkdir(parents=True, exist_ok=True)
            plot_metrics(mean_series, folder / "plots" / SUMMARY, colors=colors,
                         title=f"{suite.name}: mean over {len(shared)} scene{'' if len(shared) == 1 else 's'}")
        write_suite_page(folder, report_dir, f"{suite.name} ({profile})", tables, _run_pages(jobs))
    return summary


def _run_pages(jobs: list[Job]) -> dict:
    """scene -> planner -> folders of the finished runs, each with its page (written where a run
    finished before runs had one)."""
    out: dict = {}
    for job in jobs:
        rec = finished_record(job)
        if rec is None:
            continue
        if not (Path(job.out) / REPORT_FILE).is_file():
            write_run_page(job.out, rec)
        out.setdefault(job.scene, {}).setdefault(job.planner, []).append(job.out)
    return out


def _overrides_note(overrides: dict) -> str:
    """A sentence naming the settings ``--set`` changed for every run ('' when none),
    so that a table copied elsewhere keeps them."""
    settings = [(f"{k}.{name}", v) for k, table in overrides.items() if isinstance(table, dict)
                for name, v in table.items()]
    settings += [(k, v) for k, v in overrides.items() if not isinstance(v, dict)]
    flat = sorted(f"{k}={v!r}" if isinstance(v, str) else f"{k}={v}" for k, v in settings)
    return f" Every run with --set {', '.join(flat)}." if flat else ""


def _fmt(s: dict) -> str:
    if s["iqm"] is None:
        return "n/a"
    # One seed has no spread to estimate: no "± 0.00".
    return f"{s['iqm']:.2f}" if s["n"] < 2 else f"{s['iqm']:.2f} ± {s['se']:.2f}"


def _table(summary: dict, scenes, planners, metric: str, title: str):
    cells = {(c["scene"], c["planner"]): c for c in summary["cells"]}
    views = tuple(summary.get("table_views", TABLE_VIEWS))
    empty = {"iqm": None, "se": None, "n": 0}
    stats = {(s, p, v): cells[(s, p)][f"{metric}@{v}"] if (s, p) in cells else empty
             for s in scenes for p in planners for v in views}
    counts = {st["n"] for st in stats.values() if st["n"]}
    # One seed count for the whole table, or each cell's own when they differ
    # (a suite still running).
    per_cell = len(counts) > 1
    n = max(counts, default=0)
    if per_cell:
        stat = "Interquartile mean ± standard error of the mean over seeds (n per cell)"
    elif n == 1:
        stat = "One seed (no standard error)"
    else:
        stat = f"Interquartile mean ± standard error of the mean over {n} seeds"
    end = summary.get("budget_end_column")
    named = {v: f"end ({v})" if v == end else str(v) for v in views}
    head = ["planner"] + [f"{s} @{named[v]}" for s in scenes for v in views] + ["planning (s)", "wall time (s)"]
    at = " and ".join(map(str, views)) + " views captured"
    if end is not None:
        at = (" and ".join(str(v) for v in views if v != end) + " views captured and " if len(views) > 1 else "") + \
            f"the end of the travel budget (at most {end} views: a run it stops sooner at its last view)"
    lines = [f"## {title}", "", f"{stat}, at {at}. "
             "Times are means over scenes of each cell's interquartile mean: planning is the time spent "
             "choosing views and training the planner's ensemble; wall time is the whole run, with ground "
             "truth (cached renders are fast) and evaluation." + _overrides_note(summary.get("overrides") or {}),
             "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    csv_rows = [["planner", "scene", "views", "iqm", "se", "n"]]
    for p in planners:
        row, times = [p], {"planning_seconds": [], "wall_seconds": []}
        for s in scenes:
            c = cells.get((s, p))
            for v in views:
                st = stats[(s, p, v)]
                row.append(f"{_fmt(st)} ({st['n']})" if per_cell and st["iqm"] is not None else _fmt(st))
                csv_rows.append([p, s, v, fixed(st["iqm"], DECIMALS[metric]), fixed(st["se"], DECIMALS[metric]),
                                 st["n"]])
            for key, found in times.items():
                if c and (c.get(key) or {}).get("iqm") is not None:
                    found.append(c[key]["iqm"])
        row += [f"{np.mean(found):.{1 if key == 'planning_seconds' else 0}f}" if found else "n/a"
                for key, found in times.items()]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n", csv_rows


def _mean_table(means: dict, planners, title: str, higher_is_better: bool = True, views=TABLE_VIEWS,
                note: str = "", end: int | None = None) -> str:
    """Markdown of :func:`scene_means`: means, and margins over the baselines with scenes won
    (``note``: a sentence added to the caption; ``end``: the view count whose column is where
    a travel budget ends runs)."""
    n = max((r["scenes"] for r in means.values()), default=0)
    baselines = [b for b in BASELINES if any(f"vs_{b}@{v}" in r for r in means.values() for v in views)]
    named = {v: f"end ({v})" if v == end else str(v) for v in views}
    head = ["planner"] + [f"mean @{named[v]}" for v in views] + [f"vs {b} @{named[v]}" for b in baselines
                                                                 for v in views]
    better = "higher" if higher_is_better else "lower"
    intro = f"Mean over {n} scene{'' if n == 1 else 's'} of each cell's interquartile mean ({better} is better)"
    if baselines:
        intro += ("; 'vs B': the mean difference to planner B on each scene over the seeds both have, and "
                  "in brackets the scenes where the planner does better than B, of those compared")
    seeds = {c for r in means.values() for c in r["seeds"]}
    if len(seeds) > 1:
        intro += f"; the cells cover {min(seeds)} to {max(seeds)} seeds (a suite still running)"
    lines = [f"## {title}: mean over scenes", "", intro + "." + note, "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in planners:
        r = means[p]
        row = [p] + ["n/a" if r[f"mean@{v}"] is None else f"{r[f'mean@{v}']:.2f}" for v in views]
        for b in baselines:
            for v in views:
                key = f"vs_{b}@{v}"
                ok = r.get(key) is not None
                row.append(f"{r[key]:+.2f} ({r['wins_' + key]}/{r.get('compared_' + key, n)})" if ok else "-")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"
