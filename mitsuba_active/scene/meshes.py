"""Meshes: read a mesh file, find what colours its surface, and write it as PLY.

A mesh's surface takes the first of: a texture image (given, its
material's, or one named like the mesh beside it), its vertex colours, its
materials' colours, a single colour. :func:`appearance` picks one as
:func:`~mitsuba_active.scene.authoring.scene_from_mesh` uses it.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import mitsuba as mi
import numpy as np

from ..checks import not_a_file
from ..errors import UserError, brief
from ..imageio_utils import srgb_to_linear

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
TEXTURE_NAMES = ("{stem}_texture.png", "{stem}_texture.jpg", "{stem}.png", "{stem}.jpg", "{stem}_diffuse.png")

#: Diffuse reflectance of a mesh with no texture, vertex colours or material colour of its own:
#: a mid-tone clay, dark enough that its sunlit side stays well below the white background.
DEFAULT_COLOR = (0.45, 0.3, 0.2)


def load_mesh(path) -> "trimesh.Trimesh":
    """Load one triangle mesh with trimesh; UserError when missing, unreadable, empty or degenerate."""
    # trimesh (1 s to import) loads when a mesh is read: the command line loads it with SIGTERM handled.
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
        why = f"{type(exc).__name__}: {brief(exc)}" if isinstance(exc, (KeyError, IndexError)) else brief(exc)
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
    image, (file, file_size) = embedded_image(mesh), _material_file(mesh_path)
    if image is not None and min(image.size) <= 2:
        image = None  # trimesh's placeholder when there is none
    if file is not None and (image is None or image.size == file_size):
        return np.asarray(uv), file  # not an atlas trimesh packed of several materials: the file as it is
    if image is not None:
        return np.asarray(uv), "embedded"
    named = _named_texture(mesh_path)
    return (None, None) if named is None else (np.asarray(uv), named)


def named_textures(mesh_path: Path) -> list[Path]:
    """The images beside a mesh that are its texture by their names (:data:`TEXTURE_NAMES`), first first."""
    return [mesh_path.with_name(pattern.format(stem=mesh_path.stem)) for pattern in TEXTURE_NAMES]


def _named_texture(mesh_path: Path) -> Path | None:
    """The first of :func:`named_textures` that is a file, or None."""
    return next((cand for cand in named_textures(mesh_path) if cand.is_file()), None)


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
                          "the scene is authored without its colours and textures", stacklevel=4)


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
                      "the scene is authored without it", stacklevel=4)


def _vertex_colors(mesh) -> np.ndarray | None:
    """(V, 3) float32 linear RGB of a mesh's own vertex (or face) colours
    (stored sRGB-encoded, as images are), or None when it has none."""
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
    import trimesh  # as in load_mesh

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


def embedded_image(mesh):
    """The texture image a mesh file carries (a PIL image), or None: an OBJ
    material's ``image``, or a glTF/GLB material's ``baseColorTexture``."""
    material = getattr(mesh.visual, "material", None)
    image = getattr(material, "image", None)
    return image if image is not None else getattr(material, "baseColorTexture", None)


def _check_image(path: Path) -> tuple[int, int]:
    """The (width, height) of ``path``; UserError unless it is an image file that Mitsuba's bitmap texture reads."""
    if not path.is_file():
        raise UserError(f"texture {path} is not a file")
    try:
        return tuple(int(n) for n in mi.Bitmap(str(path)).size())
    except Exception:
        raise UserError(f"texture {path} is not an image Mitsuba can read (PNG, JPEG, EXR, HDR, ...)") from None


def appearance(mesh, mesh_path: Path, texture=None, color=None, fallback=DEFAULT_COLOR) -> tuple:
    """What colours the surface of ``mesh`` (as :func:`load_mesh` loaded it
    from ``mesh_path``): ``(uv, texture, rgb, color)``.

    ``texture`` and ``color`` are :class:`~mitsuba_active.scene.authoring.SceneOptions`'
    fields. ``uv``: (V, 2) texture coordinates or None; ``texture``: an
    image's path, ``"embedded"`` (:func:`embedded_image`) or None; ``rgb``:
    (V, 3) linear vertex colours or None; ``color``: the diffuse RGB where
    there is neither (``fallback`` where neither ``color`` nor the mesh's
    materials give one). Warns of material files and images left out.
    """
    _warn_missing_material_files(mesh_path)
    uv, found = _find_texture(mesh, mesh_path, texture)
    rgb = _vertex_colors(mesh) if found is None and texture is None else None
    parts = _material_parts(mesh_path, mesh) if rgb is None and found in (None, "embedded") else None
    if parts is not None and all(embedded_image(part) is None for part in parts):
        if found == "embedded":  # only trimesh's atlas of the materials' colours: an image named like the mesh
            named = _named_texture(mesh_path)
            part_uv = _part_uv(parts) if named is not None else None
            uv, found = (None, None) if part_uv is None else (part_uv, named)
        material = _material_colors(parts) if found is None and color is None else None
        if material is not None:
            if np.ptp(material, axis=0).max() == 0:
                color = tuple(float(c) for c in material[0])
            elif texture is None:
                rgb = material  # one colour per part: as vertex colours
    color = fallback if color is None else color
    if found is None and texture is None:
        _warn_unused_material_images(mesh_path, _mesh_uv(mesh) is not None)
    return uv, found, rgb, color


def normalise_vertices(vertices: np.ndarray, up: str = "y") -> np.ndarray:
    """Rotate to Y-up and fit into the unit box [-0.5, 0.5]^3 (uniform scale), (V, 3) float64."""
    v = np.asarray(vertices, dtype=np.float64)
    if up == "z":  # (x, y, z) -> (x, z, -y): Z-up becomes Y-up, right-handed
        v = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)
    elif up != "y":
        raise ValueError(f"up must be 'y' or 'z', got '{up}'")
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
