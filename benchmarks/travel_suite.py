"""Travel suite: cost-aware against cost-blind planning under a travel budget, and continuous candidates.

Runs scenes of a bench suite (``benchmarks/suites/shared.toml``) with a drone
under the bench profile's settings (``--profile full``: 100 candidates,
20 held-out views), at ``--resolution`` (64 px, where its figures were
measured), in these configurations:

* ``rfe``: RFE, cost-blind, under a travel budget of ``--diameters`` scene
  diameters (the scene's bounding-box diagonal, as the travel cost uses);
* ``rfe-cost``: the same with ``--cost-weight`` (λ);
* ``even``: ``even`` under the same budget, one view a round;
* ``even-tour``: ``even`` drawing all its views at once (a batch of
  ``--max-views``) and visiting them in a short tour, nearest first: the
  cost-aware form of a planner that has no scores to weigh;
* ``rfe-cost-continuous``: ``rfe-cost`` with continuous candidates;
* ``rfe-pool``: RFE on the pool of candidates, ``--views`` views, no travel budget;
* ``rfe-continuous``: the same with continuous candidates.

The travel configurations run up to ``--max-views`` views, more than their
budget lets most of them capture, so that the travel budget ends most runs
(``stopped`` says which; a run whose short tours stay inside it stops at
``--max-views``); each is scored at its last view (a run evaluates there), as
``bench`` scores ``@end``. The others are scored at
``--views``. Each run is a bench job (its folder under ``--runs``,
``CONFIG/runs/SCENE/PLANNER-seedN``): a finished run is kept and read again.

Prints the per-scene, per-seed table, the means over scenes and seeds, the
paired differences (cost-aware less cost-blind, less ``even``; continuous
less pool) and writes them to ``--out`` as JSON. ``--keep FILE`` joins an
earlier ``--out``'s scores of the runs this call does not make.

Usage::

    PYTHONPATH=. python benchmarks/travel_suite.py --scenes spot,bunny,dragon --seeds 0,1,2
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mitsuba_active  # noqa: E402,F401  (first: it finds LLVM before Dr.Jit loads)
import mitsuba as mi  # noqa: E402

from mitsuba_active.bench.jobs import finished_record, plan_jobs, run_job  # noqa: E402
from mitsuba_active.bench.stats import metric_at  # noqa: E402
from mitsuba_active.bench.suite import load_suite  # noqa: E402
from mitsuba_active.scene import load_scene  # noqa: E402
from mitsuba_active.travel import diameter_of  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TRAVEL_CONFIGS = ("rfe", "rfe-cost", "even", "even-tour", "rfe-cost-continuous")
VIEW_CONFIGS = ("rfe-pool", "rfe-continuous")
CONFIGS = TRAVEL_CONFIGS + VIEW_CONFIGS
METRICS = ("psnr", "psnr_fg")


def config_overrides(name: str, args, travel_budget: float) -> tuple[str, dict]:
    """The planner and the run settings of configuration ``name``."""
    common = {"embodiment": "drone", "eval_views": sorted({10, args.views}), "resolution": args.resolution}
    if name in TRAVEL_CONFIGS:
        settings = {**common, "budget": args.max_views, "travel_budget": round(travel_budget, 6),
                    "cost_weight": args.cost_weight if name.startswith("rfe-cost") else 0.0}
        if name == "rfe-cost-continuous":
            settings["candidates_mode"] = "continuous"
        if name == "even-tour":
            settings["batch"] = args.max_views
        return ("even" if name.startswith("even") else "rfe"), settings
    mode = "continuous" if name == "rfe-continuous" else "pool"
    return "rfe", {**common, "budget": args.views, "candidates_mode": mode}


def scene_diameter(suite, runs: Path, scene: str, profile: str) -> float:
    """The scene's diameter (scene units) as a run sees it: authored as the suite authors it."""
    job = plan_jobs(suite, runs / "_scenes", profile, seeds=[0], planners=["even"], scenes=[scene])[0]
    sc = load_scene(job.scene_xml)
    return diameter_of(sc.bbox_min, sc.bbox_max)


def score(rec: dict, name: str, views: int) -> dict:
    """A finished run's scores: at the end of its travel budget, or at ``views``."""
    travel = name in TRAVEL_CONFIGS
    count = views
    if travel:
        stopped = rec.get("stopped") or {}
        count = stopped.get("views", len(rec["captured"]))
    out = {m: metric_at(rec, m, count) for m in METRICS}
    out.update({f"{m}@10": metric_at(rec, m, 10) for m in METRICS})  # at equal views: the picks alone
    legs = rec.get("travel") or []
    out["views"] = count
    out["travel"] = legs[count - 1]["distance"] if len(legs) >= count else None
    out["stopped"] = bool(rec.get("stopped"))
    out["planning_seconds"] = rec.get("planning_seconds")
    out["wall_seconds"] = rec.get("wall_seconds")
    return out


def fmt(value, decimals: int = 2) -> str:
    """``value`` to ``decimals``, or "-" where a run has none (one stopped short of the view count)."""
    return "-" if value is None else f"{value:.{decimals}f}"


def mean(values):
    vals = [v for v in values if v is not None]
    return round(statistics.fmean(vals), 4) if vals else None


def median(values):
    vals = [v for v in values if v is not None]
    return round(statistics.median(vals), 4) if vals else None


def paired(results: dict, a: str, b: str, metric: str) -> dict:
    """``a`` less ``b`` in ``metric``, paired by scene and seed: mean, median, wins of ``a``, pairs."""
    diffs = [results[key][a][metric] - results[key][b][metric] for key in results
             if a in results[key] and b in results[key]
             and results[key][a][metric] is not None and results[key][b][metric] is not None]
    return {"mean": mean(diffs), "median": median(diffs), "wins": sum(d > 0 for d in diffs), "n": len(diffs)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--suite", default=str(ROOT / "benchmarks/suites/shared.toml"))
    ap.add_argument("--profile", default="full")
    ap.add_argument("--resolution", type=int, default=64, help="image width and height (pixels)")
    ap.add_argument("--scenes", default="spot,bunny,dragon")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--diameters", type=float, default=20.0, help="travel budget in scene diameters")
    ap.add_argument("--cost-weight", type=float, default=1.0,
                    help="λ of rfe-cost (1: ahead of 0.5 and of even-tour on the mean of 14 runs)")
    ap.add_argument("--max-views", type=int, default=40, help="view budget of the travel configurations")
    ap.add_argument("--views", type=int, default=20, help="view budget of rfe-pool and rfe-continuous")
    ap.add_argument("--runs", default=str(ROOT / "bench/travel_suite"), help="run folders")
    ap.add_argument("--out", default=str(ROOT / "benchmarks/results/travel_suite.json"))
    ap.add_argument("--report-only", action="store_true", help="read the finished runs, run nothing")
    ap.add_argument("--keep", help="an earlier --out whose scores join this call's, for the configurations, "
                                   "scenes and seeds that this call does not run")
    args = ap.parse_args()
    suite = load_suite(args.suite)
    runs = Path(args.runs)
    scenes, seeds = args.scenes.split(","), [int(s) for s in args.seeds.split(",")]
    configs = [c for c in args.configs.split(",") if c]
    unknown = set(configs) - set(CONFIGS)
    if unknown:
        sys.exit(f"unknown configurations {sorted(unknown)}; choose from {', '.join(CONFIGS)}")
    results, diameters, seconds = {}, {}, {}
    for scene in scenes:
        diameters[scene] = scene_diameter(suite, runs, scene, args.profile)
        budget = args.diameters * diameters[scene]
        for seed in seeds:
            for name in configs:
                planner, settings = config_overrides(name, args, budget)
                job = plan_jobs(suite, runs / name, args.profile, seeds=[seed], planners=[planner],
                                scenes=[scene], overrides=settings)[0]
                if finished_record(job) is None and not args.report_only:
                    t0 = time.perf_counter()
                    run_job(job)
                    seconds[f"{scene}/{seed}/{name}"] = round(time.perf_counter() - t0, 1)
                    print(f"{scene} seed {seed} {name}: {seconds[f'{scene}/{seed}/{name}']} s", flush=True)
                rec = finished_record(job)
                if rec is not None:
                    results.setdefault(f"{scene}/{seed}", {})[name] = score(rec, name, args.views)
    earlier = json.loads(Path(args.keep).read_text()) if args.keep else {}
    if earlier:  # the earlier scores first, in their order; this call's replace theirs
        kept = earlier["runs"]
        results = {key: {**kept.get(key, {}), **results.get(key, {})} for key in {**kept, **results}}
        diameters = {**earlier.get("scene_diameters", {}), **diameters}
        configs = [c for c in CONFIGS if any(c in row for row in results.values())]
    lines = [f"| scene/seed | {' | '.join(configs)} |", "|---" * (len(configs) + 1) + "|"]
    for key, row in results.items():
        cells = []
        for name in configs:
            r = row.get(name)
            cells.append("-" if r is None else
                         f"{fmt(r['psnr'])} / {fmt(r['psnr_fg'])} ({r['views']} v, {fmt(r['travel'], 1)} u)")
        lines.append(f"| {key} | {' | '.join(cells)} |")
    means = {name: {m: mean([row[name][m] for row in results.values() if name in row])
                    for m in (*METRICS, "views", "travel")} for name in configs}
    cells = [f"{fmt(means[n]['psnr'])} / {fmt(means[n]['psnr_fg'])} ({fmt(means[n]['views'], 1)} v, "
             f"{fmt(means[n]['travel'], 1)} u)" for n in configs]
    lines.append(f"| mean | {' | '.join(cells)} |")
    comparisons = {}
    for a, b in (("rfe-cost", "rfe"), ("rfe-cost", "even"), ("rfe-cost", "even-tour"), ("rfe", "even"),
                 ("rfe-cost-continuous", "rfe-cost"),
                 ("rfe-continuous", "rfe-pool")):
        if any(a in row and b in row for row in results.values()):
            comparisons[f"{a} - {b}"] = {m: paired(results, a, b, m) for m in (*METRICS, "psnr@10", "views")}
    print("\nheld-out PSNR / foreground PSNR (dB) (views, travel in scene units); travel configurations at the "
          f"end of a {args.diameters:g}-diameter budget, the others at {args.views} views")
    print("\n".join(lines))
    for k, v in comparisons.items():
        print(f"{k}: " + "; ".join(f"{m} mean {d['mean']} median {d['median']} wins {d['wins']}/{d['n']}"
                                   for m, d in v.items()))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    out = {
        "command": "python " + " ".join(sys.argv), "profile": args.profile, "embodiment": "drone",
        "diameters": args.diameters, "cost_weight": args.cost_weight, "max_views": args.max_views,
        "views": args.views, "scene_diameters": diameters, "runs": results, "means": means,
        "comparisons": comparisons, "seconds": seconds,
        "machine": platform.machine(), "cpus": os.cpu_count(), "variant": mi.variant()}
    # What only the earlier file has (a sweep's figures) stays in it.
    out.update({k: v for k, v in earlier.items() if k not in out})
    Path(args.out).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
