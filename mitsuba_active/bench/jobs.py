"""A suite's jobs: one run each of a scene, a planner and a seed, planned, checked and run.

Each job is one :class:`~mitsuba_active.run.Run` with its own folder and
run.json, so an interrupted suite resumes where it stopped; a folder whose
runs cannot be resumed by the suite's is refused before any run starts.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
import time
import warnings
from dataclasses import MISSING, asdict, dataclass, fields
from pathlib import Path

import drjit as dr
import mitsuba as mi

from ..checks import choice_named, unknown_choice
from ..errors import FolderError, UserError
from ..imageio_utils import folder_name, new_entries, remove_new
from ..planners import make_planner, planner_label
from ..planners.base import REGISTRY, planner_digest, registered_name, resolve_reference
from ..run import (Run, RunConfig, field_config, read_record, read_resumable_record, resume_obstacles, same_config,
                   other_settings, undone_unless_resumable)
from ..scene import content_hash, load_mesh, load_scene, scene_from_mesh
from ..transforms import locate_files, parse_frame, read_transforms, split_frames
from .suite import RENDER_KEYS, TABLE_KEYS, Suite, SuitePlanner

#: Settings of the two profiles. ``quick`` runs the whole suite with one seed,
#: small images and short training, in minutes on two cores; ``full`` uses
#: paper-like settings and five seeds, at 128 px, where the ``default`` preset
#: is the hash field.
PROFILES = {
    "quick": dict(seeds=[0], resolution=32, candidates=30, heldout=8, spp=16, ensemble=2,
                  initial_steps=150, steps_per_view=30, eval_steps=600, rays_per_candidate=64,
                  field_preset="fast", field={"batch_rays": 2048, "n_samples": 32}),
    "full": dict(seeds=[0, 1, 2, 3, 4], resolution=128, candidates=100, heldout=20, spp=64, ensemble=2),
}


@dataclass
class Job:
    scene: str
    planner: str
    seed: int
    scene_xml: str  #: the scene's XML, or a dataset's transforms .json or folder
    config: dict
    out: str
    content_hash: str | None = None  #: of the scene or dataset as it is now (None: missing)
    planner_digest: str | None = None  #: of a planner file of the user's own (None: the package's planner)
    #: A dataset's files (its transforms files, images and depth maps; absolute paths), for executors
    #: that send a run its scene's files; None: a scene's XML and the files it names.
    scene_files: list | None = None


def plan_jobs(suite: Suite, out_dir: Path, profile: str, seeds=None, planners=None, scenes=None,
              author: bool = True, overrides: dict | None = None) -> list[Job]:
    """Author the mesh scenes, read the datasets' frames and list every run of the suite.

    ``overrides`` (see :func:`parse_overrides`) win over the suite's and the
    scenes' settings. Every job's settings are checked, and every scene and
    mesh loaded, before anything is written (a failed authoring leaves
    nothing of its own behind); a dataset is read as its runs read it (a
    dataset scene's jobs take no ``rig``, ``fov`` or ``spp``: its cameras
    and images are as they were captured). A mesh scene is authored anew each time (``author``);
    authoring is deterministic, so unchanged scenes keep their content hash
    and their finished runs. A folder whose runs were made with another scene
    or other settings is refused before anything is replaced or run. Without
    ``author`` (reports only) the scenes are left as they are.
    """
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
                if sc.kind == "dataset":  # the suite-wide settings of its rendered scenes
                    settings.update({k: _RUN_DEFAULTS[k] for k in RENDER_KEYS})
                try:
                    cfg = RunConfig(scene=str(xml), planner=planner.ref, seed=int(seed), **settings)
                    # A generated rig has as many candidates as asked for; the XML's own and a
                    # dataset's, as it has (a dataset's are checked once read).
                    cfg.validate(None if cfg.rig == "xml" or sc.kind == "dataset" else cfg.candidates)
                    if cfg.downscale is not None and sc.kind != "dataset":
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
    hashes = {}  # scene XML (or dataset) -> content hash
    selected = [sc for sc in suite.scenes if any(j.scene == sc.name for j in jobs)]
    for sc in selected:
        if sc.kind == "dataset":  # read before anything is authored or run: a bad dataset stops the suite
            own = [j for j in jobs if j.scene == sc.name]
            hashes[str(sc.path)] = _read_dataset(sc, own, strict=author)
            if author and hashes[str(sc.path)] is not None:
                files = dataset_files(sc.path)
                for job in own:
                    job.scene_files = files
    if author:
        with _mitsuba_warnings_muted():  # its runs show them, once
            for sc in selected:  # a scene that cannot load stops the suite before any is authored or run
                if sc.kind == "dataset":
                    continue
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


#: RunConfig's own values of its fields.
_RUN_DEFAULTS = {f.name: f.default for f in fields(RunConfig) if f.default is not MISSING}


def _read_dataset(sc, jobs: list[Job], strict: bool) -> str | None:
    """Read a dataset scene's frames as each of its jobs' runs will (UserError, naming the
    scene, on a bad dataset or settings it cannot run with) and return its content hash: a
    digest of its transforms files (poses, intrinsics and image file names), as the runs
    record it. Not ``strict`` (reports only), a dataset that cannot be read has none."""
    groups: dict = {}  # jobs whose runs read the same frames at the same size
    for job in jobs:
        groups.setdefault(tuple(job.config[k] for k in ("candidates", "heldout", "resolution", "downscale")),
                          []).append(job)
    digest = None
    for group in groups.values():
        try:
            with warnings.catch_warnings():  # frames without images: its runs say so, once each
                warnings.simplefilter("ignore")
                source = RunConfig(**group[0].config).open_source(cache_dir=False)
            for job in group:  # e.g. a budget larger than its frames
                cfg = RunConfig(**job.config)
                cfg.validate(len(source.candidates))
                if cfg.along_the_way is not None or cfg.candidates_mode == "continuous":
                    raise UserError(f"{'along_the_way' if cfg.along_the_way is not None else 'candidates_mode'} "
                                    "renders new poses, which only a scene can; this is a dataset of captured "
                                    "frames")
        except UserError as exc:
            if not strict:
                return None
            raise UserError(f"scene '{sc.name}': {exc}") from None
        digest = source.content_hash
    return digest


def dataset_files(path) -> list[str] | None:
    """The files of a transforms dataset that its runs read: its transforms files and every
    frame's image and depth map that exists (missing ones are skipped by the runs as here),
    as sorted absolute paths; None for a dataset of another kind (a COLMAP project)."""
    try:
        files = locate_files(path)[0]
    except UserError:
        return None
    metas = [(f, read_transforms(f)) for f in files]
    train, test = split_frames(metas, files)
    with warnings.catch_warnings():  # a missing depth map: its runs say so
        warnings.simplefilter("ignore")
        parsed = [parse_frame(*t) for t in train + test]
    named = [*files, *(image for image, *_ in parsed), *(depth[0] for *_, depth, _ in parsed if depth[0] is not None)]
    return sorted({str(Path(f).resolve()) for f in named if Path(f).is_file()})


@contextlib.contextmanager
def _mitsuba_warnings_muted():
    """Mitsuba logs errors only (a scene it cannot load raises all the same)."""
    logger = mi.logger()
    level = logger.log_level()
    logger.set_log_level(mi.LogLevel.Error)
    try:
        yield
    finally:
        logger.set_log_level(level)


def _recorded(job: Job) -> dict | None:
    """The run record in the job's folder (finished or not), or None."""
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
    for job in jobs:
        path = Path(job.out) / "run.json"
        if not path.is_file():
            continue
        # A larger budget is not refused: the runs go on to it.
        found = resume_obstacles(read_resumable_record(path), job.config, job.content_hash, job.planner_digest)
        if "content" in found:
            raise FolderError(job.out, f"holds a run of scene '{job.scene}' made with another version of it (its "
                                       "file or the files it names changed); use another --out, or undo the change")
        if "settings" in found:
            raise other_settings(job.out, found["settings"], "use another --out for this variant of the suite")
        if "planner" in found:
            suite_dir = Path(job.out).parent.parent.parent
            raise UserError(f"{suite_dir} holds runs made with another version of the planner's code "
                            f"({job.planner}); use another --out, undo the change, or remove its runs "
                            f"({suite_dir / 'runs' / '*' / folder_name(job.planner)}-seed*)")


def run_job(job: Job, threads: int | None = None) -> dict:
    """Run (or resume) one job; returns a short status. Runs inside a worker process."""
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


def finished_record(job: Job) -> dict | None:
    """The job's run record if that run finished *with the job's settings*.

    A run in the folder with other settings (the suite or the profile changed)
    is not this job's: it is not skipped (the run then refuses the folder) nor
    reported.
    """
    rec = _recorded(job)
    if rec is None or not rec["finished"]:
        return None
    if job.content_hash is not None and rec.get("content_hash") != job.content_hash:
        return None  # the scene changed since
    if rec.get("planner_digest") != job.planner_digest:
        return None  # the planner's code changed since
    return rec if same_config(rec["config"], job.config, compare_scene=job.content_hash is None) else None
