"""``mitsuba-active scene``: author a Mitsuba scene around a mesh."""

from __future__ import annotations

import click

from ..errors import UserError
from ..scene import DEFAULT_COLOR, LOOKS, UP_AXES, SceneOptions, authoring_notes, scene_from_mesh
from .common import Choice, Command, one_line_errors


@click.command(cls=Command)
@click.argument("mesh", type=click.Path())  # a folder gets the command's own one-line error
@click.option("-o", "--output", "out", required=True, type=click.Path(),
              help="Scene XML to write; the normalised mesh (PLY) and texture go beside it.")
@click.option("--up", type=Choice(UP_AXES), default=SceneOptions.up, show_default=True,
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
@click.option("--look", type=Choice(list(LOOKS)), default=SceneOptions.look, show_default=True,
              help="plain: the lights above; contrast: a stronger sun from the side, and a mid-tone grey where "
                   "neither --color nor the mesh gives a colour.")
@click.option("--floor", is_flag=True, help="Add a floor under the object.")
@click.option("--two-sided", is_flag=True,
              help="Reflect on both sides of the surface (else its back is black, as an open mesh shows).")
@one_line_errors
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

