"""Planning cost per round: each planner's ``select()`` on one state, in turns.

    python benchmarks/planner_cost.py [--planners rfe,hybrid,hybrid:lookahead=1] [--views 10]
        [--budget 20] [--repeats 7] [--out benchmarks/results/planner_cost.json]

The state is a round on the bundled scene, with the bench's ``full``
profile's planning settings: 100 candidates at 64x64, 256 sparse rays
each, an ensemble of K=2 trained as a run trains it (200 steps plus 50 for
each of the first 2 views, then 50 a view) on ``--views`` evenly spread
views; the planners are told the run's ``--budget`` (the profile's 20), as
a run tells them. The planners' calls take turns, so load from other
processes hits all alike. Prints and writes JSON with each
planner's median ``select()`` seconds, the median of a round's 50 training
steps, and each planner's round (training plus ``select()``) as a multiple of
the first planner's.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

import mitsuba_active  # noqa: F401
from mitsuba_active.checks import setting_value
from mitsuba_active.env import SceneSource
from mitsuba_active.planners import PlanningState, make_planner
from mitsuba_active.run import RunConfig, make_ensemble, sparse_candidate_rays, train_on
from mitsuba_active.scenes import BUNDLED_SCENE
from mitsuba_active.training import acquisition_steps


def planner_spec(text: str):
    """``NAME`` or ``NAME:OPTION=VALUE+OPTION=VALUE`` -> (name, options), the
    values read as ``--planner-option`` reads them."""
    name, _, rest = text.partition(":")
    options = {}
    for item in filter(None, rest.split("+")):
        key, _, value = item.partition("=")
        options[key] = setting_value(value)
    return name, options


def train_as_a_run(ens, src, captured: list, steps_per_view: int = RunConfig.steps_per_view):
    """Train ``ens`` as a run with two initial views trains its ensemble
    (:func:`~mitsuba_active.training.acquisition_steps`) on the ``captured``
    candidate views, one view a round."""
    first = RunConfig.initial_views
    train_on(ens, [src.candidate_view(i) for i in captured[:first]],
             acquisition_steps(0, first, RunConfig.initial_steps, steps_per_view))
    for n in range(first + 1, len(captured) + 1):
        train_on(ens, [src.candidate_view(j) for j in captured[:n]],
                 acquisition_steps(n - 1, 1, RunConfig.initial_steps, steps_per_view))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--planners", default="rfe,hybrid,hybrid:lookahead=1",
                    help="comma-separated; options after a colon, joined by '+'")
    ap.add_argument("--views", type=int, default=10, help="views the ensemble has been trained on")
    ap.add_argument("--budget", type=int, default=20, help="the run's budget that planners are told")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default="benchmarks/results/planner_cost.json")
    args = ap.parse_args()

    src = SceneSource.from_xml(BUNDLED_SCENE, n_candidates=100, n_heldout=4, resolution=64, spp=16)
    ens = make_ensemble(src, RunConfig(), 2, seed=0)
    captured = [int(i) for i in np.linspace(0, 99, args.views).round()]
    train_as_a_run(ens, src, captured)
    state = PlanningState(src.candidates, captured, ens, sparse_candidate_rays(src.candidates, 256, 0),
                          np.random.default_rng(0), budget=args.budget)
    planners = {}
    for text in args.planners.split(","):
        name, options = planner_spec(text)
        planners[text] = make_planner(name, **options)
    for planner in planners.values():
        planner.select(state, 1)  # compile
    times = {text: [] for text in planners}
    training = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        ens.train(50)
        training.append(time.perf_counter() - t0)
        for text, planner in planners.items():
            t0 = time.perf_counter()
            planner.select(state, 1)
            times[text].append(time.perf_counter() - t0)
    train_s = statistics.median(training)
    first = next(iter(planners))
    result = {"scene": "bundled", "candidates": 100, "rays_per_candidate": 256, "ensemble": 2,
              "views": args.views, "budget": args.budget, "repeats": args.repeats,
              "training_50_steps_seconds": train_s,
              "planners": {}}
    base = statistics.median(times[first])
    for text, ts in times.items():
        med = statistics.median(ts)
        result["planners"][text] = {"select_seconds": ts, "median_select_seconds": med,
                                    "select_over_first": med / base,
                                    "round_over_first": (train_s + med) / (train_s + base)}
        print(f"{text:>24}: select median {med:.3f} s ({med / base:.2f}x {first}); "
              f"round with 50 training steps {(train_s + med) / (train_s + base):.2f}x")
    print(f"50 training steps: median {train_s:.3f} s")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
