"""Loading: any Mitsuba scene, with its bounds, room or object, up axis, sensors and content hash.

A scene XML is loaded with Mitsuba as it is; a scene built in Python (a
``mitsuba.Scene`` or a scene dict) is read as well, without a hash.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import mitsuba as mi
import numpy as np

from ..cameras import Camera
from ..checks import not_a_file
from ..errors import UserError, brief
from ..rigs import fibonacci_directions
from ..upright import snapped_up
from ..variant import require_variant
from .meshes import MESH_SUFFIXES
from .probes import classify, first_hits, hit_distances

#: Rays that :meth:`Scene.clearance` casts from each point (7 degrees apart:
#: a flat surface's distance comes out at most 1 % long).
CLEARANCE_RAYS = 256


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
            (:func:`~mitsuba_active.scene.probes.classify`).
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

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """(N,) float64: the distance (scene units) from each point (N, 3) to
        the nearest surface, over :data:`CLEARANCE_RAYS` directions spread
        evenly over the sphere (inf where none meets a surface)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        dirs = fibonacci_directions(CLEARANCE_RAYS)
        t = hit_distances(self.mi_scene, np.repeat(points, len(dirs), axis=0), np.tile(dirs, (len(points), 1)))
        return t.reshape(len(points), len(dirs)).min(axis=1, initial=np.inf)

    @property
    def radius(self) -> float:
        """Radius of the bounding sphere of the bounding box."""
        return 0.5 * float(np.linalg.norm(self.bbox_max - self.bbox_min))


def referenced_files(xml_path: Path, seen=None, resolver=None, base: Path | None = None,
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
            files += referenced_files(f, seen, resolver, base, params)
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
    for f in referenced_files(Path(xml_path), params=params) if refs is None else refs:
        h.update(f.read_bytes())
    return h.hexdigest()


def load_mitsuba(xml_path: Path, **params):
    """The ``mitsuba.Scene`` of an XML file; UserError, in one line, when Mitsuba cannot load it."""
    try:
        return mi.load_file(str(xml_path), **params)
    except Exception as exc:
        raise UserError(f"Mitsuba cannot load {xml_path}: {brief(exc)}") from None


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
    refs = referenced_files(xml_path, params=params)
    mi_scene = load_mitsuba(xml_path, **params)
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
    require_variant("loading a scene")
    given = type(scene).__name__
    if isinstance(scene, dict):
        try:
            scene = mi.load_dict(scene)
        except Exception as exc:
            raise UserError(f"Mitsuba cannot load the scene dict {name}: {brief(exc)}") from None
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
