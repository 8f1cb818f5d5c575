"""Wall time of one suite run by local worker processes and by Ray, and whether their tables agree.

    python benchmarks/bench_executors.py [--suite benchmarks/suites/shared.toml] [--planners random,even]
        [--workers 2] [--work bench-executors] [--out benchmarks/results/bench_executors.json]

Runs ``mitsuba-active bench SUITE --profile quick --executor ray`` and then
``--workers N`` (Ray: an instance of the command's own, one run per 1/N of the CPUs) into fresh
folders under ``--work``, each timed as a whole command (Ray's start and stop
included), and compares their ``results.json`` less the runs' times.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TIMES = ("wall_seconds", "planning_seconds")


def bench(suite: str, out: Path, planners: str, extra: list) -> float:
    cmd = [sys.executable, "-m", "mitsuba_active", "bench", suite, "--profile", "quick", "--planners", planners,
           "--out", str(out), "--quiet", *extra]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    return time.perf_counter() - t0


def tables(out: Path) -> dict:
    res = json.loads((out / "report" / "results.json").read_text())
    return {**res, "cells": [{k: v for k, v in c.items() if k not in TIMES} for c in res["cells"]]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default=str(ROOT / "benchmarks" / "suites" / "shared.toml"))
    ap.add_argument("--planners", default="random,even")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--work", default="bench-executors")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_executors.json"))
    args = ap.parse_args()
    work = Path(args.work)
    shutil.rmtree(work, ignore_errors=True)
    # Ray first: should the ground-truth cache be cold, Ray pays for it.
    ray = bench(args.suite, work / "ray", args.planners, ["--executor", "ray", "--cpus-per-run",
                                                            str((os.cpu_count() or 1) / args.workers)])
    local = bench(args.suite, work / "local", args.planners, ["--workers", str(args.workers)])
    a, b = tables(work / "local"), tables(work / "ray")
    result = {"suite": Path(args.suite).name, "profile": "quick", "planners": args.planners.split(","),
              "runs": a["runs"], "workers": args.workers, "cpus": os.cpu_count(),
              "local_seconds": round(local, 1), "ray_seconds": round(ray, 1),
              "ray_overhead_percent": round(100 * (ray - local) / local, 1),
              # The runs' own wall times, summed: what the machine's load alone changes.
              "run_seconds_sum": {k: round(sum(json.loads(p.read_text())["wall_seconds"]
                                               for p in (work / k).rglob("run.json")), 1) for k in ("local", "ray")},
              "same_tables": a == b}
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
