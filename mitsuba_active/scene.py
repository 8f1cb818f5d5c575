"""Scenes: author a Mitsuba scene from a mesh, or load any Mitsuba XML.

A generated scene is a Y-up world with the mesh normalised into the unit
bounding box ``[-0.5, 0.5]^3``, a diffuse (or textured) material, a
constant environment light and a sun, and optionally point lights and a floor.
The XML is plain Mitsuba 3 and loads with ``mitsuba.load_file`` alone.
"""

from __future__ import annotations

import dataclasses
import filecmp
import hashlib
import itertools
import math
import os
import re
import shutil
import tempfile
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .checks import is_number, is_whole, not_a_file
from .errors import UserError
from .imageio_utils import new_entries, remove_new
from .probes import classify, first_hits
from .upaxis import shown_up_axis
from .variant import require_variant

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
TEXTURE_NAMES = ("{stem}_texture.png", "{stem}_texture.jpg", "{stem}.png", "{stem}.jpg", "{stem}_diffuse.png")


# ---------------------------------------------------------------------------
# Authoring from meshes
# ---------------------------------------------------------------------------

#: Half width of the authored floor, in units of the normalised object (which spans 1).
FLOOR_HALF_WIDTH = 0.8
#: Diffuse reflectance of a mesh with no texture, vertex colours or material colour of its own:
#: a mid-tone clay, dark enough that its sunlit side stays well below the white background.
DEFAULT_COLOR = (0.45, 0.3, 0.2)
#: Most point lights on the ring (as ``scene --point-lights`` allows), and the
#: deepest path tracer (Mitsuba reads the depth as a 32-bit integer).
MAX_POINT_LIGHTS = 16
MAX_DEPTH = 1024
#: Stands for "--" (an option's dashes) in an XML comment, which may not hold two hyphens.
COMMENT_DASHES = "\u2011\u2011"
#: What ``SceneOptions.up`` takes.
UP_AXES = ("auto", "y", "z")


@dataclass
class SceneOptions:
    """How :func:`scene_from_mesh` dresses a mesh.

    Attributes:
        up: the mesh's up axis, ``"y"`` or ``"z"``; the scene is Y-up.
            ``"auto"`` takes the axis the shape rests on a flat base across
            (:func:`~mitsuba_active.upaxis.shown_up_axis`), else ``"y"``, and
            warns unless the shape showed Y.
        color: diffuse RGB reflectance in [0, 1] when there is no texture
            (or vertex colours); ``None`` takes the colours the mesh's
            materials give (an OBJ material's ``Kd``, a glTF material's
            ``baseColorFactor``, both linear), else :data:`DEFAULT_COLOR`
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

    def __post_init__(self):
        if self.up not in UP_AXES:
            raise UserError(f"the up axis must be one of {', '.join(UP_AXES)}, got {self.up!r}")
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


def load_mesh(path) -> "trimesh.Trimesh":
    """Load one triangle mesh with trimesh; UserError when missing, unreadable, empty or degenerate."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise UserError(not_a_file(path, "mesh file"))
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise UserError(f"unsupported mesh format '{path.suffix}' ({path}); use one of {', '.join(MESH_SUFFIXES)}")
    try:
        # NumPy warns of the casts of non-finite vertices, which are refused below.
        with np.errstate(invalid="ignore", over="ignore"):
            mesh = trimesh.load(str(path), force="mesh")
            # trimesh's processing drops non-finite vertices with their faces: look at the file's own.
            raw = trimesh.load(str(path), force="mesh", process=False)
            finite = np.isfinite(raw.vertices).all()
    except Exception as exc:
        # A bare KeyError names only the missing key (a glTF buffer, say): say what it is.
        why = f"{type(exc).__name__}: {_one_line(exc)}" if isinstance(exc, (KeyError, IndexError)) else _one_line(exc)
        raise UserError(f"cannot read mesh {path}: it is damaged or not a {path.suffix} mesh ({why})") from None
    if not finite or (isinstance(mesh, trimesh.Trimesh) and not np.isfinite(mesh.vertices).all()):
        raise UserError(f"mesh {path} has non-finite vertex coordinates (NaN or infinite)")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise UserError(f"mesh {path} has no triangles")
    extent = float(np.max(mesh.extents))
    if not extent > 0 or mesh.area <= 1e-12 * extent ** 2:  # any size, as long as it has some area
        raw_extent = float(np.ptp(raw.vertices, axis=0).max()) if len(raw.vertices) else 0.0
        # trimesh merges vertices closer than its tolerance (1e-8): a tiny mesh with area loses it.
        if 0 < raw_extent < 1e-6 and raw.area > 1e-12 * raw_extent ** 2:
            raise UserError(f"mesh {path} spans only {raw_extent:.3g} units, too small for trimesh, which merges "
                            "vertices closer than 1e-8: scale it up")
        raise UserError(f"mesh {path} is degenerate (zero area or zero extent)")
    return mesh


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


def _mesh_uv(mesh):
    """The mesh's (V, 2) texture coordinates, or None when it has none for every vertex."""
    uv = getattr(mesh.visual, "uv", None)
    return uv if uv is not None and len(uv) == len(mesh.vertices) else None


def _find_texture(mesh, mesh_path: Path, texture) -> tuple[np.ndarray | None, Path | None]:
    """UVs (V, 2) and texture image path, or (None, None) when the mesh is untextured."""
    uv = _mesh_uv(mesh)
    has_uv = uv is not None
    if texture and not has_uv:
        raise UserError(f"a texture (texture, --texture) needs texture coordinates, and {mesh_path} has none")
    if texture is False or not has_uv:
        return None, None
    if texture:
        tex = Path(texture)
        if not tex.exists():
            raise UserError(f"texture file not found: {tex}")
        _check_image(tex)
        return np.asarray(uv), tex
    # The mesh's material first, then an image named like the mesh beside it.
    image, (file, file_size) = _embedded_image(mesh), _material_file(mesh_path)
    if image is not None and min(image.size) <= 2:
        image = None  # trimesh's placeholder when there is none
    if file is not None and (image is None or image.size == file_size):
        return np.asarray(uv), file  # not an atlas trimesh packed of several materials: the file as it is
    if image is not None:
        return np.asarray(uv), "embedded"
    named = _named_texture(mesh_path)
    return (None, None) if named is None else (np.asarray(uv), named)


def _named_textures(mesh_path: Path) -> list[Path]:
    """The images beside a mesh that are its texture by their names (:data:`TEXTURE_NAMES`), first first."""
    return [mesh_path.with_name(pattern.format(stem=mesh_path.stem)) for pattern in TEXTURE_NAMES]


def _named_texture(mesh_path: Path) -> Path | None:
    """The first of :func:`_named_textures` that is a file, or None."""
    return next((cand for cand in _named_textures(mesh_path) if cand.is_file()), None)


def _material_images(mesh_path: Path) -> set[Path]:
    """The image files an OBJ's materials name (``map_Kd``, which trimesh
    misses when options precede the name), resolved, whether or not they
    exist; empty for other formats."""
    if mesh_path.suffix.lower() != ".obj":
        return set()
    found = set()
    for lib in re.findall(rb"^mtllib[ \t]+(.+?)[ \t\r]*$", mesh_path.read_bytes(), re.M):
        lib = lib.decode("utf-8", "replace")
        for mtl in [mesh_path.parent / name for name in (lib, *lib.split())]:  # one name with spaces, or several
            if mtl.is_file():
                text = mtl.read_bytes()
                found |= {(mtl.parent / name.decode("utf-8", "replace").split()[-1]).resolve()  # after options
                          for name in re.findall(rb"^[ \t]*map_Kd[ \t]+(\S.*?)[ \t\r]*$", text, re.M)}
    return found


def _warn_missing_material_files(mesh_path: Path) -> None:
    """Warn for each material file (``mtllib``) an OBJ names that is not there: its colours
    and textures cannot be used, as for a missing texture."""
    if mesh_path.suffix.lower() != ".obj":
        return
    for lib in re.findall(rb"^mtllib[ \t]+(.+?)[ \t\r]*$", mesh_path.read_bytes(), re.M):
        lib = lib.decode("utf-8", "replace")
        if not any((mesh_path.parent / name).is_file() for name in (lib, *lib.split())):
            warnings.warn(f"the material file {mesh_path.parent / lib} named by {mesh_path} is not a file; "
                          "the scene is authored without its colours and textures", stacklevel=3)


def _material_file(mesh_path: Path) -> tuple[Path | None, tuple | None]:
    """The one image file an OBJ's materials name and its (width, height);
    ``(None, None)`` for other formats, for several images, or when Mitsuba
    cannot read it."""
    found = _material_images(mesh_path)
    if len(found) != 1:
        return None, None
    (image,) = found
    try:
        return image, _check_image(image)  # a file Mitsuba reads
    except UserError:
        return None, None


def _warn_unused_material_images(mesh_path: Path, has_uv: bool) -> None:
    """Warn, once per image, that an image an OBJ's materials name is left out of its scene, and why
    (for a mesh authored without a texture, though none was turned off)."""
    for image in sorted(_material_images(mesh_path)):
        if not has_uv:
            why = "is left out: the mesh has no texture coordinates"
        elif not image.is_file():
            why = "is not a file"
        else:
            try:
                _check_image(image)
                continue  # readable: the texture trimesh found for the mesh (an atlas of several) is used
            except UserError:
                why = "is not an image Mitsuba can read"
        warnings.warn(f"the texture {image} named by the materials of {mesh_path} {why}; "
                      "the scene is authored without it", stacklevel=3)


def _vertex_colors(mesh) -> np.ndarray | None:
    """(V, 3) float32 linear RGB of a mesh's own vertex (or face) colours
    (stored sRGB-encoded, as images are), or None when it has none."""
    from .imageio_utils import srgb_to_linear

    if getattr(mesh.visual, "kind", None) in ("vertex", "face"):  # face colours: averaged at each vertex
        colors = np.asarray(mesh.visual.vertex_colors)
    else:  # a mesh with UVs too keeps them among its vertex attributes
        colors = np.asarray(mesh.vertex_attributes.get("color", np.zeros((0, 3))))
    if colors.ndim != 2 or len(colors) != len(mesh.vertices) or colors.shape[1] < 3:
        return None
    scale = 255.0 if np.issubdtype(colors.dtype, np.integer) else 1.0  # bytes, or floats in [0, 1]
    return srgb_to_linear(colors[:, :3] / scale)


def _material_parts(mesh_path: Path, mesh) -> list | None:
    """The parts of an OBJ or glTF file, one per material (trimesh meshes), whose
    vertices, in order, are those of ``mesh`` (as :func:`load_mesh` loaded it);
    None for other files, an OBJ without materials, or parts that are not the mesh's.

    trimesh concatenates the parts into one mesh, packing the colours of several
    materials into a texture atlas of its own and pointing their UVs into it: the
    parts keep each material and the file's own UVs.
    """
    import trimesh

    suffix = mesh_path.suffix.lower()
    if suffix not in (".obj", ".gltf", ".glb") or (
            suffix == ".obj" and not re.search(rb"^mtllib[ \t]", mesh_path.read_bytes(), re.M)):
        return None
    try:
        parts = trimesh.load(str(mesh_path), force="scene").dump()
    except Exception:  # load_mesh read the file: nothing more to learn from it
        return None
    # The parts' vertices, in order, must be the mesh's, for what they carry to land where it belongs.
    stacked = np.concatenate([part.vertices for part in parts]) if parts else np.zeros((0, 3))
    if stacked.shape != np.shape(mesh.vertices) or not np.allclose(stacked, mesh.vertices):
        return None
    return parts


def _part_uv(parts) -> np.ndarray | None:
    """(V, 2) the parts' own texture coordinates, or None unless every part has them."""
    uvs = [getattr(part.visual, "uv", None) for part in parts]
    if not all(uv is not None and len(uv) == len(part.vertices) for uv, part in zip(uvs, parts)):
        return None
    return np.concatenate([np.asarray(uv, np.float64) for uv in uvs])


def _material_colors(parts) -> np.ndarray | None:
    """(V, 3) linear RGB reflectance of each vertex of the parts: their
    material's colour (an OBJ material's ``Kd``, a glTF material's
    ``baseColorFactor``), :data:`DEFAULT_COLOR` for a part whose material
    gives none; None when no part's does."""
    fallback = np.asarray(DEFAULT_COLOR, np.float64)
    colors, found = [], False
    for part in parts:
        material = getattr(part.visual, "material", None)
        kd = (getattr(material, "kwargs", None) or {}).get("kd")  # the MTL's own numbers
        factor = getattr(material, "baseColorFactor", None)  # glTF's linear factor, as bytes
        color = fallback
        if kd is not None and len(kd) >= 3 and np.isfinite(np.asarray(kd[:3], np.float64)).all():
            color = np.clip(np.asarray(kd[:3], np.float64), 0.0, 1.0)
        elif factor is not None:
            color = np.asarray(factor[:3], np.float64) / 255.0
        found |= color is not fallback
        colors.append(np.broadcast_to(color, (len(part.vertices), 3)))
    return np.concatenate(colors) if found else None


def _embedded_image(mesh):
    """The texture image a mesh file carries (a PIL image), or None: an OBJ
    material's ``image``, or a glTF/GLB material's ``baseColorTexture``."""
    material = getattr(mesh.visual, "material", None)
    image = getattr(material, "image", None)
    return image if image is not None else getattr(material, "baseColorTexture", None)


def _check_image(path: Path) -> tuple[int, int]:
    """The (width, height) of ``path``; UserError unless it is an image file that Mitsuba's bitmap texture reads."""
    import mitsuba as mi

    if not path.is_file():
        raise UserError(f"texture {path} is not a file")
    try:
        return tuple(int(n) for n in mi.Bitmap(str(path)).size())
    except Exception:
        raise UserError(f"texture {path} is not an image Mitsuba can read (PNG, JPEG, EXR, HDR, ...)") from None


def normalise_vertices(vertices: np.ndarray, up: str = "y") -> np.ndarray:
    """Rotate to Y-up and fit into the unit box [-0.5, 0.5]^3 (uniform scale), (V, 3) float64."""
    v = np.asarray(vertices, dtype=np.float64)
    if up == "z":  # (x, y, z) -> (x, z, -y): Z-up becomes Y-up, right-handed
        v = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)
    elif up != "y":
        raise UserError(f"--up must be 'y' or 'z', got '{up}'")
    lo, hi = v.min(axis=0), v.max(axis=0)
    return (v - 0.5 * (lo + hi)) / float(np.max(hi - lo))


def write_ply(path, vertices, faces, uv=None, rgb=None):
    """Write a binary little-endian PLY with optional per-vertex UVs (Mitsuba's
    ``u``/``v``) and linear RGB colours in [0, 1] (``r``/``g``/``b``, which
    Mitsuba reads as the ``vertex_color`` attribute)."""
    vertices = np.asarray(vertices, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int32)
    props = ["x", "y", "z"] + (["u", "v"] if uv is not None else []) + (["r", "g", "b"] if rgb is not None else [])
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}"]
    header += [f"property float {p}" for p in props]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    vdata = np.hstack([vertices] + [np.asarray(a, dtype=np.float32) for a in (uv, rgb) if a is not None])
    fdata = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    fdata["n"], fdata["i"] = 3, faces
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(np.ascontiguousarray(vdata, dtype="<f4").tobytes())
        f.write(fdata.tobytes())


def _replaceable(out_xml: Path, keep: set[Path]) -> set[Path]:
    """Files that authoring ``out_xml`` anew may replace: those the XML being
    replaced names that no other scene XML beside it names, except ``keep``
    (resolved paths: the input mesh and its own textures)."""
    def named_by(xml: Path) -> set[Path]:
        try:
            return set(_referenced_files(xml))
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
    if opts.sun:
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
    _warn_missing_material_files(mesh_path)
    up, up_note = _up_axis(mesh, mesh_path) if opts.up == "auto" else (opts.up, None)
    vertices = normalise_vertices(mesh.vertices, up)
    uv, texture = _find_texture(mesh, mesh_path, opts.texture)
    rgb = _vertex_colors(mesh) if texture is None and opts.texture is None else None
    color = opts.color
    parts = _material_parts(mesh_path, mesh) if rgb is None and texture in (None, "embedded") else None
    if parts is not None and all(_embedded_image(part) is None for part in parts):
        if texture == "embedded":  # only trimesh's atlas of the materials' colours: an image named like the mesh
            named = _named_texture(mesh_path)
            part_uv = _part_uv(parts) if named is not None else None
            uv, texture = (None, None) if part_uv is None else (part_uv, named)
        material = _material_colors(parts) if texture is None and color is None else None
        if material is not None:
            if np.ptp(material, axis=0).max() == 0:
                color = tuple(float(c) for c in material[0])
            elif opts.texture is None:
                rgb = material  # one colour per part: as vertex colours
    color = DEFAULT_COLOR if color is None else color
    if texture is None and opts.texture is None:
        _warn_unused_material_images(mesh_path, _mesh_uv(mesh) is not None)

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
        keep = {mesh_path.resolve(), *(named.resolve() for named in _named_textures(mesh_path))}
        if texture not in (None, "embedded"):
            keep.add(Path(texture).resolve())
        replaceable = _replaceable(out_xml, keep)
        mesh_file, there = _landing_name(staging / "mesh.ply", out_dir, lambda tag: f"{stem}{tag}.ply", replaceable)
        unchanged = {mesh_file} if there else set()
        if texture is not None:
            suffix = ".png" if texture == "embedded" else Path(texture).suffix.lower()
            if texture == "embedded":
                _embedded_image(mesh).save(staging / f"texture{suffix}")
            else:
                shutil.copyfile(texture, staging / f"texture{suffix}")
            tex_file, there = _landing_name(staging / f"texture{suffix}", out_dir,
                                            lambda tag: f"{stem}{tag}_texture{suffix}", replaceable)
            unchanged |= {tex_file} if there else set()
        text = _scene_xml(mesh_file, tex_file, color, opts, float(vertices[:, 1].min()), rgb is not None,
                          [] if up_note is None else [up_note])
        (staging / out_xml.name).write_text(text)
        try:  # validate before anything lands
            _load_mitsuba(staging / out_xml.name)
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


# ---------------------------------------------------------------------------
# Loading any Mitsuba XML
# ---------------------------------------------------------------------------

@dataclass
class Scene:
    """A loaded Mitsuba scene and what the planner needs to know about it.

    Attributes:
        path: the XML file (for a scene built in Python, its name).
        mi_scene: the ``mitsuba.Scene``.
        bbox_min, bbox_max: (3,) float64 scene bounds in scene units.
        content_hash: hex digest of the XML and every file it references;
            None for a scene built in Python (:func:`scene_from_mitsuba`).
        interior: True when the scene is a room seen from inside
            (:func:`~mitsuba_active.probes.classify`).
        sensors: the XML's own perspective sensors as :class:`Camera` objects.
        up: (3,) world up axis, taken from the first sensor's up vector
            (snapped to the nearest axis), +Y when there is no sensor.
        floor: True when a shape has the id ``floor`` (as ``scene --floor``
            authors it): cameras below it would see its underside only.
        sensors_off_centre: how many of the XML's sensors have a principal
            point offset (or a crop window off the film's centre), which
            :attr:`sensors` do not keep (their principal point is the image
            centre; a crop window's field of view is kept).
        sensors_thin_lens: how many of the XML's sensors are thin-lens
            cameras with an aperture, which :attr:`sensors` do not keep (they
            are pinholes: no defocus).
        interior_reason: why the scene is, or is not, a room, in words for
            messages ("a room seen from inside: ...").
    """

    path: Path
    mi_scene: object
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    content_hash: str | None
    interior: bool = False
    sensors: list = field(default_factory=list)
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    floor: bool = False
    sensors_off_centre: int = 0
    sensors_thin_lens: int = 0
    interior_reason: str = ""

    @property
    def name(self) -> str:
        """The XML file's stem, or the name a scene built in Python was given (kept whole: it names no file)."""
        return str(self.path) if self.content_hash is None else self.path.stem

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (self.bbox_min + self.bbox_max)

    def free_space(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: True for points (N, 3) that are not inside a closed object.

        A point is inside when a ray from it, along any of the six axis
        directions, first meets the back face of a surface.
        """
        points = np.asarray(points, dtype=np.float64)
        free = np.ones(len(points), dtype=bool)
        for axis in range(3):
            for sign in (-1.0, 1.0):
                d = np.zeros((len(points), 3))
                d[:, axis] = sign
                hit, front = first_hits(self.mi_scene, points, d)
                free &= ~(hit & ~front)
        return free

    @property
    def radius(self) -> float:
        """Radius of the bounding sphere of the bounding box."""
        return 0.5 * float(np.linalg.norm(self.bbox_max - self.bbox_min))


def _one_line(exc) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 300 else text[:297] + "..."


def _referenced_files(xml_path: Path, seen=None, resolver=None, base: Path | None = None,
                      params=None) -> list[Path]:
    """Existing files an XML names (includes, ``filename`` strings and
    attributes such as a spectrum's), recursively.

    Names resolve as Mitsuba finds them when it loads the top-level file:
    in the folders its ``<path>`` elements add (relative to the top-level
    file's folder), then that folder, then the resolver's own (the working
    directory, Mitsuba's); an included file's names too. ``$`` parameters
    are replaced by ``params`` (the values the scene is loaded with) or,
    failing those, the XML's ``<default>`` values. UserError if malformed.
    """
    import mitsuba as mi

    seen = set() if seen is None else seen
    params = {k: str(v) for k, v in (params or {}).items()}
    base = base or xml_path.parent
    if resolver is None:
        resolver = mi.FileResolver(mi.file_resolver())
        resolver.prepend(str(base))
    try:
        root = ET.parse(xml_path).getroot()
    except ET.ParseError as exc:
        raise UserError(f"malformed XML in {xml_path}: {exc}") from None
    except OSError as exc:
        raise UserError(f"cannot read {xml_path}: {exc.strerror}") from None
    if root.tag != "scene":
        raise UserError(f"{xml_path} is not a Mitsuba scene (root element <{root.tag}>, expected <scene>)")
    if _nesting_depth(root) > MAX_XML_DEPTH:  # Mitsuba's own parser recurses, and would crash
        raise UserError(f"malformed XML in {xml_path}: elements nested more than {MAX_XML_DEPTH} deep")
    for el in root.iter("default"):
        params.setdefault(el.get("name"), el.get("value"))

    def named(text):  # None for a parameter given neither a value nor a default
        text = re.sub(r"\$(\w+)", lambda m: params.get(m.group(1)) or m.group(0), text or "")
        return text if text and "$" not in text else None

    for el in root.iter("path"):
        folder = named(el.get("value"))
        if folder:
            resolver.prepend(str(base / folder))
    files = []
    for el in root.iter():
        name = named(el.get("value") if el.tag == "string" and el.get("name") == "filename" else el.get("filename"))
        if name is None:
            continue
        f = Path(str(resolver.resolve(name)))
        if not f.is_file() or f.resolve() in seen:
            continue  # a missing file is reported by Mitsuba itself
        seen.add(f.resolve())
        files.append(f.resolve())
        if el.tag == "include":
            files += _referenced_files(f, seen, resolver, base, params)
    return files


#: Deepest nesting of elements read from a scene XML (scenes nest a few levels deep).
MAX_XML_DEPTH = 1000


def _nesting_depth(root) -> int:
    """Levels of elements under and including ``root`` (an ElementTree element), counted without recursion."""
    deepest, stack = 0, [(root, 1)]
    while stack:
        el, depth = stack.pop()
        deepest = max(deepest, depth)
        stack.extend((child, depth + 1) for child in el)
    return deepest


def content_hash(xml_path: Path, refs: list[Path] | None = None, **params) -> str:
    """Hex digest of a scene XML, its ``$`` parameters and every file it references
    (``refs``, found anew if None): what a run's ground truth depends on."""
    h = hashlib.sha256(Path(xml_path).read_bytes())
    h.update(repr(sorted(params.items())).encode())
    for f in _referenced_files(Path(xml_path), params=params) if refs is None else refs:
        h.update(f.read_bytes())
    return h.hexdigest()


def _load_mitsuba(xml_path: Path, **params):
    import mitsuba as mi

    try:
        return mi.load_file(str(xml_path), **params)
    except Exception as exc:
        raise UserError(f"Mitsuba cannot load {xml_path}: {_one_line(exc)}") from None


#: Largest coordinate of a scene's geometry that single-precision rendering
#: and its squared distances handle (scene units).
MAX_SCENE_COORDINATE = 1e12


def load_scene(xml_path, **params) -> Scene:
    """Load any Mitsuba 3 scene XML; UserError when missing, malformed or empty.

    ``params`` are passed to ``mitsuba.load_file`` (XML ``$`` defaults).
    """
    require_variant("loading a scene")
    if not isinstance(xml_path, (str, os.PathLike)):
        raise UserError(f"a scene XML is named by its path, got {type(xml_path).__name__}; a scene built in "
                        "Python (a mitsuba.Scene or a scene dict) is read with scene_from_mitsuba "
                        "(a view source of it: SceneSource.from_mitsuba)")
    xml_path = Path(xml_path)
    if xml_path.is_dir():
        raise UserError(f"{xml_path} is a folder, not a scene XML file (a transforms.json dataset is read "
                        "with mitsuba_active.datasets.DatasetSource)")
    if not xml_path.is_file():
        raise UserError(not_a_file(xml_path, "scene file"))
    if xml_path.suffix.lower() in MESH_SUFFIXES:
        raise UserError(f"{xml_path} is a mesh, not a Mitsuba scene: author one around it first with "
                        f"'mitsuba-active scene {xml_path} -o scene.xml'")
    refs = _referenced_files(xml_path, params=params)
    mi_scene = _load_mitsuba(xml_path, **params)
    return _describe(mi_scene, xml_path, content_hash(xml_path, refs, **params))


def scene_from_mitsuba(scene, name: str = "scene") -> Scene:
    """A :class:`Scene` of a scene built in Python: a ``mitsuba.Scene``, or a
    scene dict as ``mitsuba.load_dict`` takes it.

    Such a scene has no files to hash: its ``content_hash`` is None, so its
    ground truth is rendered anew rather than cached on disk, and a
    :class:`~mitsuba_active.run.Run` (which records a scene by its file)
    does not take it. ``name`` stands for the file in messages and is the
    view source's name.
    """
    import mitsuba as mi

    require_variant("loading a scene")
    given = type(scene).__name__
    if isinstance(scene, dict):
        try:
            scene = mi.load_dict(scene)
        except Exception as exc:
            raise UserError(f"Mitsuba cannot load the scene dict {name}: {_one_line(exc)}") from None
        given = f"a dict of a {type(scene).__name__} (its 'type' must be 'scene')"
    if not isinstance(scene, mi.Scene):
        if type(scene).__name__ == "Scene" and type(scene).__module__.split(".")[0] == "mitsuba":
            raise UserError(f"scene_from_mitsuba got a mitsuba.Scene of another Mitsuba variant; load it with "
                            f"'{mi.variant()}' set, the variant mitsuba-active runs")
        raise UserError(f"scene_from_mitsuba takes a mitsuba.Scene or a scene dict, got {given}")
    return _describe(scene, Path(name), None)


def _describe(mi_scene, xml_path: Path, digest: str | None) -> Scene:
    """The :class:`Scene` of a loaded Mitsuba scene (``xml_path`` names it in
    messages); UserError when it has no shapes or unusable bounds."""
    import mitsuba as mi

    from .cameras import Camera, snapped_up

    if len(mi_scene.shapes()) == 0:
        raise UserError(f"scene {xml_path} has no shapes")
    if len(mi_scene.emitters()) == 0:
        warnings.warn(f"scene {xml_path} has no lights: every view renders black", stacklevel=3)
    bbox = mi_scene.bbox()
    lo, hi = np.array(bbox.min, dtype=np.float64), np.array(bbox.max, dtype=np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or np.max(hi - lo) <= 0:
        raise UserError(f"scene {xml_path} has empty or unbounded geometry")
    size = float(np.max(np.abs(np.concatenate([lo, hi]))))
    if size > MAX_SCENE_COORDINATE:
        # Squared distances (variances, errors) would overflow single precision.
        raise UserError(f"scene {xml_path} reaches {size:.3g} scene units from the origin, more than "
                        f"{MAX_SCENE_COORDINATE:.0e}; scale it down")
    sensors, off_centre, thin_lens = [], 0, 0
    for s in mi_scene.sensors():
        sensor_params = mi.traverse(s)
        if "x_fov" not in sensor_params.keys():
            continue  # not a perspective camera
        film = s.film()
        full, crop, offset = (np.array(v, dtype=np.float64) for v in (film.size(), film.crop_size(),
                                                                      film.crop_offset()))
        # A crop window sees part of the film's field of view; off the film's centre (by more
        # than the half pixel an odd difference in size leaves) it is a principal point offset too.
        off_centre += any(float(sensor_params[key][0]) != 0 for key in ("principal_point_offset_x",
                                                                         "principal_point_offset_y")
                          if key in sensor_params.keys()) or bool(np.any(np.abs(offset + crop / 2 - full / 2) > 0.5))
        thin_lens += "aperture_radius" in sensor_params.keys() and float(sensor_params["aperture_radius"][0]) > 0
        fov = math.degrees(2 * math.atan(math.tan(math.radians(float(sensor_params["x_fov"][0])) / 2)
                                         * crop[0] / full[0]))
        m = np.array(s.world_transform().matrix, dtype=np.float64).reshape(4, 4)
        sensors.append(Camera(m, fov, int(crop[0]), int(crop[1]), float(s.near_clip()), float(s.far_clip())))
    up = snapped_up(sensors[:1])  # the first sensor's, as the scene's author set it up
    floor = any(shape.id() == "floor" for shape in mi_scene.shapes())
    enclosure = classify(mi_scene, lo, hi, up)
    return Scene(xml_path, mi_scene, lo, hi, digest, enclosure.interior, sensors, up, floor,
                 off_centre, thin_lens, enclosure.reason)

