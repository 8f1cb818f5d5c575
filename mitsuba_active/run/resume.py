"""Whether a run folder can be resumed: its record against the run that would go on from it.

:func:`resume_obstacles` is the one decision, which a run (as it starts)
and a suite (before any of its runs start) both ask; each words the refusal
for its own user. The other functions are its parts, and the reading of a
record to go on from.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

from ..checks import is_whole
from ..errors import FolderError, FolderInUse, UserError
from ..field.config import LEGACY_PRESET
from ..imageio_utils import new_entries, remove_new
from ..planners import make_planner
from ..planners.base import is_planner_file, planner_label
from ..record import json_default, read_record
from ..travel import TRAVEL_LEGACY, TRAVEL_SETTINGS


def resume_obstacles(rec: dict, current: dict, content_hash, planner_digest, cameras=None) -> dict:
    """What keeps a run from going on from the run record ``rec`` (a dict
    from :func:`read_resumable_record`), in the order a run checks them;
    empty when it can resume.

    Args:
        current: the run's settings, a config dict as run.json would hold them.
        content_hash: the digest of its scene or dataset as it is now (None: none).
        planner_digest: its planner's code now (see :func:`other_planner_code`).
        cameras: its candidate and held-out cameras as ``to_dict()`` lists, or
            None to leave them unchecked (a suite's jobs have opened no source).

    Returns:
        ``{"settings": lines of :func:`conflicting_settings`}``, ``"content": True``
        (a scene or dataset changed since), ``"cameras": True`` (other
        candidate or held-out cameras), ``"planner": True`` (other planner
        code that chose views), for those that apply. Scenes and datasets are
        compared by content where both have a digest, else by path.
    """
    by_content = rec.get("content_hash") is not None and content_hash is not None
    found: dict = {}
    changed = conflicting_settings(rec, current, compare_scene=not by_content)
    if changed:
        found["settings"] = changed
    if by_content and rec["content_hash"] != content_hash:
        found["content"] = True
    if cameras is not None and [rec.get("candidates"), rec.get("heldout")] != list(cameras):
        found["cameras"] = True
    if other_planner_code(rec, planner_digest):
        found["planner"] = True
    return found


def config_differences(recorded, current: dict, compare_scene: bool = True) -> list[str]:
    """The settings in which a run record's config (a dict from run.json)
    differs from ``current`` (a config dict, compared as run.json would hold
    it), as ``"name: recorded -> current"`` lines.

    Scene paths compare as resolved paths, so that a relative and an absolute
    path to one scene match. Callers that check the scene's content hash pass
    ``compare_scene=False``: the same scene may then be named by any path (a
    folder run from elsewhere, or moved). Planner files compare by their
    :func:`~mitsuba_active.planners.planner_label`, for the same reason:
    callers compare their content (:func:`~mitsuba_active.planners.base.planner_digest`).
    """
    return [f"{k}: {old!r} -> {new!r}" for k, (old, new) in config_changes(recorded, current, compare_scene).items()]


def config_changes(recorded, current: dict, compare_scene: bool = True) -> dict:
    """:func:`config_differences` as ``{name: (recorded value, current value)}``."""
    if not isinstance(recorded, dict):
        return {"config": ("missing", "present")}
    current_planner = current.get("planner")

    def normal(config):
        config = json.loads(json.dumps(config, default=json_default))  # tuples as lists, numpy as numbers
        if isinstance(config.get("eval_views"), list):  # the same counts in any order
            config["eval_views"] = sorted(set(config["eval_views"]))
        name = config.get("planner")
        if is_planner_file(name):
            config["planner"] = planner_label(name)
            if is_planner_file(current_planner) and config["planner"] == planner_label(current_planner):
                name = current_planner  # the file as it is now, not where the record found it
        # The fields a planner actually trains: none for even (any --ensemble
        # then is the same run), one for fisher.
        try:
            planner = make_planner(name, **dict(config.get("planner_options") or {}))
        except (UserError, TypeError, ValueError):  # not a record of this tool's planners
            planner = None
        if planner is not None:  # options as the planner resolves them: defaults given or not, alike
            resolved = {**dict(config.get("planner_options") or {}), **planner.options()}
            config["planner_options"] = json.loads(json.dumps(resolved, default=json_default))
        if planner is not None and is_whole(config.get("ensemble")):
            config["ensemble"] = planner.ensemble_size(config["ensemble"]) if planner.needs_ensemble else None
        config.setdefault("field_preset", LEGACY_PRESET)  # a record from before presets
        for name, (default, _) in TRAVEL_SETTINGS.items():  # a record from before travel ran as teleport
            config.setdefault(name, TRAVEL_LEGACY.get(name, default))
        if config["candidates_mode"] != "continuous":  # only continuous poses come nearer: any value is one run
            config.pop("nearest")
        scene = config.pop("scene", None)
        if compare_scene:
            config["scene"] = str(Path(scene).resolve()) if scene else scene
        return config

    old, new = normal(recorded), normal(current)
    keys = [k for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
    if "planner" in keys and None in (old.get("ensemble"), new.get("ensemble")) and "ensemble" in keys:
        keys.remove("ensemble")  # one of the planners trains no ensemble: the planner says it all
    if "planner" in keys and "planner_options" in keys:
        keys.remove("planner_options")  # each planner's own: the planner says it all
    return {k: (old.get(k), new.get(k)) for k in keys}


def read_resumable_record(path) -> dict:
    """:func:`read_record` of a run folder's record, for going on with the run:
    a damaged one's message says how to start over."""
    try:
        return read_record(path)
    except UserError as exc:
        raise UserError(f"{exc}; remove it to start over") from None


@contextlib.contextmanager
def undone_unless_resumable(out: Path):
    """Run the block that starts (or resumes) the run in folder ``out``; should
    it fail before the run has a record to resume from (run.json), undo what it
    added: nothing half-made is left behind (a folder that was there keeps what
    it held). A folder another run is writing (FolderInUse) is left alone."""
    new = new_entries(out)
    try:
        yield
    except FolderInUse:  # what is in the folder is the other run's
        raise
    except BaseException:
        if not (out / "run.json").is_file():
            remove_new(out, *new)
        raise


def other_settings(folder, changed: list[str], advice: str) -> FolderError:
    """The error refusing ``folder``, whose run has other settings (``changed``,
    from :func:`config_differences`; the first three are named)."""
    more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
    return FolderError(folder, f"holds a run with other settings ({'; '.join(changed[:3])}{more}); {advice}")


def conflicting_settings(rec: dict, current: dict, compare_scene: bool = True) -> list[str]:
    """The settings in which a run record (a dict from run.json) differs from
    ``current`` (:func:`config_differences`), less a budget the run can go on
    to: one at least as large as the views it has captured. A finished run
    thus takes a larger budget (it is extended), an unfinished one any budget
    it has not passed."""
    changes = config_changes(rec.get("config"), current, compare_scene)
    captured, budget = rec.get("captured"), current.get("budget")
    lines = []
    for k, (old, new) in changes.items():
        line = f"{k}: {old!r} -> {new!r}"
        if k == "budget" and isinstance(captured, list) and is_whole(budget):
            if budget >= len(captured):
                continue
            line += f": fewer than the {len(captured)} views it has captured"
        lines.append(line)
    return lines


def ends_short_of_a_batch(captured: int, initial_views: int, batch: int) -> bool:
    """Whether a run that has ``captured`` views ended with a round of fewer than
    ``batch`` views (its budget cut the round short): taken on to a larger budget,
    its rounds then differ from those of a run made with that budget from the start."""
    return bool((captured - min(initial_views, captured)) % batch)


def other_planner_code(rec: dict, digest) -> bool:
    """Whether a run record was made with other code of its planner (``digest``:
    the code's now, see :func:`~mitsuba_active.planners.base.planner_digest`)
    *and* that planner chose views in it. A run that stopped before its planner
    chose a view (a planner being fixed) holds nothing of its work: it starts over."""
    return rec.get("planner_digest") != digest and bool(rec.get("rounds"))


def same_config(recorded, current: dict, compare_scene: bool = True) -> bool:
    """Whether a run record's config has the settings of ``current`` (see :func:`config_differences`)."""
    return not config_differences(recorded, current, compare_scene)
