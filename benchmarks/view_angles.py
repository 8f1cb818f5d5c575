"""How near the held-out views lie to a captured view, per planner.

    python benchmarks/view_angles.py bench/shared-full [bench/other ...] [--views 10 20]
        [--exclude cbox,mic] [--out benchmarks/results/view_angles.json]

Reads every finished run of the suite folders (``runs/SCENE/PLANNER-seedS/run.json``)
and gives, at each view count, the mean over held-out views of the angle (degrees)
between a held-out camera's viewing direction and the nearest captured camera's,
averaged over the scenes and seeds that every planner ran, and the largest gap:
the largest such angle from any candidate's direction (the radius within which
the captured directions cover the candidates'; ``coverage`` makes it small). Beside the planners'
own picks it scores two made from viewing directions alone, from the same initial
views, candidates and held-out views of each scene and seed: ``farthest``
(``coverage``'s rule, the direction farthest from every captured one) and
``k-median`` (each pick the candidate that most lowers the mean angle from every
candidate to its nearest captured view). They show what a choice by viewing
direction alone can reach on this measure.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from mitsuba_active.cameras import Camera
from mitsuba_active.errors import UserError
from mitsuba_active.planners import PlanningState, make_planner
from mitsuba_active.record import read_record


def directions(cameras) -> np.ndarray:
    """(N, 3) unit viewing directions of cameras."""
    return np.stack([c.forward for c in cameras])


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) angles in radians between unit directions."""
    return np.arccos(np.clip(a @ b.T, -1.0, 1.0))


def mean_nearest(heldout: np.ndarray, taken: np.ndarray) -> float:
    """Mean angle (degrees) from each held-out direction to its nearest taken one."""
    return float(np.degrees(angles(heldout, taken).min(axis=1)).mean())


def largest_gap(cands: np.ndarray, taken: np.ndarray) -> float:
    """Largest angle (degrees) from a candidate direction to its nearest taken one."""
    return float(np.degrees(angles(cands, taken).min(axis=1)).max())


def farthest_picks(cameras: list, initial: list, n: int) -> list:
    """``coverage``'s picks among ``cameras`` after ``initial``, to ``n`` in all."""
    state = PlanningState(cameras, list(initial))
    return list(initial) + make_planner("coverage").select(state, n - len(initial))[0]


def k_median_over(clients: np.ndarray, cands: np.ndarray, captured: list, allowed: np.ndarray,
                  n: int) -> tuple[list, np.ndarray]:
    """``n`` greedy picks among ``cands`` (C, 3) unit directions where ``allowed``
    (C,) bool, each the one that most lowers the mean angle (radians) from
    ``clients`` (M, 3) to their nearest of ``captured`` and the picks so far; and
    the first pick's (C,) scores, minus that mean angle after each candidate."""
    between = angles(clients, cands)  # (M, C)
    nearest = between[:, captured].min(axis=1) if captured else np.full(len(clients), np.pi)
    allowed, picks, first = allowed.copy(), [], None
    for _ in range(n):
        scores = -np.minimum(nearest[:, None], between).mean(axis=0)
        scores[~allowed] = -np.inf
        first = scores if first is None else first
        k = int(np.argmax(scores))
        picks.append(k)
        allowed[k] = False
        nearest = np.minimum(nearest, between[:, k])
    return picks, first


def k_median_picks(cands: np.ndarray, initial: list, n: int) -> list:
    """Greedy k-median picks after ``initial``: each lowers the candidates' mean
    angle to their nearest pick the most."""
    allowed = np.ones(len(cands), bool)
    allowed[list(initial)] = False
    return list(initial) + k_median_over(cands, cands, list(initial), allowed, n - len(initial))[0]


#: The figures of a run's picks, by their JSON key: the printed title, and the figure of
#: the held-out and candidate directions and those taken.
MEASURES = {
    "mean_degrees": ("mean angle (degrees) from a held-out view to the nearest captured view",
                     lambda held, cands, taken: mean_nearest(held, taken)),
    "largest_gap_degrees": ("largest angle (degrees) from a candidate's direction to the nearest captured view",
                            lambda held, cands, taken: largest_gap(cands, taken)),
}


def measures(held: np.ndarray, cands: np.ndarray, picks: list, views: list) -> dict:
    """Each of :data:`MEASURES` of the first ``v`` of ``picks`` (indices into ``cands``), for every ``v`` of ``views``."""
    return {key: [figure(held, cands, cands[picks[:v]]) for v in views] for key, (_, figure) in MEASURES.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", type=Path, help="suite folders (bench --out)")
    ap.add_argument("--views", type=int, nargs="+", default=[10, 20])
    ap.add_argument("--exclude", default="", help="comma-separated scenes to leave out")
    ap.add_argument("--out", type=Path, default=None, help="also write the figures as JSON")
    args = ap.parse_args(argv)
    excluded = set(filter(None, args.exclude.split(",")))
    runs = sorted((folder, p) for folder in args.folders for p in folder.glob("runs/*/*/run.json")
                  if p.parts[-3] not in excluded)
    if not runs:
        print(f"view_angles.py: no runs under {', '.join(map(str, args.folders))}", file=sys.stderr)
        return 2
    top = max(args.views)
    per_planner, simulated = {}, {}
    for folder, path in runs:
        try:
            rec = read_record(path)
        except UserError as exc:
            print(f"view_angles.py: {exc}", file=sys.stderr)
            return 2
        planner, _, seed = path.parts[-2].rpartition("-seed")
        if len(args.folders) > 1:  # the same planner with other settings in another folder
            planner = f"{folder.name}: {planner}"
        if not rec["finished"] or len(rec["captured"]) < top:
            continue
        cameras = [Camera.from_dict(c) for c in rec["candidates"]]
        cands, held = directions(cameras), directions(Camera.from_dict(c) for c in rec["heldout"])
        captured, key = rec["captured"], (path.parts[-3], seed)
        per_planner.setdefault(planner, {})[key] = measures(held, cands, captured, args.views)
        if key not in simulated:
            initial = captured[:rec["config"]["initial_views"]]
            simulated[key] = {name: measures(held, cands, picks, args.views)
                              for name, picks in (("farthest", farthest_picks(cameras, initial, top)),
                                                  ("k-median", k_median_picks(cands, initial, top)))}
    for name in ("farthest", "k-median"):
        per_planner[name] = {key: rows[name] for key, rows in simulated.items()}
    # Every row over the scenes and seeds that every planner ran.
    common = sorted(set.intersection(*(set(rows) for rows in per_planner.values())))
    if not common:
        print(f"view_angles.py: no scene and seed with a finished run of every planner "
              f"of at least {top} views", file=sys.stderr)
        return 2
    table = {name: dict(runs=len(common),
                        **{measure: {str(v): float(np.mean([rows[key][measure][i] for key in common]))
                                     for i, v in enumerate(args.views)} for measure in MEASURES})
             for name, rows in per_planner.items()}
    for measure, (title, _) in MEASURES.items():
        print(title)
        print(f"{'picks':<32}{'runs':>6}" + "".join(f"{'@' + str(v):>9}" for v in args.views))
        for name, row in table.items():
            print(f"{name:<32}{row['runs']:>6}" + "".join(f"{row[measure][str(v)]:>9.2f}" for v in args.views))
    if args.out:
        args.out.write_text(json.dumps(dict(folders=[str(f) for f in args.folders], excluded=sorted(excluded),
                                            views=args.views, picks=table), indent=1) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
