"""A benchmark suite: its TOML file parsed and checked, and the settings ``--set`` adds.

A suite is a TOML file (see ``benchmarks/suites/shared.toml``)::

    name = "mine"
    planners = ["random", "even", "rfe", "my_planners.py:MyPlanner",   # a file beside the suite
                { name = "rfe-log", planner = "rfe", options = { form = "log" } }]   # a variant
    [defaults]              # RunConfig fields for every scene
    candidates = 100
    [[scenes]]
    name = "spot"
    mesh = "meshes/spot.obj"   # authored with scene_from_mesh (options: up, color, sun, floor, texture, look, ...;
                               # files relative to the suite; an xml scene takes none)
    [[scenes]]
    name = "room"
    xml = "room.xml"           # any Mitsuba scene
    rig = "interior"           # per-scene RunConfig overrides
    [[scenes]]
    name = "mic"
    dataset = "nerf_synthetic_mic"   # captured frames: a transforms .json or a folder holding one,
                                     # run as `plan` runs a dataset (its own test split held out)

A dataset's cameras and images are as they were captured: the rendered
scenes' settings ``rig``, ``fov`` and ``spp`` (of the profile, ``[defaults]``
or ``--set``) do not apply to it, and its own table may not set them; its
images shrink to ``resolution`` (or by ``downscale``).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path

from ..checks import not_a_file, setting_value
from ..errors import UserError
from ..imageio_utils import folder_name
from ..planners.base import planner_class, planner_label, resolve_reference
from ..run import RunConfig
from ..scene import SceneOptions

SCENE_OPTIONS = ("up", "color", "sun", "floor", "point_lights", "env_radiance", "texture", "two_sided", "look")
#: What a suite's scene is made from: the key that names its file or folder.
SCENE_KINDS = ("mesh", "xml", "dataset")
#: RunConfig fields of rendered scenes: a dataset's cameras and images are as they were captured.
RENDER_KEYS = ("rig", "fov", "spp")
#: The report's folder of plots over all scenes, beside each scene's (no scene may be named so).
SUMMARY = "summary"
#: RunConfig fields that each job sets itself (from the suite and --seeds).
JOB_KEYS = ("scene", "planner", "seed")
#: RunConfig fields that are tables: settings merge into them key by key.
TABLE_KEYS = ("field", "planner_options")


@dataclass
class SuiteScene:
    name: str
    path: Path  # mesh, XML, or a dataset's transforms .json or folder
    kind: str  # one of SCENE_KINDS
    scene_options: dict = field(default_factory=dict)
    run_options: dict = field(default_factory=dict)


def _setting_names() -> set[str]:
    """The RunConfig fields a suite or ``--set`` may set: the suite's scenes,
    planners and the seeds name each run, and are not settings."""
    return {f.name for f in fields(RunConfig)} - set(JOB_KEYS)


def _check_tables(path, where: str, settings: dict) -> None:
    for key in TABLE_KEYS:
        if not isinstance(settings.get(key, {}), dict):
            raise UserError(f"{path}: {where}: '{key}' must be a table, e.g. {key} = {{ lr = 0.01 }}")


@dataclass
class SuitePlanner:
    """A planner of a suite: its name in the tables and run folders, the
    planner it runs (a registered name or a resolved ``FILE.py:CLASS``) and
    options of its own (a variant: ``{ name = "rfe-log", planner = "rfe",
    options = { form = "log" } }``)."""
    name: str
    ref: str
    options: dict = field(default_factory=dict)


@dataclass
class Suite:
    name: str
    planners: list  # of SuitePlanner
    scenes: list
    defaults: dict


def load_suite(path) -> Suite:
    """Parse and check a suite file; UserError on anything malformed."""
    path = Path(path)
    if not path.is_file():
        raise UserError(not_a_file(path, "suite file"))
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8-sig"))  # a byte-order mark, as some editors write
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"malformed suite file {path}: {exc}") from None
    except RecursionError:
        raise UserError(f"malformed suite file {path}: nested too deeply to read") from None
    run_fields = _setting_names()
    unknown = set(data) - {"name", "planners", "defaults", "scenes"}
    if unknown:
        raise UserError(f"{path}: unknown keys {', '.join(sorted(unknown))}; a suite has name, planners, "
                        "[defaults] and [[scenes]]")
    entries = data.get("planners", ["random", "even", "rfe"])
    if not isinstance(entries, list):
        raise UserError(f"{path}: planners must be a list of names, e.g. planners = [\"even\", \"rfe\"]")
    planners = {}
    for entry in entries:
        p = _suite_planner(path, entry)
        if p.name in planners and (planners[p.name].ref, planners[p.name].options) != (p.ref, p.options):
            raise UserError(f"{path}: two planners are named {p.name}")
        planners[p.name] = p  # a planner named twice is one planner
    planners = list(planners.values())
    if not planners:
        raise UserError(f"{path}: the suite has no planners (planners = [] runs nothing)")
    for p in planners:  # their options are checked with each job's settings
        try:
            planner_class(p.ref)
        except UserError as exc:
            raise UserError(f"{path}: {exc}") from None
    title = data.get("name", path.stem)
    if not isinstance(title, str) or not title.strip():
        raise UserError(f"{path}: name must be a text (the suite's title), got {title!r}")
    defaults = data.get("defaults", {})
    if not isinstance(defaults, dict):
        raise UserError(f"{path}: defaults must be a table of settings ([defaults]), got {defaults!r}")
    scene_tables = data.get("scenes", [])
    if not (isinstance(scene_tables, list) and all(isinstance(s, dict) for s in scene_tables)):
        raise UserError(f"{path}: scenes must be tables ([[scenes]] with mesh, xml or dataset = \"...\")")
    bad = set(defaults) - run_fields
    if bad:
        raise UserError(f"{path}: unknown settings in [defaults]: {', '.join(sorted(bad))}")
    _check_tables(path, "[defaults]", defaults)
    scenes = []
    for i, s in enumerate(scene_tables):
        given = [k for k in SCENE_KINDS if k in s]
        if len(given) != 1:
            raise UserError(f"{path}: scene #{i + 1} needs exactly one of 'mesh', 'xml' or 'dataset'")
        kind = given[0]
        if not isinstance(s[kind], str):
            raise UserError(f"{path}: scene #{i + 1}: {kind} must be a file's path, got {s[kind]!r}")
        name = s.get("name") or _default_name(path.parent / s[kind], kind)
        # The name makes folders inside the suite's (scenes/NAME, runs/NAME, report/plots/NAME beside
        # report/plots/summary), CSV and Markdown cells and a --scenes entry.
        if (not isinstance(name, str) or name in (".", "..", SUMMARY) or not name.isprintable()
                or any(c in name for c in "/\\,|") or ("name" in s and name != name.strip())):
            raise UserError(f"{path}: scene #{i + 1}: name {name!r} cannot name a scene's folders and table rows "
                            f"(no '/', '\\', ',' or '|', no space at either end, not '.', '..' or '{SUMMARY}')")
        extra = set(s) - {"name", *SCENE_KINDS} - set(SCENE_OPTIONS) - run_fields
        if extra:
            raise UserError(f"{path}: scene '{name}' has unknown settings: {', '.join(sorted(extra))}")
        _check_tables(path, f"scene '{name}'", s)
        scene_options = {k: v for k, v in s.items() if k in SCENE_OPTIONS}
        if kind != "mesh" and scene_options:
            raise UserError(f"{path}: scene '{name}': {', '.join(sorted(scene_options))} dress a mesh; "
                            + ("an xml scene is rendered as its file says" if kind == "xml" else
                               "a dataset's images are as they were captured"))
        rendering = sorted(k for k in RENDER_KEYS if k in s)
        if kind == "dataset" and rendering:
            raise UserError(f"{path}: scene '{name}': {', '.join(rendering)} apply to rendered scenes; a dataset's "
                            "cameras and images are as they were captured")
        if isinstance(scene_options.get("texture"), str):  # named relative to the suite, as its files are
            scene_options["texture"] = str((path.parent / scene_options["texture"]).resolve())
        try:
            SceneOptions(**scene_options)
        except UserError as exc:
            raise UserError(f"{path}: scene '{name}': {exc}") from None
        where = path.parent / s[kind]
        if kind == "dataset":  # as `plan` tells datasets from scenes; its frames are read with the jobs
            if not (where.is_dir() or (where.is_file() and where.suffix.lower() == ".json")):
                raise UserError(f"{path}: scene '{name}': dataset = {s[kind]!r} is no dataset: expected a "
                                f"transforms .json file or a folder holding one ({where} "
                                f"{'is another file' if where.exists() else 'does not exist'})")
        elif not where.is_file():  # before a suite authors or runs anything
            raise UserError(f"{path}: scene '{name}': {not_a_file(where, kind + ' file')}")
        if kind == "xml" and Path(s[kind]).suffix.lower() != ".xml":  # as `plan` tells scenes from datasets
            raise UserError(f"{path}: scene '{name}': xml = {s[kind]!r} is not a Mitsuba scene file (.xml)")
        scenes.append(SuiteScene(name, where.resolve(), kind, scene_options,
                                 {k: v for k, v in s.items() if k in run_fields}))
    if not scenes:
        raise UserError(f"{path}: the suite has no scenes")
    names = [s.name for s in scenes]
    if len(set(names)) != len(names):
        raise UserError(f"{path}: scene names must be unique")
    return Suite(title, planners, scenes, defaults)


def _default_name(where: Path, kind: str) -> str:
    """A scene's name unless the suite gives one: its file's stem, or a dataset's folder name
    (that of its transforms .json)."""
    if kind != "dataset":
        return where.stem
    return (where.parent if where.suffix.lower() == ".json" else where).resolve().name


def _suite_planner(path: Path, entry) -> SuitePlanner:
    """A suite's ``planners`` entry: a planner's name, or a table naming a variant."""
    # A planner file is named relative to the suite, as its scenes are.
    if isinstance(entry, str):
        ref = resolve_reference(entry, path.parent)
        return SuitePlanner(planner_label(ref), ref)
    example = '{ name = "rfe-log", planner = "rfe", options = { form = "log" } }'
    if not isinstance(entry, dict):
        raise UserError(f"{path}: a planners entry is a planner's name or a table such as {example}, got {entry!r}")
    extra = set(entry) - {"name", "planner", "options"}
    name, planner, options = entry.get("name"), entry.get("planner"), entry.get("options", {})
    if extra or not isinstance(planner, str) or not isinstance(options, dict):
        raise UserError(f"{path}: a planner variant is a table such as {example}, got {entry!r}")
    # The name makes run folders and table rows.
    if not isinstance(name, str) or not name or folder_name(name) != name or name in (".", ".."):
        raise UserError(f"{path}: planner variant name {name!r}: use letters, digits, '-', '_' and '.'")
    return SuitePlanner(name, resolve_reference(planner, path.parent), dict(options))


def parse_overrides(items) -> dict:
    """``KEY=VALUE`` strings (``bench --set``) to run settings.

    KEY is a :class:`~mitsuba_active.run.RunConfig` field (``ensemble``) or an
    entry of one of its tables (``field.lr``, ``planner_options.form``). VALUE
    is read as a TOML value (``4``, ``0.02``, ``[5, 10]``, ``true``); anything
    else is a string (``rig=interior``).

    Returns:
        dict in the layout of a suite's ``[defaults]``.
    """
    run_fields = _setting_names()
    out: dict = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise UserError(f"--set takes KEY=VALUE, got '{item}'")
        value = setting_value(text)
        table, dot, name = key.partition(".")
        if key in JOB_KEYS:
            raise UserError(f"--set: '{key}' names the runs; choose them with --{key}s")
        if dot and table in TABLE_KEYS and name:
            if name in out.get(table, {}):  # which one was meant?
                raise UserError(f"--set {key} is given twice; give it once")
            out.setdefault(table, {})[name] = value
        elif not dot and key in run_fields and key not in TABLE_KEYS:
            if key in out:
                raise UserError(f"--set {key} is given twice; give it once")
            out[key] = value
        else:
            raise UserError(f"--set: unknown setting '{key}'; use a run setting "
                            f"({', '.join(sorted(run_fields - set(TABLE_KEYS)))}) "
                            f"or field.OPTION / planner_options.OPTION")
    return out
