"""``mitsuba-active bench``: run a benchmark suite of scenes x planners x seeds, and report it."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import click

from ..bench import PROFILES, parse_overrides, run_suite
from ..errors import UserError
from ..executors import EXECUTORS, RAY_OPTION_NAMES, STORAGE, RayOptions
from ..field.config import FIELD_PRESETS
from ..imageio_utils import folder_name
from ..training import FIT_GAIN_DB, FLOOR_MARGIN_DB
from .common import OUT, Choice, Command, given_options, one_line_errors


def _ray_options(command):
    """``bench``'s options of :class:`~mitsuba_active.executors.RayOptions`, one for each of its fields."""
    types = {"address": str, "cpus_per_run": float, "gpus_per_run": float, "retries": int,
             "storage": Choice(list(STORAGE))}
    for f in reversed(fields(RayOptions)):
        command = click.option(RAY_OPTION_NAMES[f.name], f.name, type=types[f.name], default=f.default,
                               show_default=f.default is not None, help=f.metadata["help"])(command)
    return command


@click.command(cls=Command)
@click.argument("suite", type=click.Path(dir_okay=False))
@click.option("--out", "out", type=click.Path(file_okay=False), default=None,
              help="Suite folder [bench/SUITE-PROFILE, plus each --set]; finished runs there are kept and skipped "
                   "(with a larger budget in the suite file, they go on from the views they have).")
@click.option("--profile", type=Choice(list(PROFILES)), default="quick", show_default=True,
              help="quick: small images and few steps, one seed; full: paper-like settings, five seeds.")
@click.option("--workers", type=int, default=1, show_default=True,
              help="Parallel worker processes (--executor local).")
@click.option("--executor", type=Choice(list(EXECUTORS)), default="local", show_default=True,
              help="What runs the runs: " + "; ".join(f"{k}, {v}" for k, v in EXECUTORS.items()) + ".")
@_ray_options
@click.option("--seeds", default=None, help="Comma-separated seeds [the profile's].")
@click.option("--planners", default=None, help="Comma-separated planners [the suite's].")
@click.option("--scenes", default=None, help="Comma-separated scene names [all].")
@click.option("--field", "field_preset", type=Choice(list(FIELD_PRESETS)), default=None,
              help="The radiance field's preset for every run [the suite's, else the profile's].")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="A run setting over the suite's, for every run (repeatable): e.g. ensemble=4, "
                   "field.lr=0.02, planner_options.form=log. Use another --out for each variant.")
@click.option("--report-only", is_flag=True,
              help="Run nothing: write the tables and plots of the runs finished so far.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@one_line_errors
def bench(suite, out, profile, workers, executor, seeds, planners, scenes, field_preset, overrides, report_only,
          quiet, **ray_options):
    """Run a benchmark SUITE (TOML) of scenes x planners x seeds.

    Writes tables and plots of its finished runs into report/ in the suite folder (--out).
    """
    given = given_options()
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
    click.get_current_context().meta[OUT] = out
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


