"""A ceiling for planners that choose by viewing direction: picks made knowing the held-out views.

    python benchmarks/heldout_oracle.py bench/shared-full --out bench/heldout.json
    mitsuba-active bench benchmarks/suites/shared.toml --profile full --workers 2 \\
        --set "eval_views=[10,20]" --planners benchmarks/heldout_oracle.py:HeldOutKMedian \\
        --set 'planner_options.heldout="bench/heldout.json"' --out bench/oracle

The first command reads the finished runs of a suite folder (``bench --out``)
and writes, for each scene, its candidates' and held-out cameras' viewing
directions. ``HeldOutKMedian`` then picks, greedily, the candidate that most
lowers the mean angle from the held-out views to their nearest captured view:
what a planner could do on that measure if it knew where it will be judged. No
planner may know that; the suite measures how much a choice by direction can
gain at all.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from mitsuba_active.cameras import Camera
from mitsuba_active.errors import UserError
from mitsuba_active.planners import Planner, PlanningState, check_batch, unseen
from mitsuba_active.record import read_record


def forwards(cameras) -> np.ndarray:
    """(N, 3) unit viewing directions of ``cameras``."""
    return np.stack([c.forward for c in cameras])


def k_median_over(held: np.ndarray, cands: np.ndarray, captured: list, allowed: np.ndarray,
                  n: int) -> tuple[list, np.ndarray]:
    """``n`` greedy picks among ``cands`` (C, 3) unit directions where ``allowed``
    (C,) bool, each the one that most lowers the mean angle (radians) from
    ``held`` (H, 3) to its nearest of ``captured`` and the picks so far; and the
    first pick's (C,) scores, minus that mean angle after each candidate."""
    between = np.arccos(np.clip(held @ cands.T, -1.0, 1.0))  # (H, C)
    nearest = between[:, captured].min(axis=1) if captured else np.full(len(held), np.pi)
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


class HeldOutKMedian(Planner):
    """Greedy k-median over the held-out views' directions, read from ``heldout``
    (a JSON file this script writes): a ceiling, not a planner."""

    def __init__(self, heldout: str = ""):
        try:
            self.scenes = json.loads(Path(heldout).read_text())["scenes"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"heldout must name a file written by heldout_oracle.py ({exc})") from None
        self.heldout = str(heldout)

    def options(self) -> dict:
        return {"heldout": self.heldout}

    def select(self, state: PlanningState, batch: int):
        allowed = unseen(state)
        check_batch(allowed, batch)
        cands = forwards(state.candidates)
        # Scenes on one rig share their directions: any of them serves, if their held-out views agree.
        held = [np.asarray(scene["heldout"]) for scene in self.scenes
                if np.shape(scene["candidates"]) == cands.shape and np.allclose(scene["candidates"], cands, atol=1e-6)]
        if not held:
            raise UserError(f"{self.heldout} holds no scene with these {len(cands)} candidates")
        if any(h.shape != held[0].shape or not np.allclose(h, held[0], atol=1e-6) for h in held):
            raise UserError(f"{self.heldout} holds scenes with these candidates but other held-out views")
        return k_median_over(held[0], cands, list(state.captured), allowed, batch)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="a suite folder (bench --out)")
    ap.add_argument("--out", type=Path, required=True, help="the JSON file to write")
    args = ap.parse_args(argv)
    scenes = {}
    for path in sorted(args.folder.glob("runs/*/*/run.json")):
        try:
            rec = read_record(path)
        except UserError as exc:
            print(f"heldout_oracle.py: {exc}", file=sys.stderr)
            return 2
        scenes.setdefault(path.parts[-3], dict(
            name=path.parts[-3],
            candidates=forwards(Camera.from_dict(c) for c in rec["candidates"]).tolist(),
            heldout=forwards(Camera.from_dict(c) for c in rec["heldout"]).tolist()))
    if not scenes:
        print(f"heldout_oracle.py: no runs under {args.folder}", file=sys.stderr)
        return 2
    args.out.write_text(json.dumps(dict(folder=str(args.folder), scenes=list(scenes.values()))) + "\n")
    print(f"wrote {args.out}: {len(scenes)} scenes ({', '.join(scenes)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
