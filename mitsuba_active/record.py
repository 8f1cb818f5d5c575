"""A run's record: the format of run.json, and its reader, which checks every part.

A run keeps ``run.json`` current after every round: its settings
(``config``), the candidate and held-out cameras, the views captured, each
round's picks and scores, the metrics at each evaluated view count, and
what a resume needs (the planner's random state, the ensemble's file).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from .cameras import Camera
from .checks import is_number, is_whole
from .errors import UserError

RUN_FORMAT = 1

#: Name of the planner's ensemble file in a run folder, after the views it was trained on.
ENSEMBLE_FILE = re.compile(r"ensemble_\d{3,}\.npz")


#: The parts of a run record and their types (those before the line are in every record;
#: the others came later, or come with a round).
RECORD_PARTS = {"config": dict, "candidates": list, "heldout": list, "captured": list, "metrics": list,
                "finished": bool,
                # ---
                "rounds": list, "versions": dict, "rng_state": dict, "planner_options": dict, "distances": bool,
                "bbox": list, "budget_changes": list, "resumed_with": list, "ensemble_file": str,
                "candidate_files": list, "heldout_files": list, "travel": list, "stopped": dict,
                "added": list}
REQUIRED_PARTS = ("config", "candidates", "heldout", "captured", "metrics", "finished")


def read_record(path) -> dict:
    """The run record in ``path`` (run.json), its parts checked, so that a
    hand-edited or damaged record is refused in one line, not deep in a
    resume, a report or an export.

    Raises:
        UserError: "PATH is damaged (what is wrong)", or not a run record.
    """
    path = Path(path)
    try:
        rec = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as exc:  # not JSON, not text, or nested past Python's stack
        raise UserError(f"{path} is damaged ({exc})") from None
    if not isinstance(rec, dict) or not set(REQUIRED_PARTS) <= set(rec):
        raise UserError(f"{path} is not a run record")
    if rec.get("format", RUN_FORMAT) != RUN_FORMAT:
        raise UserError(f"{path} is a run record of format {rec['format']!r}, which this version of mitsuba-active "
                        f"does not read (it reads format {RUN_FORMAT})")

    def damaged(why: str) -> UserError:
        return UserError(f"{path} is damaged ({why})")

    for key, kind in RECORD_PARTS.items():
        if key in rec and not (isinstance(rec[key], kind) or (key == "ensemble_file" and rec[key] is None)):
            raise damaged(f"its {key} is {type(rec[key]).__name__}, not {kind.__name__}")
    for key in ("wall_seconds", "planning_seconds"):
        if key in rec and not (is_number(rec[key], finite=True) and rec[key] >= 0):
            raise damaged(f"its {key} is {rec[key]!r}, not a number of seconds")
    for key in ("candidates", "heldout"):
        try:
            for cam in rec[key]:
                Camera.from_dict(cam)
        except UserError as exc:
            raise damaged(f"one of its {key}: {exc}") from None
    for key, cams in (("candidate_files", "candidates"), ("heldout_files", "heldout")):
        files = rec.get(key)
        if files is not None and not (len(files) == len(rec[cams]) and all(isinstance(f, str) for f in files)):
            raise damaged(f"its {key} are not the file names of its {len(rec[cams])} {cams}")
    try:
        for added in rec.get("added", ()):
            Camera.from_dict(added["camera"])
    except (UserError, TypeError, KeyError) as exc:
        raise damaged(f"one of its added cameras: {exc}") from None
    n = len(run_cameras(rec))
    if not all(is_whole(i) and 0 <= i < n for i in rec["captured"]):
        raise damaged(f"its captured views are not indices of its {n} candidates")
    # Its views on disk are the captured ones in order: a list edited by hand would pair them with other poses.
    captured, budget = rec["captured"], rec["config"].get("budget")
    if rec["finished"] and is_whole(budget) and len(captured) != budget and not rec.get("stopped"):
        raise damaged(f"it is finished with {len(captured)} captured views, but its budget is {budget}")
    for r in rec.get("rounds", ()):
        views, picks = (r.get("views"), r.get("picks")) if isinstance(r, dict) else (None, None)
        if not (isinstance(picks, list) and is_whole(views) and len(picks) <= views <= len(captured)
                and captured[views - len(picks):views] == picks):
            raise damaged("its rounds did not pick the views it lists as captured")
    for m in rec["metrics"]:
        if not (isinstance(m, dict) and is_whole(m.get("views")) and is_number(m.get("psnr"))
                and all(m.get(k) is None or is_number(m[k])
                        for k in ("psnr_fg", "ssim", "distance_error", "floor_psnr", "floor_psnr_fg", "fit_psnr",
                                  "fit_start_psnr"))):
            raise damaged("an entry of its metrics is not the scores at a view count")
    counts = [m["views"] for m in rec["metrics"]]
    if counts != sorted(set(counts)) or not all(1 <= v <= len(captured) for v in counts):
        raise damaged(f"its metrics are at view counts {counts}, not once each at counts of its "
                      f"{len(captured)} captured views")
    if not all(isinstance(v, str) for v in rec.get("versions", {}).values()):
        raise damaged("its versions are not names of versions")
    ens_file = rec.get("ensemble_file")
    if ens_file is not None and not ENSEMBLE_FILE.fullmatch(ens_file):  # the run removes it when replaced
        raise damaged(f"its ensemble_file {ens_file!r} is not one of the run's ensemble_NNN.npz files")
    travel = rec.get("travel")
    # At least one entry per captured view: a run notes its travel before it lists the capture.
    if travel is not None and not (len(travel) >= len(captured) and all(
            isinstance(t, dict) and is_number(t.get("distance")) and is_number(t.get("time")) for t in travel)):
        raise damaged("its travel is not the distance and time so far at each captured view")
    bbox = rec.get("bbox")
    if bbox is not None and not (np.shape(bbox) == (2, 3) and all(is_number(v, finite=True)
                                                                   for corner in bbox for v in corner)):
        raise damaged(f"its bbox is {bbox!r}, not two corners of three numbers")
    return rec


def run_cameras(rec: dict) -> list[dict]:
    """The cameras a record's captured indices name: its candidates, then the cameras the run
    added (views along the way, continuous candidates), as ``to_dict()`` dicts."""
    return list(rec["candidates"]) + [a["camera"] for a in rec.get("added", ())]


def along_the_way_views(rec: dict) -> list[int]:
    """The view numbers (positions in ``captured``) of a record's views captured along the way."""
    base, added = len(rec["candidates"]), rec.get("added", ())
    return [n for n, i in enumerate(rec["captured"])
            if i >= base and added[i - base].get("kind") == ALONG_THE_WAY]


#: The ``kind`` of an added camera captured along a route, and of one a continuous round offered.
ALONG_THE_WAY, CONTINUOUS = "along the way", "continuous"


def json_default(o):
    """``json.dumps``' default for run.json: numpy numbers and arrays as Python's."""
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"cannot store {type(o).__name__} in run.json")
