"""How well the planner's ensemble's disagreement tracks its error, candidate by candidate.

    python benchmarks/disagreement.py [--views 10] [--steps-per-view 50 200] [--members 2]
        [--out benchmarks/results/disagreement.json]

On the bundled scene (100 candidates at 64x64), the ensemble is trained as a
run trains it (200 steps plus ``--steps-per-view`` for each of 2 initial
views, then ``--steps-per-view`` after each further view) on ``--views``
views picked farthest-point (``coverage``'s rule). For every candidate not
captured it renders the whole image and takes

- ``disagreement``: the members' colour variance summed over its pixels (RFE's
  score, on every ray instead of a sparse set);
- ``error``: the squared error of the members' mean colour against the ground
  truth, summed over its pixels;
- ``angle``: degrees to the nearest captured viewing direction.

It prints the Spearman rank correlations between them, one line per
``--steps-per-view``, and writes them as JSON. A disagreement that ranks the
candidates as their error does is what RFE needs.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

import mitsuba_active  # noqa: F401
from mitsuba_active.cameras import camera_rays
from mitsuba_active.env import SceneSource
from mitsuba_active.run import RunConfig, make_ensemble
from mitsuba_active.scenes import BUNDLED_SCENE

from planner_cost import train_as_a_run
from view_angles import angles, directions, farthest_picks


def measure(src, n_views: int, steps_per_view: int, members: int, seed: int) -> dict:
    """Spearman correlations of disagreement, error and angle over the uncaptured candidates."""
    dirs = directions(src.candidates)
    captured = farthest_picks(src.candidates, [0, len(dirs) // 2], n_views)
    ens = make_ensemble(src, RunConfig(), members, seed=seed)
    train_as_a_run(ens, src, captured, steps_per_view)
    others = [i for i in range(len(dirs)) if i not in captured]
    disagreement, error = [], []
    for i in others:
        o, d = camera_rays(src.candidates[i])
        pred = ens.predict(o.reshape(-1, 3), d.reshape(-1, 3))
        truth = src.candidate_view(i).rgb.reshape(-1, 3)
        disagreement.append(float(pred["rgb_var"].sum()))
        error.append(float(((pred["rgb_mean"] - truth) ** 2).sum()))
    angle = np.degrees(angles(dirs[others], dirs[captured]).min(axis=1))
    return {"steps_per_view": steps_per_view, "disagreement_error": rank_correlation(disagreement, error),
            "disagreement_angle": rank_correlation(disagreement, angle), "error_angle": rank_correlation(error, angle)}


def rank_correlation(a, b) -> float:
    """Spearman's rank correlation of two sequences of numbers."""
    return float(spearmanr(a, b)[0])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=10, help="views captured (at least 3)")
    ap.add_argument("--steps-per-view", type=int, nargs="+", default=[50, 200])
    ap.add_argument("--members", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="benchmarks/results/disagreement.json")
    args = ap.parse_args()
    if args.views < 3 or args.members < 2 or min(args.steps_per_view) < 1:
        ap.error("needs --views >= 3, --members >= 2 and --steps-per-view >= 1")
    src = SceneSource.from_xml(BUNDLED_SCENE, n_candidates=100, n_heldout=4, resolution=64, spp=16)
    rows = []
    for steps in args.steps_per_view:
        row = measure(src, args.views, steps, args.members, args.seed)
        rows.append(row)
        print(f"{steps:>5} steps a view: Spearman disagreement~error {row['disagreement_error']:+.2f}, "
              f"disagreement~angle {row['disagreement_angle']:+.2f}, error~angle {row['error_angle']:+.2f}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"scene": "bundled", "views": args.views, "members": args.members,
                                         "seed": args.seed, "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
