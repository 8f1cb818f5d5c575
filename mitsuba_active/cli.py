"""The ``mitsuba-active`` command line.

Every command turns bad input (:class:`~mitsuba_active.errors.UserError`)
and files it cannot read or write (``OSError``) into one line on stderr and
exit code 2.
"""

from __future__ import annotations

import functools
import os
import signal
import sys
import threading
import warnings
from dataclasses import fields
from pathlib import Path

from .interrupts import interruptible_imports, interrupts_deferred, sigterm_as_interrupt

with interruptible_imports():  # click, numpy and the libraries below load here, after the package's own imports
    import click
    from click.core import ParameterSource
    from tqdm import tqdm

    from .bench import PROFILES, parse_overrides, run_suite
    from .checks import nearest, setting_value
    from .console import mitsuba_log_as_warnings, one_line, show_warning
    from .embodiments import EMBODIMENTS
    from .errors import FolderError, UserError, os_error_line
    from .executors import EXECUTORS, RAY_OPTION_NAMES, STORAGE, RayOptions
    from .export import export_transforms
    from .field.config import DEFAULT_PRESET, FIELD_PRESETS
    from .imageio_utils import folder_name
    from .planners import make_planner
    from .planners.base import registered_name
    from .renders import render_views
    from .report import _plt
    from .rigs import RIG_KINDS, auto_rig
    from .run import INTERIOR_DISTANCE_WEIGHT, Run, RunConfig, default_out_dir, undone_unless_resumable
    from .scene import (DEFAULT_COLOR, LOOKS, MESH_SUFFIXES, UP_AXES, SceneOptions, authoring_notes,
                        content_hash, scene_from_mesh)
    from .scenes import BUNDLED_SCENE
    from .sources import SceneSource
    from .training import FIT_GAIN_DB, FLOOR_MARGIN_DB
    from .travel import CANDIDATE_MODES, TRAVEL_SETTINGS
    from .viewer import serve


#: Where a command keeps the output folder it writes (``ctx.meta``), once its default is filled in.
_OUT = "mitsuba_active.out"


def _output_option() -> tuple[str, Path] | None:
    """The current command's option that names its output (``--out``, ``-o/--output``) and the path it names."""
    ctx = click.get_current_context(silent=True)
    option = next((p for p in ctx.command.params if p.name == "out"), None) if ctx else None
    path = ctx.meta.get(_OUT, ctx.params.get("out")) if option else None
    return ("/".join(option.opts), Path(path)) if path is not None else None


def _naming_output(paths, around: bool) -> str | None:
    """``--out runs/x`` when one of ``paths`` is the current command's output
    (with ``around``, also a path inside it or above it); else None."""
    output = _output_option()
    if output is None:
        return None
    option, out = output
    target = Path(os.path.abspath(out))
    for p in paths:
        if isinstance(p, (str, os.PathLike)):
            p = Path(os.path.abspath(p))
            if p == target or (around and (target in p.parents or p in target.parents)):
                return f"{option} {out}"
    return None


def _error_line(exc: Exception) -> str:
    """The line that reports a UserError or an OSError, naming the output's option when it is about the output."""
    if isinstance(exc, FolderError):
        named = _naming_output([exc.folder], around=False)
        return f"{named}: {exc.reason}" if named else str(exc)
    if isinstance(exc, OSError):
        line = os_error_line(exc)
        named = _naming_output([exc.filename, exc.filename2], around=True)
        return f"{named}: {line}" if named else line
    return str(exc)


def _load_libraries() -> None:
    """Load the libraries that the package loads when first used, trimesh and
    matplotlib's pyplot (with its file-only backend), with Ctrl-C held back (see
    :mod:`.interrupts`) and SIGTERM handled: an interrupt then stops the
    command cleanly, not an import halfway (trimesh's imports swallow it, and
    a swallowed interrupt ends the process by SIGINT after a successful command)."""
    import trimesh  # noqa: F401  (here, not above: under the command's SIGTERM handler)

    _plt()


def _close_progress_bars() -> None:
    """Close the progress bars an interruption left open, so that the next message starts a line of its own."""
    tqdm = sys.modules.get("tqdm")
    for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", ())):
        bar.close()


def _caused_by_interrupt(exc) -> bool:
    """Whether ``exc`` is, or wraps, a KeyboardInterrupt: Dr.Jit's loops and
    custom operations re-raise what their Python bodies raised (Ctrl-C, or
    SIGTERM through :func:`~.interrupts.sigterm_as_interrupt`) as a RuntimeError caused by it."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def _one_line_errors(fn):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if sys.stderr is None:  # started with stderr closed (2>&-): progress bars and messages go nowhere
            sys.stderr = open(os.devnull, "w")
        # Signal handlers belong to the main thread (a command may be invoked from another).
        handled = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGTERM, sigterm_as_interrupt) if handled else None
        try:
            with warnings.catch_warnings(), mitsuba_log_as_warnings():
                warnings.showwarning = show_warning
                with interrupts_deferred():
                    _load_libraries()
                return fn(*args, **kwargs)
        # OSError: an output folder that cannot be created or written, a full disk...
        except (UserError, OSError) as exc:
            click.echo(f"mitsuba-active: error: {one_line(_error_line(exc))}", err=True)
            sys.exit(2)
        except (KeyboardInterrupt, RuntimeError) as exc:
            if not _caused_by_interrupt(exc):
                raise
            _close_progress_bars()
            click.echo("mitsuba-active: interrupted", err=True)
            # An interrupt that landed inside exec() of a source string (dataclasses
            # make their methods so, during a late import) leaves CPython's flag for
            # an unhandled KeyboardInterrupt set, and under `python -m` the process
            # would then end by SIGINT instead of this exit code. Each exec() of a
            # string starts by clearing that flag.
            exec("None")
            sys.exit(130)
        finally:
            if handled:  # None: a handler not set from Python, which cannot be put back
                signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)
    return wrapper


class _Choice(click.Choice):
    """A choice given in any case (``--rig Sphere``); a mistyped one is answered with the nearest choice."""

    def __init__(self, choices):
        super().__init__(choices, case_sensitive=False)

    def get_invalid_choice_message(self, value, ctx) -> str:
        near = nearest(value, self.choices)
        return super().get_invalid_choice_message(value, ctx) + (f" (Did you mean '{near}'?)" if near else "")


class _Command(click.Command):
    """A command whose summary in ``mitsuba-active --help`` is its docstring's first sentence whole."""

    def get_short_help_str(self, limit: int = 45) -> str:
        return super().get_short_help_str(limit=1000)  # click cuts it to fit the terminal, with "..."


class _Commands(click.Group):
    """The commands, each a :class:`_Command`."""

    command_class = _Command


@click.group(cls=_Commands, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mitsuba-active")
def main():
    """Active view planning of radiance fields with Mitsuba 3 and Dr.Jit."""


@main.command()
@click.argument("mesh", type=click.Path())  # a folder gets the command's own one-line error
@click.option("-o", "--output", "out", required=True, type=click.Path(),
              help="Scene XML to write; the normalised mesh (PLY) and texture go beside it.")
@click.option("--up", type=_Choice(UP_AXES), default=SceneOptions.up, show_default=True,
              help="The mesh's up axis; auto: the axis its shape rests on a flat base across, else y (said in "
                   "a note).")
@click.option("--color", nargs=3, type=float, default=None,
              help="Diffuse RGB reflectance when the mesh has no texture or vertex colours. "
                   "Default: its materials' colours (OBJ Kd, glTF baseColorFactor), else "
                   f"{' '.join(f'{c:g}' for c in DEFAULT_COLOR)}.")
@click.option("--texture", type=click.Path(), default=None,
              help="Texture image (the mesh needs UVs). Default: the mesh's own, else its vertex colours, "
                   "if any.")
@click.option("--no-texture", is_flag=True,
              help="Ignore the mesh's texture and vertex colours: one diffuse colour (--color, else its "
                   "material's if it has just one).")
@click.option("--env-radiance", type=float, default=SceneOptions.env_radiance, show_default=True,
              help="Constant environment light; also the background's colour.")
@click.option("--sun/--no-sun", default=SceneOptions.sun, show_default=True,
              help="A directional sun light from above, which shades the object.")
@click.option("--point-lights", type=click.IntRange(0, 16), default=0, show_default=True,
              help="Point lights spread on a ring above the object.")
@click.option("--look", type=_Choice(list(LOOKS)), default=SceneOptions.look, show_default=True,
              help="plain: the lights above; contrast: a stronger sun from the side, and a mid-tone grey where "
                   "neither --color nor the mesh gives a colour.")
@click.option("--floor", is_flag=True, help="Add a floor under the object.")
@click.option("--two-sided", is_flag=True,
              help="Reflect on both sides of the surface (else its back is black, as an open mesh shows).")
@_one_line_errors
def scene(mesh, out, up, color, texture, no_texture, env_radiance, sun, point_lights, look, floor, two_sided):
    """Author a Mitsuba scene XML around a mesh.

    MESH is an OBJ, PLY, STL, GLB, glTF or OFF file.
    """
    if texture is not None and no_texture:
        raise UserError("give --texture FILE or --no-texture, not both")
    path = scene_from_mesh(mesh, out, up=up, color=None if color is None else tuple(color),
                           texture=False if no_texture else texture, env_radiance=env_radiance, sun=sun,
                           point_lights=point_lights, look=look, floor=floor, two_sided=two_sided)
    for note in authoring_notes(path):
        click.echo(note, err=True)
    click.echo(f"wrote {path}")


def _rig_options(fn):
    for opt in reversed([
        click.option("--rig", type=_Choice(RIG_KINDS),
                     default="auto", show_default=True,
                     help="Candidate cameras: generated around (or, for rooms, inside) the scene, or the XML's own."),
        click.option("--candidates", "n_candidates", type=int, default=100, show_default=True,
                     help="Number of candidate views."),
        click.option("--heldout", "n_heldout", type=int, default=20, show_default=True,
                     help="Number of held-out evaluation views."),
        click.option("--resolution", type=int, default=64, show_default=True,
                     help="Image width and height (--rig xml: width; the sensors' films set the aspect)."),
        click.option("--fov", type=float, default=None, help="Horizontal field of view in degrees [40, rooms 70]."),
        click.option("--spp", type=int, default=64, show_default=True, help="Samples per pixel of ground truth."),
    ]):
        fn = opt(fn)
    return fn


def _travel_options(fn):
    """plan's options of :data:`~mitsuba_active.travel.TRAVEL_SETTINGS`, named as the settings are."""
    for name, (default, text) in reversed(TRAVEL_SETTINGS.items()):
        kind = {"embodiment": _Choice(list(EMBODIMENTS)), "candidates_mode": _Choice(list(CANDIDATE_MODES))}.get(
            name, float)
        fn = click.option(f"--{name.replace('_', '-')}", name, type=kind, default=default,
                          show_default=default is not None, help=text)(fn)
    return fn


def _check_rig_options(rig: str) -> None:
    """UserError for a rig option given on the command line that the rig ignores."""
    if rig == "xml" and "n_candidates" in _given_options():
        raise UserError("--candidates does not apply to --rig xml: the scene's own sensors are the candidates")


@main.command()
@click.argument("scene_xml", required=False, type=click.Path())
@click.option("-o", "--output", "out", required=True, type=click.Path(file_okay=False), help="Output folder.")
@_rig_options
@click.option("--views", type=int, default=None, help="Render only the first N views of the split [all].")
@click.option("--split", type=_Choice(["candidates", "heldout"]), default="candidates", show_default=True,
              help="The views to render: the candidates, or the held-out views runs are scored on.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@_one_line_errors
def render(scene_xml, out, rig, n_candidates, n_heldout, resolution, fov, spp, views, split, quiet):
    """Render ground-truth RGB and distance of a scene's views into OUT.

    Each view is an EXR (RGB and distance) and PNG previews.

    SCENE_XML defaults to the bundled scene.
    """
    if not out.strip():  # '' would be the current folder
        raise UserError("-o/--output names no folder; give one, e.g. -o views")
    _check_rig_options(rig)
    source = SceneSource.from_xml(scene_xml or BUNDLED_SCENE, rig, n_candidates, n_heldout, resolution, fov,
                                  spp=spp)
    cams = source.candidates if split == "candidates" else source.heldout
    if views is not None:
        if views <= 0:
            raise UserError(f"--views must be positive, got {views}")
        cams = cams[:views]
    out = Path(out)
    render_views(source, cams, split, out, progress=not quiet)
    for note in _auto_rig_note(rig, source):
        click.echo(note, err=True)
    click.echo(f"wrote {len(cams)} view{'' if len(cams) == 1 else 's'} to {out}")


def _parse_options(items) -> dict:
    """``NAME=VALUE`` strings to a dict; values are read as ``bench --set`` reads them (TOML, else text)."""
    options = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise UserError(f"--planner-option takes NAME=VALUE, got '{item}'")
        if name in options:  # which one was meant?
            raise UserError(f"--planner-option {name} is given twice; give it once")
        options[name] = setting_value(text)
    return options


def _parse_counts(text: str) -> list[int]:
    try:
        counts = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"--eval-views takes comma-separated view counts, got '{text}'") from None
    if not counts or min(counts) <= 0:
        raise UserError(f"--eval-views needs positive view counts, got '{text}'")
    return counts


@main.command()
@click.argument("scene_path", required=False, type=click.Path())
@click.option("--planner", default="rfe", show_default=True,
              help="View planner: rfe, fisher, variational, coverage, even or random; one of your own as FILE.py:CLASS "
                   "(see examples/custom_planner.py).")
@click.option("--budget", type=int, default=20, show_default=True, help="Views captured in total.")
@click.option("--initial-views", type=int, default=2, show_default=True, help="Random views before planning.")
@click.option("--ensemble", type=int, default=2, show_default=True, help="Fields K in the planner's ensemble.")
@click.option("--batch", type=int, default=1, show_default=True, help="Views chosen per round.")
@click.option("--seed", type=click.IntRange(0, 2**31 - 1), default=0, show_default=True,
              help="Seeds the initial views, the planner's randomness and every field.")
@_rig_options
@click.option("--downscale", type=int, default=None, help="Image downscale of a dataset [to fit --resolution].")
@click.option("--rays-per-candidate", type=int, default=256, show_default=True,
              help="Sparse rays scored per candidate view.")
@click.option("--score", "score_form", type=_Choice(["sum", "log"]), default="sum", show_default=True,
              help="rfe: sum of variances or sum of log-variances.")
@click.option("--planner-option", "planner_option", multiple=True, metavar="NAME=VALUE",
              help="A planner setting, e.g. fisher's lam=0.1 or probes=2 (repeatable).")
@click.option("--steps-per-view", type=int, default=None,
              help="Ensemble training steps per captured view (warm start) [50].")
@click.option("--eval-views", default="5,10,15,20", show_default=True, help="View counts to evaluate at.")
@click.option("--eval-steps", type=int, default=None, help="Training steps of each evaluation field [1500].")
@click.option("--field", "field_preset", type=_Choice(list(FIELD_PRESETS)), default=DEFAULT_PRESET,
              show_default=True, help="The radiance fields' preset: "
                                      + "; ".join(f"{k}: {p.summary}" for k, p in FIELD_PRESETS.items()) + ".")
@click.option("--distance-weight", type=float, default=0.0, show_default=True,
              help="Weight of the distance loss (0: photometric only).")
@_travel_options
@click.option("--out", "out", type=click.Path(file_okay=False), default=None,
              help="Run folder [runs/SCENE-PLANNER-seedN]; an unfinished run there is resumed, a finished one "
                   "given a larger --budget goes on from the views it has.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
@_one_line_errors
def plan(scene_path, planner, budget, initial_views, ensemble, batch, seed, rig, n_candidates, n_heldout,
         resolution, fov, spp, downscale, rays_per_candidate, score_form, planner_option, steps_per_view, eval_views,
         eval_steps, field_preset, distance_weight, out, quiet, **travel):
    """Choose views of SCENE_PATH with a planner; score the reconstruction.

    SCENE_PATH is a Mitsuba scene XML, a mesh (a scene is authored around
    it with the defaults of `mitsuba-active scene`, in OUT/scene), a
    transforms.json (or a folder holding one), a COLMAP project folder
    (sparse/0 and images/), or nothing for the bundled scene. Writes run.json, metrics.csv, plots, a contact sheet of the chosen
    views and held-out renders.
    """
    scene_path = str(scene_path or BUNDLED_SCENE)
    planner = registered_name(planner)  # in any case: --planner RFE is rfe
    given = _given_options()
    _check_rig_options(rig)
    if planner != "rfe" and "score_form" in given:
        raise UserError(f"--score applies to the rfe planner only, not to {planner}")
    parsed = _parse_options(planner_option)
    if "score_form" in given and "form" in parsed:
        raise UserError("give rfe's score once: --score or --planner-option form=...")
    options = {"form": score_form} if planner == "rfe" else {}
    options.update(parsed)
    chosen = make_planner(planner, **options)  # unknown planner: fail before any rendering
    if "ensemble" in given:
        if not chosen.needs_ensemble:
            raise UserError(f"--ensemble does not apply to the {planner} planner, which trains no ensemble")
        if chosen.max_members is not None and ensemble > chosen.max_members:
            raise UserError(f"the {planner} planner trains {chosen.max_members} field; "
                            f"--ensemble {ensemble} does not apply")
    cfg = RunConfig(scene=scene_path, planner=planner, planner_options=options, budget=budget,
                    initial_views=initial_views, ensemble=ensemble, batch=batch, seed=seed,
                    resolution=resolution, candidates=n_candidates, heldout=n_heldout, rig=rig, fov=fov, spp=spp,
                    downscale=downscale, rays_per_candidate=rays_per_candidate,
                    eval_views=_parse_counts(eval_views), distance_weight=distance_weight,
                    field_preset=field_preset, **travel)
    if steps_per_view is not None:
        cfg.steps_per_view = steps_per_view
    if eval_steps is not None:
        cfg.eval_steps = eval_steps
    cfg.validate()
    dropped = sorted(set(cfg.eval_views) - set(cfg.report_counts()))
    if dropped and "eval_views" in given:
        click.echo(f"note: --eval-views {', '.join(map(str, dropped))} left out: below the {cfg.initial_views} "
                   f"initial views or above the budget of {cfg.budget}", err=True)
    out = Path(out) if out else default_out_dir(scene_path, planner, seed)
    click.get_current_context().meta[_OUT] = out
    with undone_unless_resumable(out):
        notes = []
        if Path(scene_path).suffix.lower() in MESH_SUFFIXES:
            scene_path = cfg.scene = _author_into_run(scene_path, out)
            notes = authoring_notes(scene_path)
        record = _plan(cfg, out, quiet, given, notes)
    rows = ", ".join(f"{m['views']}: {m['psnr']:.2f} dB (foreground "
                     + ("n/a)" if m.get("psnr_fg") is None else f"{m['psnr_fg']:.2f} dB)") for m in record["metrics"])
    click.echo(f"held-out PSNR by views captured: {rows}")
    click.echo(f"results in {out}")


def _author_into_run(mesh, out: Path) -> str:
    """Author the scene of a mesh in ``OUT/scene``; returns its XML path.

    A folder holding a run of another scene is refused before its scene is replaced.
    """
    target = out / "scene" / f"{Path(mesh).stem}.xml"

    def same_scene(digest: str) -> None:
        # Authoring is deterministic: the run's own scene comes out the same.
        if (out / "run.json").is_file() and not (target.is_file() and content_hash(target) == digest):
            raise FolderError(out, "holds a run of another scene; choose another run folder")

    return str(scene_from_mesh(mesh, target, check=same_scene))


def _given_options() -> set[str]:
    """Names of the current command's options given on the command line (not defaults)."""
    ctx = click.get_current_context()
    return {name for name in ctx.params if ctx.get_parameter_source(name) is ParameterSource.COMMANDLINE}


def _auto_rig_note(rig: str, source) -> list[str]:
    """Which rig ``--rig auto`` chose for a scene, why, and how to choose another: a line, or none."""
    if rig != "auto" or not isinstance(source, SceneSource):
        return []
    chosen, why = auto_rig(source.scene)
    others = " or ".join(k for k in ("sphere", "hemisphere", "interior") if k != chosen)
    return [f"note: rig {chosen}, as {source.scene.path.name} is {why}; choose another with --rig {others}"]


def _plan(cfg, out: Path, quiet: bool, given=frozenset(), notes=()) -> dict:
    """Open the scene or dataset ``cfg.scene`` and run (or resume) the run in ``out``.

    ``given``: the options given on the command line, which must apply; ``notes``: lines to
    print as the run starts."""
    source = cfg.open_source()
    if cfg.downscale is not None and isinstance(source, SceneSource):
        raise UserError("--downscale applies to datasets; a scene renders at --resolution")
    if not isinstance(source, SceneSource):
        if "spp" in given:
            raise UserError("--spp applies to scenes; a dataset's images are as they were captured")
        for name, flag, asked, kept, kind in (
                ("n_candidates", "--candidates", cfg.candidates, len(source.candidates), "training"),
                ("n_heldout", "--heldout", cfg.heldout, len(source.heldout), "held-out")):
            if name in given and asked > kept:
                click.echo(f"note: {source.name} has {kept} {kind} frames; {flag} {asked} uses all of them",
                           err=True)
    if cfg.rig == "interior" and isinstance(source, SceneSource) and not source.scene.interior:
        click.echo(f"note: {Path(cfg.scene).name} is an object seen from outside; --rig interior puts the "
                   "cameras inside its bounding box", err=True)
    if cfg.distance_weight == 0 and isinstance(source, SceneSource) and source.scene.interior:
        # Colour alone leaves a sparse-view field free to fill a room with fog (see docs/cli.md).
        click.echo(f"note: {Path(cfg.scene).name} is a room seen from inside, which fits far better "
                   f"with the distance maps: try --distance-weight {INTERIOR_DISTANCE_WEIGHT:g}", err=True)
    # tqdm.write keeps a line from landing on a progress bar that is being drawn.
    return Run(source, cfg, out, progress=not quiet, log=lambda m: tqdm.write(m, file=sys.stderr),
               notes=[*notes, *_auto_rig_note(cfg.rig, source)]).execute()


@main.command()
@click.argument("run_dir", type=click.Path(file_okay=False))
@click.option("-o", "--output", "out", type=click.Path(file_okay=False), default=None,
              help="Dataset folder [RUN_DIR/export].")
@_one_line_errors
def export(run_dir, out):
    """Export a run's chosen and held-out views as a transforms.json dataset.

    The dataset reads in nerfstudio and instant-ngp, split as the run was.
    """
    click.echo(f"wrote {export_transforms(run_dir, out)}")


def _ray_options(command):
    """``bench``'s options of :class:`~mitsuba_active.executors.RayOptions`, one for each of its fields."""
    types = {"address": str, "cpus_per_run": float, "gpus_per_run": float, "retries": int,
             "storage": _Choice(list(STORAGE))}
    for f in reversed(fields(RayOptions)):
        command = click.option(RAY_OPTION_NAMES[f.name], f.name, type=types[f.name], default=f.default,
                               show_default=f.default is not None, help=f.metadata["help"])(command)
    return command


@main.command()
@click.argument("run_dir", type=click.Path())
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to serve on (0.0.0.0: every one).")
@click.option("--port", type=int, default=8080, show_default=True,
              help="Port to serve on (the next free one if taken).")
@click.option("--follow", is_flag=True, help="Redraw as a plan writes the folder.")
@_one_line_errors
def view(run_dir, host, port, follow):
    """Show a run in the browser: its cameras, each round's scores, its captures.

    Clicking a camera renders the planner's ensemble's mean and variance from it. Needs
    the viewer extra: pip install 'mitsuba-active[viewer]'.
    """
    serve(run_dir, host, port, follow, log=lambda m: click.echo(m, err=True))


@main.command()
@click.argument("suite", type=click.Path(dir_okay=False))
@click.option("--out", "out", type=click.Path(file_okay=False), default=None,
              help="Suite folder [bench/SUITE-PROFILE, plus each --set]; finished runs there are kept and skipped "
                   "(with a larger budget in the suite file, they go on from the views they have).")
@click.option("--profile", type=_Choice(list(PROFILES)), default="quick", show_default=True,
              help="quick: small images and few steps, one seed; full: paper-like settings, five seeds.")
@click.option("--workers", type=int, default=1, show_default=True,
              help="Parallel worker processes (--executor local).")
@click.option("--executor", type=_Choice(list(EXECUTORS)), default="local", show_default=True,
              help="What runs the runs: " + "; ".join(f"{k}, {v}" for k, v in EXECUTORS.items()) + ".")
@_ray_options
@click.option("--seeds", default=None, help="Comma-separated seeds [the profile's].")
@click.option("--planners", default=None, help="Comma-separated planners [the suite's].")
@click.option("--scenes", default=None, help="Comma-separated scene names [all].")
@click.option("--field", "field_preset", type=_Choice(list(FIELD_PRESETS)), default=None,
              help="The radiance field's preset for every run [the suite's, else the profile's].")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="A run setting over the suite's, for every run (repeatable): e.g. ensemble=4, "
                   "field.lr=0.02, planner_options.form=log. Use another --out for each variant.")
@click.option("--report-only", is_flag=True,
              help="Run nothing: write the tables and plots of the runs finished so far.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@_one_line_errors
def bench(suite, out, profile, workers, executor, seeds, planners, scenes, field_preset, overrides, report_only,
          quiet, **ray_options):
    """Run a benchmark SUITE (TOML) of scenes x planners x seeds.

    Writes tables and plots of its finished runs into report/ in the suite folder (--out).
    """
    given = _given_options()
    if executor != "ray":
        named = [RAY_OPTION_NAMES[k] for k in ray_options if k in given]
        if named:
            raise UserError(f"{named[0]} is for --executor ray")
    elif "workers" in given:
        raise UserError("--workers is for --executor local; Ray runs as many runs at once as its CPUs "
                        "allow (--cpus-per-run)")

    split = lambda s: [x.strip() for x in s.split(",") if x.strip()] if s else None  # noqa: E731
    for option, value in (("--seeds", seeds), ("--planners", planners), ("--scenes", scenes)):
        if value is not None and not split(value):  # '' would otherwise mean all of them
            raise UserError(f"{option} names none; leave it out for the suite's")
    try:
        seed_list = [int(x) for x in split(seeds)] if seeds else None
    except ValueError:
        raise UserError(f"--seeds takes comma-separated integers, got '{seeds}'") from None
    if field_preset is not None:
        overrides = (f"field_preset={field_preset}", *overrides)
    if not out:
        # Each variant of a suite gets a folder of its own: a folder's finished
        # runs are kept only when their settings match.
        tag = "".join("-" + folder_name(o) for o in overrides)
        out = Path("bench") / f"{Path(suite).stem}-{profile}{tag}"
    out = Path(out)
    click.get_current_context().meta[_OUT] = out
    summary = run_suite(suite, out, profile, workers, seed_list, split(planners), split(scenes),
                        progress=not quiet, report_only=report_only, overrides=parse_overrides(overrides),
                        log=lambda m: click.echo(f"note: {m}", err=True), executor=executor,
                        ray=RayOptions(**ray_options) if executor == "ray" else None)
    if summary["unreported_seeds"]:
        others = ",".join(map(str, summary["unreported_seeds"]))
        click.echo(f"note: {out} also holds finished runs of seed{'s' if ',' in others else ''} {others}, "
                   "which this report leaves out: name every seed to report with --seeds", err=True)
    if not summary["cells"]:
        click.echo(f"note: no finished runs with these settings in {out} yet: no report written", err=True)
    else:
        if summary["runs_reported"] < summary["runs"]:
            # Only --report-only gets here: a suite that runs finishes every job or stops with an error.
            click.echo(f"note: the report covers {summary['runs_reported']} of the suite's {summary['runs']} runs; "
                       "the others have not finished with these settings and planner code", err=True)
        if summary["short_training"]:
            click.echo(f"note: in {summary['short_training']} of the reported runs the evaluation field scores less "
                       f"than {FLOOR_MARGIN_DB:g} dB above the background colour alone on the held-out views, or fits "
                       f"its own training views less than {FIT_GAIN_DB:g} dB better than at its first steps: raise "
                       "eval_steps for scores that compare the planners", err=True)
        if len(summary["versions"]) > 1:
            click.echo(f"note: the reported runs were made with {len(summary['versions'])} different versions of "
                       "mitsuba-active, Mitsuba or Dr.Jit (see versions in report/results.json)", err=True)
        click.echo(f"tables and plots in {out / 'report'}")


if __name__ == "__main__":
    main()
