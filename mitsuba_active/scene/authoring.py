"""Authoring: a Mitsuba scene XML around a mesh, with its files landed beside it.

A generated scene is a Y-up world with the mesh normalised into the unit
bounding box ``[-0.5, 0.5]^3``, a diffuse (or textured) material, a
constant environment light and a sun, and optionally point lights and a floor.
The XML is plain Mitsuba 3 and loads with ``mitsuba.load_file`` alone.
"""

from __future__ import annotations

import dataclasses
import filecmp
import itertools
import os
import re
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..checks import is_number, is_whole
from ..errors import UserError
from ..imageio_utils import new_entries, remove_new
from .loading import content_hash, load_mitsuba, referenced_files
from .meshes import (DEFAULT_COLOR, appearance, embedded_image, load_mesh, named_textures, normalise_vertices,
                     write_ply)
from .upaxis import shown_up_axis

#: Half width of the authored floor, in units of the normalised object (which spans 1).
FLOOR_HALF_WIDTH = 0.8
#: Most point lights on the ring (as ``scene --point-lights`` allows), and the
#: deepest path tracer (Mitsuba reads the depth as a 32-bit integer).
MAX_POINT_LIGHTS = 16
MAX_DEPTH = 1024
#: Stands for "--" (an option's dashes) in an XML comment, which may not hold two hyphens.
COMMENT_DASHES = "\u2011\u2011"
#: What ``SceneOptions.up`` takes.
UP_AXES = ("auto", "y", "z")
#: What ``SceneOptions.look`` takes.
LOOKS = ("plain", "contrast")
#: The ``contrast`` look's sun: from the side and above, so that views from every height see light and
#: shade, and stronger than the plain look's; direction (towards the scene) and irradiance.
CONTRAST_SUN = ((-0.6, -0.5, -0.45), 4.0)
#: The ``contrast`` look's colour where neither ``color`` nor the mesh gives one: linear 0.25 grey,
#: mid-grey once shown in sRGB, dark against the environment's white and far from black in shade.
MID_TONE = (0.25, 0.25, 0.25)


@dataclass
class SceneOptions:
    """How :func:`scene_from_mesh` dresses a mesh.

    Attributes:
        up: the mesh's up axis, ``"y"`` or ``"z"``; the scene is Y-up.
            ``"auto"`` takes the axis the shape rests on a flat base across
            (:func:`~mitsuba_active.scene.upaxis.shown_up_axis`), else
            ``"y"``, and warns unless the shape showed Y.
        color: diffuse RGB reflectance in [0, 1] when there is no texture
            (or vertex colours); ``None`` takes the colours the mesh's
            materials give (an OBJ material's ``Kd``, a glTF material's
            ``baseColorFactor``, both linear), else
            :data:`~mitsuba_active.scene.meshes.DEFAULT_COLOR`
            (also for a part whose material gives none).
        texture: an image to use as the diffuse texture (needs UVs); ``None``
            looks for the mesh's own (its material, or ``<stem>_texture.png``
            beside it), else uses its vertex colours if it has them;
            ``False`` never textures and ignores vertex colours (and
            material colours, unless there is just one).
        env_radiance: radiance of the constant environment light, which is
            also the background's colour.
        sun: add a directional light from above, which shades the object.
        point_lights: number of point lights spread on a ring above the object.
        floor: add a diffuse floor under the object.
        two_sided: the object's material reflects on both sides of its
            surface; by default (as Mitsuba's ``diffuse``) the back of a
            surface renders black, which an open mesh shows through its holes.
        max_depth: path tracer depth.
        look: ``"plain"``, or ``"contrast"``: the sun (:data:`CONTRAST_SUN`) lights the object
            from the side, and where neither ``color`` nor the mesh gives a colour it is
            :data:`MID_TONE`, so that it stands out from the background and shows its shading.
    """

    up: str = "auto"
    color: tuple | None = None
    texture: str | bool | None = None
    env_radiance: float = 1.0
    sun: bool = True
    point_lights: int = 0
    floor: bool = False
    two_sided: bool = False
    max_depth: int = 6
    look: str = "plain"

    def __post_init__(self):
        if self.up not in UP_AXES:
            raise UserError(f"the up axis must be one of {', '.join(UP_AXES)}, got {self.up!r}")
        if self.look not in LOOKS:
            raise UserError(f"the look must be one of {', '.join(LOOKS)}, got {self.look!r}")
        if self.look == "contrast" and self.sun is False:
            raise UserError("the contrast look is lit by its sun: leave sun out, or choose the plain look")
        color = self.color
        if color is not None:
            if isinstance(color, str) or not hasattr(color, "__len__") or len(color) != 3 \
                    or not all(is_number(c, finite=True) and 0.0 <= c <= 1.0 for c in color):
                raise UserError(f"color must be three numbers in [0, 1], got {color!r}")
            self.color = tuple(float(c) for c in color)
        if self.texture is not False and not isinstance(self.texture, (str, os.PathLike, type(None))):
            raise UserError(f"texture must be an image path, false (none) or unset (the mesh's own), "
                            f"got {self.texture!r}")
        if not is_number(self.env_radiance, finite=True) or self.env_radiance < 0:
            raise UserError(f"env_radiance must be a number >= 0, got {self.env_radiance!r}")
        for name in ("sun", "floor", "two_sided"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise UserError(f"{name} must be true or false, got {getattr(self, name)!r}")
            setattr(self, name, bool(getattr(self, name)))
        for name, least, most in (("point_lights", 0, MAX_POINT_LIGHTS), ("max_depth", 1, MAX_DEPTH)):
            value = getattr(self, name)
            if not is_whole(value) or not least <= value <= most:
                raise UserError(f"{name} must be a whole number in [{least}, {most}], got {value!r}")


def _up_axis(mesh, mesh_path: Path) -> tuple[str, str | None]:
    """The up axis ``auto`` takes for a mesh, and a note saying so unless its shape plainly shows Y."""
    shown = shown_up_axis(mesh)
    if shown == "z":
        return "z", (f"{mesh_path.name} rests on a flat base across its z axis, so it was taken as Z-up "
                     "(--up y keeps its axes)")
    if shown is None:
        return "y", f"took y as the up axis of {mesh_path.name}, whose shape shows none (--up z if it is Z-up)"
    return "y", None


def authoring_notes(xml_path) -> list[str]:
    """The notes :func:`scene_from_mesh` left in a scene XML it wrote (as
    comments), such as the up axis it took: lines for the user."""
    return [n.replace(COMMENT_DASHES, "--")
            for n in re.findall(r"<!-- (note: .*?) -->", Path(xml_path).read_text(errors="replace"))]


def _replaceable(out_xml: Path, keep: set[Path]) -> set[Path]:
    """Files that authoring ``out_xml`` anew may replace: those the XML being
    replaced names that no other scene XML beside it names, except ``keep``
    (resolved paths: the input mesh and its own textures)."""
    def named_by(xml: Path) -> set[Path]:
        try:
            return set(referenced_files(xml))
        except UserError:  # not a scene, or damaged: it names nothing
            return set()

    if not out_xml.is_file():
        return set()
    own = named_by(out_xml)
    for other in out_xml.parent.glob("*.xml"):
        if own and other.resolve() != out_xml.resolve():
            own -= named_by(other)
    return own - keep


def _landing_name(staged: Path, out_dir: Path, name_for, replaceable: set[Path]) -> tuple[str, bool]:
    """The name ``staged`` will have in ``out_dir`` (it is renamed so in its
    staging folder), and whether ``out_dir`` holds that file already.

    The name is ``name_for(tag)`` with ``tag`` empty, or ``_scene``,
    ``_scene2``, ...: the first that is free in ``out_dir``, holds the same
    bytes there, or is ``replaceable`` (see :func:`_replaceable`). Any
    other file (the input mesh, its texture, a file of the user's or of
    another scene beside this one) is never replaced.
    """
    for k in itertools.count():
        name = name_for("" if k == 0 else "_scene" if k == 1 else f"_scene{k}")
        target = out_dir / name
        there = target.is_file() and filecmp.cmp(staged, target, shallow=False)
        if there or (not target.exists() and not target.is_symlink()) or target.resolve() in replaceable:
            staged.rename(staged.with_name(name))
            return name, there
    raise AssertionError("unreachable")


def _scene_xml(mesh_file: str, texture_file: str | None, color: tuple, opts: SceneOptions, bottom: float,
               vertex_colors: bool, notes: list[str]) -> str:
    """The scene XML's text; ``color``: the object's diffuse reflectance where it has no texture or
    vertex colours; ``bottom``: the object's lowest height (y), where a floor goes; ``notes``: lines
    for the user, kept as comments (:func:`authoring_notes`)."""
    c = " ".join(f"{x:g}" for x in color)
    if vertex_colors:
        bsdf = ('<bsdf type="diffuse"><texture type="mesh_attribute" name="reflectance">'
                '<string name="name" value="vertex_color"/></texture></bsdf>')
    elif texture_file:
        bsdf = (f'<bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
                f'<string name="filename" value="{texture_file}"/></texture></bsdf>')
    else:
        bsdf = f'<bsdf type="diffuse"><rgb name="reflectance" value="{c}"/></bsdf>'
    if opts.two_sided:
        bsdf = f'<bsdf type="twosided">{bsdf}</bsdf>'
    lines = [
        '<scene version="3.0.0">',
        '    <!-- Generated by mitsuba-active: Y-up, object in [-0.5, 0.5]^3 -->',
        *(f"    <!-- note: {n.replace('--', COMMENT_DASHES)} -->" for n in notes),
        '    <default name="spp" value="64"/>',
        '    <default name="res" value="256"/>',
        f'    <integrator type="path"><integer name="max_depth" value="{opts.max_depth}"/></integrator>',
        '    <sensor type="perspective">',
        '        <float name="fov" value="40"/>',
        '        <transform name="to_world"><lookat origin="1.2, 0.9, 2.2" target="0, 0, 0" up="0, 1, 0"/></transform>',
        '        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>',
        '        <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/>'
        '<rfilter type="box"/></film>',
        '    </sensor>',
        f'    <shape type="ply" id="object"><string name="filename" value="{mesh_file}"/>{bsdf}</shape>',
        f'    <emitter type="constant"><rgb name="radiance" value="{opts.env_radiance:g}"/></emitter>',
    ]
    if opts.sun and opts.look == "contrast":
        (x, y, z), irradiance = CONTRAST_SUN
        lines.append(f'    <emitter type="directional"><vector name="direction" x="{x:g}" y="{y:g}" z="{z:g}"/>'
                     f'<rgb name="irradiance" value="{irradiance:g}"/></emitter>')
    elif opts.sun:
        lines.append('    <emitter type="directional"><vector name="direction" x="-0.4" y="-1" z="-0.3"/>'
                     '<rgb name="irradiance" value="2.5"/></emitter>')
    for k in range(opts.point_lights):
        a = 2 * np.pi * k / opts.point_lights
        lines.append(f'    <emitter type="point"><point name="position" x="{2 * np.cos(a):.4f}" y="2" '
                     f'z="{2 * np.sin(a):.4f}"/><rgb name="intensity" value="3"/></emitter>')
    if opts.floor:
        # A platform a little wider than the object, just under its lowest point: a
        # wider floor would widen the scene's bounds, and with them the camera rig and
        # the fields' box.
        lines.append('    <shape type="rectangle" id="floor"><transform name="to_world"><rotate x="1" angle="-90"/>'
                     f'<scale value="{FLOOR_HALF_WIDTH}"/><translate y="{bottom - 0.001:.6g}"/></transform>'
                     '<bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>')
    lines.append("</scene>")
    return "\n".join(lines) + "\n"


def scene_from_mesh(mesh_path, out_xml, options: SceneOptions | None = None, *, check=None, **kwargs) -> Path:
    """Author a Mitsuba scene XML around a mesh; returns the XML path.

    The normalised mesh is written as ``<stem>.ply`` next to ``out_xml``,
    and its texture image, when it has one, as ``<stem>_texture.<ext>``.
    A file of that name with other content is replaced only when the XML
    being replaced names it and no other XML beside it does (nor is it the
    mesh or its own texture); else it is kept, and the scene's gets another
    name (``<stem>_scene.ply``, ``<stem>_scene2.ply``, ...). Either every
    file is written, or none is. ``kwargs`` override fields of :class:`SceneOptions`.

    With ``up="auto"``, the axis taken is noted in the XML unless the shape
    plainly shows Y (:func:`authoring_notes` reads the notes).

    ``check``, if given, is called with the new scene's :func:`content_hash`
    once it is authored and validated, before any of its files lands: it
    raises UserError to refuse the scene (a folder holding runs of another
    version of it), and then nothing is written or replaced.
    """
    known = {f.name for f in dataclasses.fields(SceneOptions)}
    unknown = sorted(set(kwargs) - known)
    if unknown:
        raise UserError(f"unknown scene option {', '.join(unknown)}; the options of SceneOptions are: "
                        f"{', '.join(sorted(known))}")
    opts = dataclasses.replace(options or SceneOptions(), **kwargs)  # checked by __post_init__
    if opts.env_radiance == 0 and not opts.sun and opts.point_lights == 0:
        warnings.warn("the scene has no light (no environment, sun or point lights): every view renders black",
                      stacklevel=2)
    if Path(out_xml).suffix.lower() != ".xml":  # also '' and a folder's name
        raise UserError(f"the scene file to write must end in .xml, got '{out_xml}'")
    mesh_path, out_xml = Path(mesh_path), Path(out_xml)
    mesh = load_mesh(mesh_path)
    up, up_note = _up_axis(mesh, mesh_path) if opts.up == "auto" else (opts.up, None)
    vertices = normalise_vertices(mesh.vertices, up)
    uv, texture, rgb, color = appearance(mesh, mesh_path, opts.texture, opts.color,
                                         MID_TONE if opts.look == "contrast" else DEFAULT_COLOR)

    out_dir = out_xml.parent if str(out_xml.parent) else Path(".")
    added = new_entries(out_dir)  # undone on failure
    out_dir.mkdir(parents=True, exist_ok=True)
    # Written names go into the XML: characters XML or Mitsuba's $parameters would misread become _.
    stem = re.sub(r"[^\w.-]", "_", mesh_path.stem)
    tex_file, staging = None, None
    try:
        try:
            staging = Path(tempfile.mkdtemp(prefix=".mitsuba-active-", dir=out_dir))
        except OSError as exc:
            raise UserError(f"cannot write into {out_dir}: {exc.strerror}") from None
        # Mitsuba's PLY reader takes v as given, OBJ/trimesh UVs have v up: flip.
        write_ply(staging / "mesh.ply", vertices, mesh.faces, None if uv is None else
                  np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1), rgb)
        keep = {mesh_path.resolve(), *(named.resolve() for named in named_textures(mesh_path))}
        if texture not in (None, "embedded"):
            keep.add(Path(texture).resolve())
        replaceable = _replaceable(out_xml, keep)
        mesh_file, there = _landing_name(staging / "mesh.ply", out_dir, lambda tag: f"{stem}{tag}.ply", replaceable)
        unchanged = {mesh_file} if there else set()
        if texture is not None:
            suffix = ".png" if texture == "embedded" else Path(texture).suffix.lower()
            if texture == "embedded":
                embedded_image(mesh).save(staging / f"texture{suffix}")
            else:
                shutil.copyfile(texture, staging / f"texture{suffix}")
            tex_file, there = _landing_name(staging / f"texture{suffix}", out_dir,
                                            lambda tag: f"{stem}{tag}_texture{suffix}", replaceable)
            unchanged |= {tex_file} if there else set()
        text = _scene_xml(mesh_file, tex_file, color, opts, float(vertices[:, 1].min()), rgb is not None,
                          [] if up_note is None else [up_note])
        (staging / out_xml.name).write_text(text)
        try:  # validate before anything lands
            load_mitsuba(staging / out_xml.name)
        except UserError as exc:  # name the files as the user will find them, not the staging folder
            raise UserError(str(exc).replace(str(staging), str(out_dir))) from None
        if check is not None:
            check(content_hash(staging / out_xml.name))
        # The XML lands last: an XML on disk always finds its mesh and texture.
        for f in sorted(staging.iterdir(), key=lambda f: f.name == out_xml.name):
            if f.name not in unchanged:  # a file already there with these bytes is left as it is
                os.replace(f, out_dir / f.name)
    except BaseException:
        remove_new(out_dir, *added)
        raise
    finally:
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
    return out_xml
