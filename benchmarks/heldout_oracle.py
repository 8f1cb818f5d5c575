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
# As a script, and as a planner file (see mitsuba_active.planners.base), this folder is on sys.path.
from view_angles import directions, k_median_over


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
        cands = directions(state.candidates)
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
            candidates=directions(Camera.from_dict(c) for c in rec["candidates"]).tolist(),
            heldout=directions(Camera.from_dict(c) for c in rec["heldout"]).tolist()))
    if not scenes:
        print(f"heldout_oracle.py: no runs under {args.folder}", file=sys.stderr)
        return 2
    args.out.write_text(json.dumps(dict(folder=str(args.folder), scenes=list(scenes.values()))) + "\n")
    print(f"wrote {args.out}: {len(scenes)} scenes ({', '.join(scenes)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
