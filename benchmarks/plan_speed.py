"""Speed of the planning loop: the README's main job, and candidate scoring.

    python benchmarks/plan_speed.py [--repeats 3] [--skip-main-job] [--out benchmarks/results/plan_speed.json]

Prints and writes JSON with
- the wall time of ``mitsuba-active plan`` with its defaults (RFE, K=2, 20 views, 64x64)
  on the bundled scene (ground truth cached after the first repeat; the first is reported too);
- the time to score 100 candidates with 256 rays each at K=4 (RFE variance), median of repeats.
"""

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import mitsuba_active  # noqa: F401
from mitsuba_active.env import SceneSource
from mitsuba_active.planners import PlanningState, make_planner
from mitsuba_active.run import RunConfig, make_ensemble, sparse_candidate_rays, train_on
from mitsuba_active.scenes import BUNDLED_SCENE


def time_scoring(repeats: int) -> dict:
    src = SceneSource.from_xml(BUNDLED_SCENE, n_candidates=100, n_heldout=4, resolution=64, spp=16)
    ens = make_ensemble(src, RunConfig(), 4, seed=0)
    views = [src.candidate_view(i) for i in range(0, 100, 20)]
    train_on(ens, views, 50)
    state = PlanningState(src.candidates, [0, 20, 40, 60, 80], ens, sparse_candidate_rays(src.candidates, 256, 0),
                          np.random.default_rng(0))
    planner = make_planner("rfe")
    planner.select(state, 1)  # compile
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        planner.select(state, 1)
        times.append(time.perf_counter() - t0)
    return {"candidates": 100, "rays_per_candidate": 256, "ensemble": 4, "seconds": times,
            "median_seconds": statistics.median(times)}


def time_main_job(repeats: int) -> dict:
    times = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "mitsuba_active", "plan", "--quiet", "--out", f"{tmp}/run"],
                           check=True, stdout=subprocess.DEVNULL)
            times.append(time.perf_counter() - t0)
            metrics = json.loads(Path(f"{tmp}/run/run.json").read_text())["metrics"]
    return {"command": "mitsuba-active plan (defaults: rfe, K=2, 20 views, 64x64, bundled scene)",
            "seconds": times, "median_seconds": statistics.median(times), "first_seconds": times[0],
            "metrics": metrics}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--skip-main-job", action="store_true")
    ap.add_argument("--out", default="benchmarks/results/plan_speed.json")
    args = ap.parse_args()
    result = {"scoring": time_scoring(max(args.repeats, 5))}
    print(f"scoring 100 candidates x 256 rays at K=4: median {result['scoring']['median_seconds']:.3f} s")
    if not args.skip_main_job:
        result["main_job"] = time_main_job(args.repeats)
        mj = result["main_job"]
        print(f"main job: median {mj['median_seconds']:.1f} s over {args.repeats} runs (first {mj['first_seconds']:.1f} s)")
        print("  PSNR by views: " + ", ".join(f"{m['views']}: {m['psnr']:.2f} dB" for m in mj["metrics"]))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
