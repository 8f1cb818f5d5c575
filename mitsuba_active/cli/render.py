"""``mitsuba-active render``: ground-truth views of a scene, and the rig options it shares with ``plan``."""

from __future__ import annotations

from pathlib import Path

import click

from ..errors import UserError
from ..renders import render_views
from ..rigs import RIG_KINDS, auto_rig
from ..scenes import BUNDLED_SCENE
from ..sources import SceneSource
from .common import Choice, Command, given_options, one_line_errors


def rig_options(fn):
    for opt in reversed([
        click.option("--rig", type=Choice(RIG_KINDS),
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


def check_rig_options(rig: str) -> None:
    """UserError for a rig option given on the command line that the rig ignores."""
    if rig == "xml" and "n_candidates" in given_options():
        raise UserError("--candidates does not apply to --rig xml: the scene's own sensors are the candidates")


@click.command(cls=Command)
@click.argument("scene_xml", required=False, type=click.Path())
@click.option("-o", "--output", "out", required=True, type=click.Path(file_okay=False), help="Output folder.")
@rig_options
@click.option("--views", type=int, default=None, help="Render only the first N views of the split [all].")
@click.option("--split", type=Choice(["candidates", "heldout"]), default="candidates", show_default=True,
              help="The views to render: the candidates, or the held-out views runs are scored on.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@one_line_errors
def render(scene_xml, out, rig, n_candidates, n_heldout, resolution, fov, spp, views, split, quiet):
    """Render ground-truth RGB and distance of a scene's views into OUT.

    Each view is an EXR (RGB and distance) and PNG previews.

    SCENE_XML defaults to the bundled scene.
    """
    if not out.strip():  # '' would be the current folder
        raise UserError("-o/--output names no folder; give one, e.g. -o views")
    check_rig_options(rig)
    source = SceneSource.from_xml(scene_xml or BUNDLED_SCENE, rig, n_candidates, n_heldout, resolution, fov,
                                  spp=spp)
    cams = source.candidates if split == "candidates" else source.heldout
    if views is not None:
        if views <= 0:
            raise UserError(f"--views must be positive, got {views}")
        cams = cams[:views]
    out = Path(out)
    render_views(source, cams, split, out, progress=not quiet)
    for note in auto_rig_note(rig, source):
        click.echo(note, err=True)
    click.echo(f"wrote {len(cams)} view{'' if len(cams) == 1 else 's'} to {out}")


def auto_rig_note(rig: str, source) -> list[str]:
    """Which rig ``--rig auto`` chose for a scene, why, and how to choose another: a line, or none."""
    if rig != "auto" or not isinstance(source, SceneSource):
        return []
    chosen, why = auto_rig(source.scene)
    others = " or ".join(k for k in ("sphere", "hemisphere", "interior") if k != chosen)
    return [f"note: rig {chosen}, as {source.scene.path.name} is {why}; choose another with --rig {others}"]

