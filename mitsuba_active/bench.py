"""Benchmark suites: scenes x planners x seeds, run in parallel, reported as tables and plots.

A suite is a TOML file (see ``benchmarks/suites/shared.toml``)::

    name = "mine"
    planners = ["random", "even", "rfe", "my_planners.py:MyPlanner",   # a file beside the suite
                { name = "rfe-log", planner = "rfe", options = { form = "log" } }]   # a variant
    [defaults]              # RunConfig fields for every scene
    candidates = 100
    [[scenes]]
    name = "spot"
    mesh = "meshes/spot.obj"   # authored with scene_from_mesh (options: up, color, sun, floor, texture, ...;
                               # files relative to the suite; an xml scene takes none)
    [[scenes]]
    name = "room"
    xml = "room.xml"           # any Mitsuba scene
    rig = "interior"           # per-scene RunConfig overrides

Each (scene, planner, seed) is one :class:`~mitsuba_active.run.Run` with its
own folder and run.json, so an interrupted suite resumes where it stopped.
Unless a suite sets otherwise, every run has budget 20 and is evaluated at
5, 10, 15 and 20 views; the tables report 10 and 20 views, as the seed paper does
(other budgets: the budget and the count nearest half of it), and a table of means
over scenes gives each planner's margin over ``random`` and ``even``.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
import time
import tomllib
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from .checks import choice_named, not_a_file, setting_value, unknown_choice
from .errors import FolderError, UserError
from .executors import EXECUTORS, RayOptions, prepare_ray, run_local, run_ray
from .imageio_utils import folder_name, new_entries, remove_new, replaced_folder
from .metrics import DECIMALS, fixed, iqm, standard_error
from .webpage import REPORT_FILE, write_run_page, write_suite_page

SCENE_OPTIONS = ("up", "color", "sun", "floor", "point_lights", "env_radiance", "texture", "two_sided")
#: The report's folder of plots over all scenes, beside each scene's (no scene may be named so).
SUMMARY = "summary"

#: Settings of the two profiles. ``quick`` runs the whole suite with one seed,
#: small images and short training, in minutes on two cores; ``full`` uses
#: paper-like settings and five seeds.
PROFILES = {
    "quick": dict(seeds=[0], resolution=32, candidates=30, heldout=8, spp=16, ensemble=2,
                  initial_steps=150, steps_per_view=30, eval_steps=600, rays_per_candidate=64,
                  field_preset="fast", field={"batch_rays": 2048, "n_samples": 32}),
    "full": dict(seeds=[0, 1, 2, 3, 4], resolution=64, candidates=100, heldout=20, spp=64, ensemble=2),
}
#: View counts of the tables, as in the seed paper, when every run evaluates them.
TABLE_VIEWS = (10, 20)
#: Planners that the scene-mean table measures every other planner against.
BASELINES = ("random", "even")
#: Differences up to this (dB, or points of the metric) are ties, not wins:
#: planners that captured the same views differ by rounding alone.
TIE = 1e-6
#: Metrics of the tables: title, and whether higher values are better.
METRICS = {"psnr": ("Photometric held-out PSNR (dB)", True),
           "psnr_fg": ("Foreground held-out PSNR (dB)", True),
           "distance_error": ("Distance error (%)", False)}
#: Metrics of the plots, and those of the summary plot over scenes.
PLOTTED = ("psnr", "psnr_fg", "ssim", "distance_error", "floor_psnr", "floor_psnr_fg")
SUMMARY_PLOTTED = ("psnr", "psnr_fg", "floor_psnr", "floor_psnr_fg")
#: RunConfig fields that each job sets itself (from the suite and --seeds).
JOB_KEYS = ("scene", "planner", "seed")
#: RunConfig fields that are tables: settings merge into them key by key.
TABLE_KEYS = ("field", "planner_options")
#: Most --workers per CPU core (each worker trains fields on its share of the cores).
MAX_WORKERS_PER_CORE = 4


@dataclass
class SuiteScene:
    name: str
    path: Path  # mesh or XML
    kind: str  # "mesh" or "xml"
    scene_options: dict = field(default_factory=dict)
    run_options: dict = field(default_factory=dict)


def _setting_names() -> set[str]:
    """The RunConfig fields a suite or ``--set`` may set: the suite's scenes,
    planners and the seeds name each run, and are not settings."""
    from .run import RunConfig

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
    from .planners.base import planner_class
    from .scene import SceneOptions

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
        raise UserError(f"{path}: scenes must be tables ([[scenes]] with mesh = \"...\" or xml = \"...\")")
    bad = set(defaults) - run_fields
    if bad:
        raise UserError(f"{path}: unknown settings in [defaults]: {', '.join(sorted(bad))}")
    _check_tables(path, "[defaults]", defaults)
    scenes = []
    for i, s in enumerate(scene_tables):
        if ("mesh" in s) == ("xml" in s):
            raise UserError(f"{path}: scene #{i + 1} needs exactly one of 'mesh' or 'xml'")
        kind = "mesh" if "mesh" in s else "xml"
        if not isinstance(s[kind], str):
            raise UserError(f"{path}: scene #{i + 1}: {kind} must be a file's path, got {s[kind]!r}")
        name = s.get("name") or Path(s[kind]).stem
        # The name makes folders inside the suite's (scenes/NAME, runs/NAME, report/plots/NAME beside
        # report/plots/summary), CSV and Markdown cells and a --scenes entry.
        if (not isinstance(name, str) or name in (".", "..", SUMMARY) or not name.isprintable()
                or any(c in name for c in "/\\,|") or ("name" in s and name != name.strip())):
            raise UserError(f"{path}: scene #{i + 1}: name {name!r} cannot name a scene's folders and table rows "
                            f"(no '/', '\\', ',' or '|', no space at either end, not '.', '..' or '{SUMMARY}')")
        extra = set(s) - {"name", "mesh", "xml"} - set(SCENE_OPTIONS) - run_fields
        if extra:
            raise UserError(f"{path}: scene '{name}' has unknown settings: {', '.join(sorted(extra))}")
        _check_tables(path, f"scene '{name}'", s)
        scene_options = {k: v for k, v in s.items() if k in SCENE_OPTIONS}
        if kind == "xml" and scene_options:
            raise UserError(f"{path}: scene '{name}': {', '.join(sorted(scene_options))} dress a mesh; "
                            "an xml scene is rendered as its file says")
        if isinstance(scene_options.get("texture"), str):  # named relative to the suite, as its files are
            scene_options["texture"] = str((path.parent / scene_options["texture"]).resolve())
        try:
            SceneOptions(**scene_options)
        except UserError as exc:
            raise UserError(f"{path}: scene '{name}': {exc}") from None
        if not (path.parent / s[kind]).is_file():  # before a suite authors or runs anything
            raise UserError(f"{path}: scene '{name}': {not_a_file(path.parent / s[kind], kind + ' file')}")
        if kind == "xml" and Path(s[kind]).suffix.lower() != ".xml":  # as `plan` tells scenes from datasets
            raise UserError(f"{path}: scene '{name}': xml = {s[kind]!r} is not a Mitsuba scene file (.xml)")
        scenes.append(SuiteScene(name, (path.parent / s[kind]).resolve(), kind, scene_options,
                                 {k: v for k, v in s.items() if k in run_fields}))
    if not scenes:
        raise UserError(f"{path}: the suite has no scenes")
    names = [s.name for s in scenes]
    if len(set(names)) != len(names):
        raise UserError(f"{path}: scene names must be unique")
    return Suite(title, planners, scenes, defaults)


def _suite_planner(path: Path, entry) -> SuitePlanner:
    """A suite's ``planners`` entry: a planner's name, or a table naming a variant."""
    from .planners.base import planner_label, resolve_reference

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


@dataclass
class Job:
    scene: str
    planner: str
    seed: int
    scene_xml: str
    config: dict
    out: str
    content_hash: str | None = None  #: of the scene as it is now (None: its XML is missing)
    planner_digest: str | None = None  #: of a planner file of the user's own (None: the package's planner)


def plan_jobs(suite: Suite, out_dir: Path, profile: str, seeds=None, planners=None, scenes=None,
              author: bool = True, overrides: dict | None = None) -> list[Job]:
    """Author the mesh scenes and list every run of the suite.

    ``overrides`` (see :func:`parse_overrides`) win over the suite's and the
    scenes' settings. Every job's settings are checked, and every scene and
    mesh loaded, before anything is written (a failed authoring leaves
    nothing of its own behind). A mesh scene is authored anew each time (``author``);
    authoring is deterministic, so unchanged scenes keep their content hash
    and their finished runs. A folder whose runs were made with another scene
    or other settings is refused before anything is replaced or run. Without
    ``author`` (reports only) the scenes are left as they are.
    """
    from .planners import make_planner, planner_label
    from .planners.base import REGISTRY, planner_digest, registered_name, resolve_reference
    from .run import RunConfig, field_config
    from .scene import content_hash, load_mesh, load_scene

    if profile not in PROFILES:
        raise UserError(unknown_choice("profile", profile, PROFILES))
    unknown = set(scenes or ()) - {sc.name for sc in suite.scenes}
    if unknown:
        raise UserError(f"no scene named {', '.join(sorted(unknown))} in the suite; it has "
                        f"{', '.join(sc.name for sc in suite.scenes)}")
    overrides = overrides or {}
    prof = dict(PROFILES[profile])
    # A seed or planner named twice is one run, not two in one folder.
    seeds = list(dict.fromkeys(seeds or prof["seeds"]))
    # The suite's planner files are named relative to it; a --planners entry
    # is one of its planners (by the name its tables show) or a planner
    # named relative to the current folder.
    suite_planners = {p.name: p for p in suite.planners}
    chosen = {}
    for name in planners or list(suite_planners):
        p = suite_planners.get(choice_named(planner_label(name), suite_planners))
        if p is None and ":" not in name and registered_name(name) not in REGISTRY:
            others = [n for n in sorted(REGISTRY) if n not in suite_planners]
            raise UserError(f"{unknown_choice('planner', name, [*suite_planners, *others])}, "
                            "or name a planner of your own as FILE.py:CLASS")
        if p is None:
            ref = resolve_reference(name)
            p = SuitePlanner(planner_label(ref), ref)
        chosen.setdefault(p.name, p)
    planners = list(chosen.values())
    folders = {}
    for p in planners:  # files of one name in two folders: their tables and run folders would mix
        other = folders.setdefault(folder_name(p.name).casefold(), p)
        if other is not p:
            raise UserError(f"the planners {other.name} and {p.name} would share run folders "
                            "and table rows; rename one of them")
    digests = {p.name: planner_digest(p.ref) for p in planners}  # each file read once
    prof.pop("seeds")
    jobs, meshes = [], {}
    for sc in suite.scenes:
        if scenes and sc.name not in scenes:
            continue
        xml = sc.path
        if sc.kind == "mesh":
            xml = meshes[sc.name] = out_dir / "scenes" / sc.name / f"{sc.name}.xml"
        for planner in planners:
            for seed in seeds:
                # The profile sets the effort; the suite's defaults, each scene's own
                # settings and the command line's overrides win, in that order.
                layers = (prof, suite.defaults, sc.run_options, {"planner_options": planner.options}, overrides)
                settings = {"budget": 20, "eval_views": [5, 10, 15, 20]}
                for layer in layers:
                    settings.update(layer)
                # Tables merge key by key: a suite's `field` adds to the profile's.
                for key in TABLE_KEYS:
                    settings[key] = {k: v for layer in layers for k, v in layer.get(key, {}).items()}
                try:
                    cfg = RunConfig(scene=str(xml), planner=planner.ref, seed=int(seed), **settings)
                    # A generated rig has as many candidates as asked for; the XML's own, as it has.
                    cfg.validate(None if cfg.rig == "xml" else cfg.candidates)
                    if cfg.downscale is not None:  # a suite's scenes are scenes, never datasets
                        raise UserError("downscale applies to datasets; a scene renders at its resolution")
                except UserError as exc:  # e.g. budget = "20"
                    raise UserError(f"scene '{sc.name}': {exc}") from None
                own = {k: v for k, v in (overrides.get("planner_options") or {}).items()
                       if k in planner.options and planner.options[k] != v}
                if own:  # the row would carry the variant's name and another planner's results
                    k = next(iter(own))
                    raise UserError(f"planner '{planner.name}' sets {k} = {planner.options[k]!r} itself; "
                                    f"--set planner_options.{k} = {own[k]!r} would run another planner under its "
                                    "name (list that one in the suite)")
                # Options the runs would refuse, refused before anything is written.
                try:
                    make_planner(planner.ref, **cfg.planner_options).check_ensemble_size(cfg.ensemble)
                except UserError as exc:
                    raise UserError(f"planner '{planner.name}': {exc}") from None
                field_config(cfg)
                jobs.append(Job(sc.name, planner.name, int(seed), str(xml), asdict(cfg),
                                str(out_dir / "runs" / sc.name / f"{folder_name(planner.name)}-seed{seed}"),
                                planner_digest=digests[planner.name]))
    hashes = {}  # scene XML -> content hash
    if author:
        selected = [sc for sc in suite.scenes if any(j.scene == sc.name for j in jobs)]
        with _mitsuba_warnings_muted():  # its runs show them, once
            for sc in selected:  # a scene that cannot load stops the suite before any is authored or run
                try:
                    load_mesh(sc.path) if sc.kind == "mesh" else load_scene(sc.path)
                except UserError as exc:
                    raise UserError(f"scene '{sc.name}': {exc}") from None
        added = new_entries(out_dir)
        try:
            for sc in selected:
                if sc.name in meshes:
                    xml = meshes[sc.name]
                    hashes[str(xml)] = _author_suite_scene(sc, xml, [j for j in jobs if j.scene == sc.name])
        except BaseException:
            remove_new(out_dir, *added)
            raise
    else:
        # A mesh scene as the suite would author it now, in a scratch folder (the suite's is
        # left as it is): runs of an edited mesh or options are refused, as a run of the suite would be.
        with tempfile.TemporaryDirectory() as scratch, _mitsuba_warnings_muted():
            for name, xml in meshes.items():
                if not xml.is_file():  # never authored: no run in the folder was made from it
                    continue
                sc = next(sc for sc in suite.scenes if sc.name == name)
                # Into a copy of the scene's folder: the names of the files it writes depend on those there.
                shutil.copytree(xml.parent, Path(scratch) / name, symlinks=True)
                hashes[str(xml)] = _author_suite_scene(sc, Path(scratch) / name / xml.name,
                                                       [j for j in jobs if j.scene == name])
    for xml in {j.scene_xml for j in jobs} - set(hashes):
        hashes[xml] = content_hash(Path(xml)) if Path(xml).is_file() else None
    for job in jobs:
        job.content_hash = hashes[job.scene_xml]
    _refuse_other_runs(jobs)  # --report-only too: it would report a mix, or leave runs out unsaid
    return jobs


@contextlib.contextmanager
def _mitsuba_warnings_muted():
    """Mitsuba logs errors only (a scene it cannot load raises all the same)."""
    import mitsuba as mi

    logger = mi.logger()
    level = logger.log_level()
    logger.set_log_level(mi.LogLevel.Error)
    try:
        yield
    finally:
        logger.set_log_level(level)


def _recorded(job: Job) -> dict | None:
    """The run record in the job's folder (finished or not), or None."""
    from .run import read_record

    path = Path(job.out) / "run.json"
    if not path.is_file():
        return None
    try:
        return read_record(path)
    except UserError:  # damaged: the run itself says so
        return None


def _author_suite_scene(sc, xml: Path, jobs: list[Job]) -> str:
    """Author a mesh scene of the suite and return its content hash, unless its
    runs in the suite folder were made with another scene (edited options or
    mesh): then nothing is replaced, and the suite is refused."""
    from .scene import scene_from_mesh

    authored = []

    def same_scene(digest: str) -> None:
        stale = [j.out for j in jobs if (rec := _recorded(j)) and rec.get("content_hash") not in (None, digest)]
        if stale:
            raise UserError(f"the runs of scene '{sc.name}' in {Path(stale[0]).parent.parent.parent} were made with "
                            "another version of it (its options or mesh changed); use another --out, or undo "
                            "the change")
        authored.append(digest)  # the files land as they were hashed

    scene_from_mesh(sc.path, xml, check=same_scene, **sc.scene_options)
    return authored[0]


def _refuse_other_runs(jobs: list[Job]) -> None:
    """Refuse, before any run starts, a suite folder whose runs have other settings, were made with another
    version of their scene or planner, or have a damaged record."""
    from .run import conflicting_settings, other_planner_code, other_settings, read_resumable_record

    for job in jobs:
        path = Path(job.out) / "run.json"
        if not path.is_file():
            continue
        rec = read_resumable_record(path)
        if job.content_hash is not None and rec.get("content_hash") not in (None, job.content_hash):
            raise FolderError(job.out, f"holds a run of scene '{job.scene}' made with another version of it (its "
                                       "file or the files it names changed); use another --out, or undo the change")
        # A larger budget is not refused: the runs go on to it.
        changed = conflicting_settings(rec, job.config, compare_scene=job.content_hash is None)
        if changed:
            raise other_settings(job.out, changed, "use another --out for this variant of the suite")
        if other_planner_code(rec, job.planner_digest):
            suite_dir = Path(job.out).parent.parent.parent
            raise UserError(f"{suite_dir} holds runs made with another version of the planner's code "
                            f"({job.planner}); use another --out, undo the change, or remove its runs "
                            f"({suite_dir / 'runs' / '*' / folder_name(job.planner)}-seed*)")


def run_job(job: Job, threads: int | None = None) -> dict:
    """Run (or resume) one job; returns a short status. Runs inside a worker process."""
    import drjit as dr

    import mitsuba_active  # noqa: F401

    from .planners.base import planner_digest
    from .run import Run, RunConfig, undone_unless_resumable

    if threads:
        dr.set_thread_count(threads)
    cfg = RunConfig(**job.config)
    if finished_record(job) is not None:
        return {"job": f"{job.scene}/{job.planner}/{job.seed}", "skipped": True}
    if planner_digest(cfg.planner) != job.planner_digest:  # one suite, one version of each planner
        raise UserError(f"the planner's code ({job.planner}) changed while the suite ran; its runs so far "
                        "are kept: undo the change to go on, or use another --out")
    t0 = time.perf_counter()
    out = Path(job.out)
    # Only the job's own folder may be undone, never a parent another worker's job shares.
    out.parent.mkdir(parents=True, exist_ok=True)
    with undone_unless_resumable(out):
        Run(cfg.open_source(), cfg, out, progress=False, log=lambda m: None).execute()
    return {"job": f"{job.scene}/{job.planner}/{job.seed}", "skipped": False,
            "seconds": round(time.perf_counter() - t0, 1)}


def run_suite(suite_path, out_dir, profile="quick", workers=1, seeds=None, planners=None, scenes=None,
              progress=True, log=print, report_only=False, overrides=None, executor="local",
              ray: RayOptions | None = None) -> dict:
    """Run every job of a suite (resuming finished ones) and write the report; returns the summary.

    ``report_only`` runs nothing and reports the runs finished so far (safe
    while another process is still running the suite). ``overrides``
    (:func:`parse_overrides`) change every run's settings. ``executor`` runs
    them (:data:`~mitsuba_active.executors.EXECUTORS`): ``local``, in
    ``workers`` processes; ``ray``, as Ray tasks, as ``ray`` says."""
    from tqdm import tqdm

    from .run import ends_short_of_a_batch

    if executor not in EXECUTORS:
        raise ValueError(f"executor is one of {', '.join(EXECUTORS)}, got {executor!r}")
    if ray is not None and executor != "ray":
        raise ValueError("ray options are for executor='ray'")
    suite = load_suite(suite_path)
    out_dir = Path(out_dir)
    cores = os.cpu_count() or 1
    if not 1 <= workers <= MAX_WORKERS_PER_CORE * cores:
        raise UserError(f"--workers must be between 1 and {MAX_WORKERS_PER_CORE * cores} "
                        f"({MAX_WORKERS_PER_CORE} per core of this machine's {cores}), got {workers}")
    if executor == "ray" and not report_only:  # before anything is authored
        ray = ray or RayOptions()
        prepare_ray(ray)
    jobs = plan_jobs(suite, out_dir, profile, seeds, planners, scenes, author=not report_only,
                     overrides=overrides)
    if report_only:
        return write_report(suite, jobs, out_dir / "report", profile, overrides)
    kept = sum(finished_record(job) is not None for job in jobs)
    if kept:
        log(f"{kept} of the suite's {len(jobs)} runs finished earlier with these settings: kept, not run again")
    grown = [(job, rec) for job in jobs if (rec := _recorded(job)) and rec["finished"]
             and rec["config"].get("budget", job.config["budget"]) < job.config["budget"]]
    if grown:
        log(f"{len(grown)} of the suite's runs finished earlier with a smaller budget: they go on from the views "
            "they have")
        short = sum(ends_short_of_a_batch(len(rec["captured"]), job.config["initial_views"],
                                          job.config["batch"]) for job, rec in grown)
        if short:
            log(f"note: in {short} of them the last round captured fewer views than a batch, so their rounds from "
                "here differ from those of runs made with this budget from the start")
    bar = tqdm(total=len(jobs), desc=f"suite {suite.name}", unit="run", disable=not progress)
    try:
        if executor == "ray":
            bar.update(kept)
            out_dir.mkdir(parents=True, exist_ok=True)  # the folder a worker on shared storage sees
            run_ray([job for job in jobs if finished_record(job) is None], ray, bar)
        else:
            run_local(jobs, workers, bar)
    finally:
        bar.close()
    return write_report(suite, jobs, out_dir / "report", profile, overrides)


# ---------------------------------------------------------------------------
# Reports
# ---------------------------------------------------------------------------

def finished_record(job: Job) -> dict | None:
    """The job's run record if that run finished *with the job's settings*.

    A run in the folder with other settings (the suite or the profile changed)
    is not this job's: it is not skipped (the run then refuses the folder) nor
    reported.
    """
    from .run import same_config

    rec = _recorded(job)
    if rec is None or not rec["finished"]:
        return None
    if job.content_hash is not None and rec.get("content_hash") != job.content_hash:
        return None  # the scene changed since
    if rec.get("planner_digest") != job.planner_digest:
        return None  # the planner's code changed since
    return rec if same_config(rec["config"], job.config, compare_scene=job.content_hash is None) else None


def collect(jobs: list[Job]) -> dict:
    """scene -> planner -> list of finished run records (one per seed)."""
    out: dict = {}
    for job in jobs:
        rec = finished_record(job)
        if rec is not None:
            out.setdefault(job.scene, {}).setdefault(job.planner, []).append(rec)
    return out


def unreported_seeds(jobs: list[Job]) -> list[int]:
    """Seeds of runs in the jobs' folders that finished with the jobs' settings
    (but their seed) and that the jobs leave out: a suite run with
    ``--seeds 0,1`` reported without them."""
    asked = {job.seed for job in jobs}
    found = set()
    groups = {}  # one job of each scene and planner: its seeds' folders lie side by side
    for job in jobs:
        folder = Path(job.out)
        groups.setdefault((folder.parent, folder.name[:folder.name.rindex("-seed") + len("-seed")]), job)
    for (parent, stem), job in groups.items():
        for other in parent.glob(f"{stem}*"):
            tail = other.name[len(stem):]
            if not tail.isdigit() or int(tail) in asked or int(tail) in found:
                continue
            seed = int(tail)
            twin = replace(job, seed=seed, out=str(other), config={**job.config, "seed": seed})
            if finished_record(twin) is not None:
                found.add(seed)
    return sorted(found)


def metric_at(rec: dict, metric: str, views: int):
    for m in rec["metrics"]:
        if m["views"] == views and m.get(metric) is not None:
            return m[metric]
    return None


def usable(value) -> bool:
    """Whether a seed's value counts in a table: a finite number (a NaN PSNR, from a dataset image
    with NaN pixels, or an infinite one, from a perfect view, counts as missing), in every cell and margin alike."""
    return value is not None and bool(np.isfinite(value))


def summarize(values) -> dict:
    vals = [v for v in values if usable(v)]
    return {"iqm": iqm(vals) if vals else None, "se": standard_error(vals) if vals else None, "n": len(vals)}


def table_views(jobs: list[Job]) -> tuple:
    """The view counts the tables report: :data:`TABLE_VIEWS` when every job
    evaluates them and none more, else the largest count every job evaluates and the one
    nearest half of it, the larger of two as near (a suite with another budget
    or other counts: of 2, 4 and 6 views, 4 and 6), but not the initial views
    (where every planner has the same views)."""
    from .run import RunConfig

    common = set.intersection(*[set(RunConfig(**j.config).report_counts()) for j in jobs]) if jobs else set()
    if not common or (set(TABLE_VIEWS) <= common and max(common) == max(TABLE_VIEWS)):
        return TABLE_VIEWS
    last = max(common)
    initial = max(int(j.config.get("initial_views", 0)) for j in jobs)
    rest = sorted((v for v in common - {last} if v > initial), key=lambda v: (abs(v - last / 2), -v))
    return (rest[0], last) if rest else (last,)


def write_report(suite: Suite, jobs: list[Job], report_dir: Path, profile: str, overrides=None) -> dict:
    """Tables (Markdown, CSV, JSON) in the layout of the seed's Tables I and III, and plots.

    ``overrides`` (the command line's ``--set``) are recorded in ``results.json``.
    With no finished run, nothing is written (an earlier report stays)."""
    from .report import plot_metrics
    from .training import weak_evaluation

    data = collect(jobs)
    scenes = [s.name for s in suite.scenes if s.name in data]
    planners = [p for p in dict.fromkeys(j.planner for j in jobs)]
    views = table_views(jobs)
    reported = [r for by_planner in data.values() for recs in by_planner.values() for r in recs]
    summary = {"suite": suite.name, "profile": profile, "overrides": overrides or {},
               "table_views": list(views), "runs": len(jobs), "runs_reported": len(reported),
               "unreported_seeds": unreported_seeds(jobs),
               # Runs whose evaluation fields scored near the background alone, or barely fit their own views.
               "short_training": sum(any(weak_evaluation(m) for m in r["metrics"]) for r in reported),
               # Finished runs are kept across upgrades: which versions made the reported ones.
               "versions": [json.loads(v) for v in sorted({json.dumps(r.get("versions"), sort_keys=True)
                                                           for r in reported})],
               "cells": []}
    if not data:  # nothing finished: keep whatever report is there
        return summary
    for scene in scenes:
        for planner in planners:
            recs = data[scene].get(planner, [])
            cell = {"scene": scene, "planner": planner, "seeds": len(recs),
                    "wall_seconds": summarize([r.get("wall_seconds") for r in recs]),
                    "planning_seconds": summarize([r.get("planning_seconds") for r in recs])}
            for metric in METRICS:
                for v in views:
                    cell[f"{metric}@{v}"] = summarize([metric_at(r, metric, v) for r in recs])
            # Each seed's values, for comparisons over the seeds two planners share.
            cell["per_seed"] = {str(r["config"]["seed"]): {f"{metric}@{v}": metric_at(r, metric, v)
                                                          for metric in METRICS for v in views} for r in recs}
            summary["cells"].append(cell)
    # The report is written whole into a new folder that then replaces the earlier one:
    # no half-written report after an interruption, and no plots of scenes it no longer covers.
    with replaced_folder(report_dir) as folder:
        summary["mean_over_scenes"] = {metric: scene_means(summary, scenes, planners, metric) for metric in METRICS}
        tables = []
        for metric, (title, _) in METRICS.items():
            md, csv_rows = _table(summary, scenes, planners, metric, title)
            (folder / f"table_{metric}.md").write_text(md)
            (folder / f"table_{metric}.csv").write_text("\n".join(",".join(map(str, r)) for r in csv_rows) + "\n")
            tables.append(md)
        note = _overrides_note(summary["overrides"])
        tables.insert(0, "\n".join(
            _mean_table(summary["mean_over_scenes"][m], planners, *METRICS[m], views=views, note=note)
            for m in METRICS))
        (folder / "table_mean.md").write_text(tables[0])
        (folder / "results.json").write_text(json.dumps(summary, indent=1))
        # Plots: per scene, IQM over seeds with a +-SE band; and a summary over the scenes
        # that every planner with results has. A planner has one colour in every plot.
        colors = {p: f"C{i % 10}" for i, p in enumerate(planners)}
        with_results = {p for by_planner in data.values() for p in by_planner}
        shared = [s for s in scenes if with_results <= set(data[s])]
        overall: dict = {}
        for scene in scenes:
            series, bands = {}, {}
            for planner, recs in data[scene].items():
                # The counts every seed has (a run taken on to a larger budget also has its earlier one).
                counts = sorted(set.intersection(*[{m["views"] for m in r["metrics"]} for r in recs]))
                rows, lo, hi = [], {}, {}
                for c in counts:
                    row = {"views": c}
                    for metric in PLOTTED:
                        s = summarize([metric_at(r, metric, c) for r in recs])
                        row[metric] = s["iqm"]
                        if s["iqm"] is not None:
                            lo.setdefault(metric, []).append(s["iqm"] - s["se"])
                            hi.setdefault(metric, []).append(s["iqm"] + s["se"])
                    rows.append(row)
                series[planner] = rows
                bands[planner] = {m: (lo[m], hi[m]) for m in lo if len(lo[m]) == len(counts)}
                for row in rows:
                    for metric in SUMMARY_PLOTTED:
                        if row[metric] is not None and scene in shared:
                            by_count = overall.setdefault(planner, {}).setdefault(metric, {})
                            by_count.setdefault(row["views"], []).append(row[metric])
            scene_plots = folder / "plots" / scene
            scene_plots.mkdir(parents=True, exist_ok=True)
            plot_metrics(series, scene_plots, title=scene, bands=bands, colors=colors)
        # A point of the summary is a mean over all of its scenes, never over some.
        mean_series = {}
        for p, by_metric in overall.items():
            points: dict = {}
            for metric, by_count in by_metric.items():
                for v, x in by_count.items():
                    if len(x) == len(shared):
                        points.setdefault(v, {"views": v})[metric] = float(np.mean(x))
            mean_series[p] = [points[v] for v in sorted(points)]
        if any(mean_series.values()):
            (folder / "plots" / SUMMARY).mkdir(parents=True, exist_ok=True)
            plot_metrics(mean_series, folder / "plots" / SUMMARY, colors=colors,
                         title=f"{suite.name}: mean over {len(shared)} scene{'' if len(shared) == 1 else 's'}")
        write_suite_page(folder, report_dir, f"{suite.name} ({profile})", tables, _run_pages(jobs))
    return summary


def _run_pages(jobs: list[Job]) -> dict:
    """scene -> planner -> folders of the finished runs, each with its page (written where a run
    finished before runs had one)."""
    out: dict = {}
    for job in jobs:
        rec = finished_record(job)
        if rec is None:
            continue
        if not (Path(job.out) / REPORT_FILE).is_file():
            write_run_page(job.out, rec)
        out.setdefault(job.scene, {}).setdefault(job.planner, []).append(job.out)
    return out


def _overrides_note(overrides: dict) -> str:
    """A sentence naming the settings ``--set`` changed for every run ('' when none),
    so that a table copied elsewhere keeps them."""
    settings = [(f"{k}.{name}", v) for k, table in overrides.items() if isinstance(table, dict)
                for name, v in table.items()]
    settings += [(k, v) for k, v in overrides.items() if not isinstance(v, dict)]
    flat = sorted(f"{k}={v!r}" if isinstance(v, str) else f"{k}={v}" for k, v in settings)
    return f" Every run with --set {', '.join(flat)}." if flat else ""


def _fmt(s: dict) -> str:
    if s["iqm"] is None:
        return "n/a"
    # One seed has no spread to estimate: no "± 0.00".
    return f"{s['iqm']:.2f}" if s["n"] < 2 else f"{s['iqm']:.2f} ± {s['se']:.2f}"


def _table(summary: dict, scenes, planners, metric: str, title: str):
    cells = {(c["scene"], c["planner"]): c for c in summary["cells"]}
    views = tuple(summary.get("table_views", TABLE_VIEWS))
    empty = {"iqm": None, "se": None, "n": 0}
    stats = {(s, p, v): cells[(s, p)][f"{metric}@{v}"] if (s, p) in cells else empty
             for s in scenes for p in planners for v in views}
    counts = {st["n"] for st in stats.values() if st["n"]}
    # One seed count for the whole table, or each cell's own when they differ
    # (a suite still running).
    per_cell = len(counts) > 1
    n = max(counts, default=0)
    if per_cell:
        stat = "Interquartile mean ± standard error of the mean over seeds (n per cell)"
    elif n == 1:
        stat = "One seed (no standard error)"
    else:
        stat = f"Interquartile mean ± standard error of the mean over {n} seeds"
    head = ["planner"] + [f"{s} @{v}" for s in scenes for v in views] + ["planning (s)", "wall time (s)"]
    lines = [f"## {title}", "", f"{stat}, at " + " and ".join(map(str, views)) + " views captured. "
             "Times are means over scenes of each cell's interquartile mean: planning is the time spent "
             "choosing views and training the planner's ensemble; wall time is the whole run, with ground "
             "truth (cached renders are fast) and evaluation." + _overrides_note(summary.get("overrides") or {}),
             "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    csv_rows = [["planner", "scene", "views", "iqm", "se", "n"]]
    for p in planners:
        row, times = [p], {"planning_seconds": [], "wall_seconds": []}
        for s in scenes:
            c = cells.get((s, p))
            for v in views:
                st = stats[(s, p, v)]
                row.append(f"{_fmt(st)} ({st['n']})" if per_cell and st["iqm"] is not None else _fmt(st))
                csv_rows.append([p, s, v, fixed(st["iqm"], DECIMALS[metric]), fixed(st["se"], DECIMALS[metric]),
                                 st["n"]])
            for key, found in times.items():
                if c and (c.get(key) or {}).get("iqm") is not None:
                    found.append(c[key]["iqm"])
        row += [f"{np.mean(found):.{1 if key == 'planning_seconds' else 0}f}" if found else "n/a"
                for key, found in times.items()]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n", csv_rows


def scene_means(summary: dict, scenes, planners, metric: str) -> dict:
    """Each planner over the scenes where every planner with results has a value at every table view.

    A planner without any such scene yet (a suite still running) is left out
    of that condition and gets no means. Returns ``{planner: {"scenes": n,
    "seeds": the distinct seed counts of its cells, "mean@V": mean of the
    cells' IQMs, "vs_B@V": mean difference to baseline B, "wins_vs_B@V":
    scenes where the planner is better than B, "compared_vs_B@V": scenes
    compared}}`` for each table view V and each baseline of :data:`BASELINES`
    with results (better: higher, or lower for errors, by more than :data:`TIE`).

    A difference on a scene is paired: the two planners' interquartile means
    over the seeds both have (cells' ``per_seed``), so that a planner missing
    a seed (a suite still running) is not compared with its baseline's other
    seeds; a scene where they share no seed is not compared.
    """
    cells = {(c["scene"], c["planner"]): c for c in summary["cells"]}
    views = tuple(summary.get("table_views", TABLE_VIEWS))

    def value(s, p, v):
        c = cells.get((s, p))
        return None if c is None else c[f"{metric}@{v}"]["iqm"]

    def paired(s, p, b, v):
        """(p's, b's) value on scene s over the seeds both have, or None."""
        key, cp, cb = f"{metric}@{v}", cells[(s, p)], cells[(s, b)]
        common = [k for k in cp["per_seed"] if k in cb["per_seed"]
                  and usable(cp["per_seed"][k].get(key)) and usable(cb["per_seed"][k].get(key))]
        if not common:
            return None
        return tuple(iqm([c["per_seed"][k][key] for k in common]) for c in (cp, cb))

    def has_all(s, p):
        return all(value(s, p, v) is not None for v in views)

    present = [p for p in planners if any(has_all(s, p) for s in scenes)]
    complete = [s for s in scenes if present and all(has_all(s, p) for p in present)]
    higher_is_better = METRICS[metric][1]
    rows = {}
    for p in planners:
        used = complete if p in present else []
        row = {"scenes": len(used), "seeds": sorted({cells[(s, p)].get("seeds") for s in used} - {None})}
        for v in views:
            row[f"mean@{v}"] = float(np.mean([value(s, p, v) for s in used])) if used else None
            for b in BASELINES:
                if b == p or b not in present or not used:
                    continue
                pairs = [pair for s in used if (pair := paired(s, p, b, v)) is not None]
                diff = [a - c for a, c in pairs]
                row[f"vs_{b}@{v}"] = float(np.mean(diff)) if diff else None
                row[f"wins_vs_{b}@{v}"] = int(sum((d > TIE) if higher_is_better else (d < -TIE) for d in diff))
                row[f"compared_vs_{b}@{v}"] = len(diff)
        rows[p] = row
    return rows


def _mean_table(means: dict, planners, title: str, higher_is_better: bool = True, views=TABLE_VIEWS,
                note: str = "") -> str:
    """Markdown of :func:`scene_means`: means, and margins over the baselines with scenes won
    (``note``: a sentence added to the caption)."""
    n = max((r["scenes"] for r in means.values()), default=0)
    baselines = [b for b in BASELINES if any(f"vs_{b}@{v}" in r for r in means.values() for v in views)]
    head = ["planner"] + [f"mean @{v}" for v in views] + [f"vs {b} @{v}" for b in baselines for v in views]
    better = "higher" if higher_is_better else "lower"
    intro = f"Mean over {n} scene{'' if n == 1 else 's'} of each cell's interquartile mean ({better} is better)"
    if baselines:
        intro += ("; 'vs B': the mean difference to planner B on each scene over the seeds both have, and "
                  "in brackets the scenes where the planner does better than B, of those compared")
    seeds = {c for r in means.values() for c in r["seeds"]}
    if len(seeds) > 1:
        intro += f"; the cells cover {min(seeds)} to {max(seeds)} seeds (a suite still running)"
    lines = [f"## {title}: mean over scenes", "", intro + "." + note, "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in planners:
        r = means[p]
        row = [p] + ["n/a" if r[f"mean@{v}"] is None else f"{r[f'mean@{v}']:.2f}" for v in views]
        for b in baselines:
            for v in views:
                key = f"vs_{b}@{v}"
                ok = r.get(key) is not None
                row.append(f"{r[key]:+.2f} ({r['wins_' + key]}/{r.get('compared_' + key, n)})" if ok else "-")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"
