"""The ``mitsuba-active`` command line.

Every command turns bad input (:class:`~mitsuba_active.errors.UserError`)
into one line on stderr and exit code 2.
"""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import click

from .errors import UserError

from .scenes import BUNDLED_SCENE


def _one_line_errors(fn):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except UserError as exc:
            click.echo(f"mitsuba-active: error: {exc}", err=True)
            sys.exit(2)
        except KeyboardInterrupt:
            click.echo("mitsuba-active: interrupted", err=True)
            sys.exit(130)
    return wrapper


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mitsuba-active")
def main():
    """Active view planning of radiance fields with Mitsuba 3 and Dr.Jit."""


@main.command()
@click.argument("mesh", type=click.Path(dir_okay=False))
@click.option("-o", "--output", "out", required=True, type=click.Path(dir_okay=False),
              help="Scene XML to write; the normalised mesh (PLY) and texture go beside it.")
@click.option("--up", type=click.Choice(["y", "z"]), default="y", show_default=True, help="The mesh's up axis.")
@click.option("--color", nargs=3, type=float, default=(0.6, 0.6, 0.6), show_default=True,
              help="Diffuse RGB reflectance when the mesh has no texture.")
@click.option("--texture", type=click.Path(dir_okay=False), default=None,
              help="Texture image (the mesh needs UVs). Default: the mesh's own, if any.")
@click.option("--no-texture", is_flag=True, help="Ignore the mesh's texture.")
@click.option("--env-radiance", type=float, default=1.0, show_default=True, help="Constant environment light.")
@click.option("--sun", is_flag=True, help="Add a directional sun light.")
@click.option("--point-lights", type=click.IntRange(0, 16), default=0, show_default=True)
@click.option("--floor", is_flag=True, help="Add a floor under the object.")
@_one_line_errors
def scene(mesh, out, up, color, texture, no_texture, env_radiance, sun, point_lights, floor):
    """Author a Mitsuba scene XML around MESH (OBJ, PLY, STL, GLB)."""
    from .scene import scene_from_mesh

    path = scene_from_mesh(mesh, out, up=up, color=tuple(color), texture=False if no_texture else texture,
                           env_radiance=env_radiance, sun=sun, point_lights=point_lights, floor=floor)
    click.echo(f"wrote {path}")


def _rig_options(fn):
    for opt in reversed([
        click.option("--rig", type=click.Choice(["auto", "sphere", "hemisphere", "rings", "interior", "xml"]),
                     default="auto", show_default=True,
                     help="Candidate cameras: generated around (or, for rooms, inside) the scene, or the XML's own."),
        click.option("--candidates", "n_candidates", type=int, default=100, show_default=True,
                     help="Number of candidate views."),
        click.option("--heldout", "n_heldout", type=int, default=20, show_default=True,
                     help="Number of held-out evaluation views."),
        click.option("--resolution", type=int, default=64, show_default=True, help="Image width and height."),
        click.option("--fov", type=float, default=None, help="Horizontal field of view in degrees [40, rooms 70]."),
        click.option("--spp", type=int, default=64, show_default=True, help="Samples per pixel of ground truth."),
    ]):
        fn = opt(fn)
    return fn


@main.command()
@click.argument("scene_xml", required=False, type=click.Path(dir_okay=False))
@click.option("-o", "--output", "out", required=True, type=click.Path(file_okay=False), help="Output folder.")
@_rig_options
@click.option("--views", type=int, default=None, help="Render only the first N candidates [all].")
@click.option("--split", type=click.Choice(["candidates", "heldout"]), default="candidates", show_default=True)
@_one_line_errors
def render(scene_xml, out, rig, n_candidates, n_heldout, resolution, fov, spp, views, split):
    """Render ground-truth RGB and distance of a scene's views into OUT (EXR + PNG).

    SCENE_XML defaults to the bundled scene.
    """
    from tqdm import tqdm

    from .env import SceneSource
    from .imageio_utils import colorize, write_exr, write_png, srgb_to_linear

    source = SceneSource.from_xml(scene_xml or BUNDLED_SCENE, rig, n_candidates, n_heldout, resolution, fov,
                                  spp=spp)
    cams = source.candidates if split == "candidates" else source.heldout
    if views is not None:
        if views <= 0:
            raise UserError(f"--views must be positive, got {views}")
        cams = cams[:views]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    records = []
    for i, cam in enumerate(tqdm(cams, desc="rendering", unit="view")):
        v = source.groundtruth.render(cam)
        stem = f"{split[:4]}_{i:03d}"
        write_exr(out / f"{stem}.exr", {"RGB": srgb_to_linear(v.rgb), "Z": v.distance})
        write_png(out / f"{stem}.png", v.rgb)
        write_png(out / f"{stem}_distance.png", colorize(v.distance, v.mask))
        records.append({"file": f"{stem}.png", **cam.to_dict(), "intrinsics": cam.intrinsics().tolist()})
    from .imageio_utils import atomic_write

    with atomic_write(out / "cameras.json") as tmp:
        tmp.write_text(json.dumps({"scene": str(source.scene.path), "split": split, "views": records}, indent=1))
    click.echo(f"wrote {len(cams)} views to {out}")


if __name__ == "__main__":
    main()
