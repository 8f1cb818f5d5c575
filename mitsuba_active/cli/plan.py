"""``mitsuba-active plan``: choose views of a scene with a planner, and score the reconstruction."""

from __future__ import annotations

import sys
from pathlib import Path

import click
from tqdm import tqdm

from ..checks import setting_value
from ..embodiments import EMBODIMENTS
from ..errors import FolderError, UserError
from ..field.config import DEFAULT_PRESET, FIELD_PRESETS
from ..planners import make_planner
from ..planners.base import registered_name
from ..run import INTERIOR_DISTANCE_WEIGHT, Run, RunConfig, default_out_dir, undone_unless_resumable
from ..scene import MESH_SUFFIXES, authoring_notes, content_hash, scene_from_mesh
from ..scenes import BUNDLED_SCENE
from ..sources import SceneSource
from ..travel import CANDIDATE_MODES, TRAVEL_SETTINGS
from .common import OUT, Choice, Command, given_options, one_line_errors
from .render import auto_rig_note, check_rig_options, rig_options


def _travel_options(fn):
    """plan's options of :data:`~mitsuba_active.travel.TRAVEL_SETTINGS`, named as the settings are."""
    for name, (default, text) in reversed(TRAVEL_SETTINGS.items()):
        kind = {"embodiment": Choice(list(EMBODIMENTS)), "candidates_mode": Choice(list(CANDIDATE_MODES))}.get(
            name, float)
        fn = click.option(f"--{name.replace('_', '-')}", name, type=kind, default=default,
                          show_default=default is not None, help=text)(fn)
    return fn


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


@click.command(cls=Command)
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
@rig_options
@click.option("--downscale", type=int, default=None, help="Image downscale of a dataset [to fit --resolution].")
@click.option("--rays-per-candidate", type=int, default=256, show_default=True,
              help="Sparse rays scored per candidate view.")
@click.option("--score", "score_form", type=Choice(["sum", "log"]), default="sum", show_default=True,
              help="rfe: sum of variances or sum of log-variances.")
@click.option("--planner-option", "planner_option", multiple=True, metavar="NAME=VALUE",
              help="A planner setting, e.g. fisher's lam=0.1 or probes=2 (repeatable).")
@click.option("--steps-per-view", type=int, default=None,
              help="Ensemble training steps per captured view (warm start) [50].")
@click.option("--eval-views", default="5,10,15,20", show_default=True, help="View counts to evaluate at.")
@click.option("--eval-steps", type=int, default=None, help="Training steps of each evaluation field [1500].")
@click.option("--field", "field_preset", type=Choice(list(FIELD_PRESETS)), default=DEFAULT_PRESET,
              show_default=True, help="The radiance fields' preset: "
                                      + "; ".join(f"{k}: {p.summary}" for k, p in FIELD_PRESETS.items()) + ".")
@click.option("--distance-weight", type=float, default=0.0, show_default=True,
              help="Weight of the distance loss (0: photometric only).")
@_travel_options
@click.option("--out", "out", type=click.Path(file_okay=False), default=None,
              help="Run folder [runs/SCENE-PLANNER-seedN]; an unfinished run there is resumed, a finished one "
                   "given a larger --budget goes on from the views it has.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
@one_line_errors
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
    given = given_options()
    check_rig_options(rig)
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
    if "nearest" in given and cfg.candidates_mode != "continuous":
        raise UserError("--nearest applies to continuous candidates (--candidates-mode continuous); "
                        "a pool's poses stay where the rig put them")
    dropped = sorted(set(cfg.eval_views) - set(cfg.report_counts()))
    if dropped and "eval_views" in given:
        click.echo(f"note: --eval-views {', '.join(map(str, dropped))} left out: below the {cfg.initial_views} "
                   f"initial views or above the budget of {cfg.budget}", err=True)
    out = Path(out) if out else default_out_dir(scene_path, planner, seed)
    click.get_current_context().meta[OUT] = out
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
               notes=[*notes, *auto_rig_note(cfg.rig, source)]).execute()

