"""Rigs: candidate and held-out cameras around an object or inside a room, or a scene's own.

``sphere``, ``hemisphere`` and ``rings`` surround an object at a distance
where it fills the view; ``interior`` places cameras inside a room; ``xml``
takes a Mitsuba scene's own sensors. Held-out views lie in the gaps between
the candidates' places (:func:`scene_rigs`).
"""

from __future__ import annotations

import math
import warnings
from fractions import Fraction

import numpy as np
from scipy.spatial import cKDTree

from .cameras import Camera, look_at, rigid_pose
from .checks import is_number, is_whole, unknown_choice
from .errors import UserError
from .upright import up_frame

#: Most cameras a generated rig makes (candidates, and held-out views).
MAX_VIEWS = 100_000

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def fibonacci_directions(n: int, offset: float = 0.0, y_min: float = -1.0, y_max: float = 1.0) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the band ``y_min <= y <= y_max`` of the sphere.

    ``offset`` in [0, 1) shifts the spiral; different offsets give disjoint sets.
    """
    i = np.arange(n, dtype=np.float64) + 0.5
    y = y_max - (y_max - y_min) * ((i + offset) % n) / n
    r = np.sqrt(np.clip(1.0 - y * y, 0.0, 1.0))
    phi = GOLDEN_ANGLE * (i + offset * 7.0)
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=1)


def places_apart(taken: np.ndarray, pool: np.ndarray, targets: np.ndarray, radius: float,
                 mirror=None) -> list[int]:
    """For each of the (T, 3) unit vectors ``targets``, the index of a point of the (P, 3) unit
    vectors ``pool`` within chord ``radius`` of it that lies farthest from the (C, 3) unit vectors
    ``taken`` and from the points chosen for earlier targets (gaps count up to ``2 * radius``;
    the nearer of points as far from them). Where none is within ``radius``, or all there are
    taken, the nearest such points are searched. Distinct points while the pool lasts.
    ``mirror``: maps chosen points to (1, 3) points that later ones keep away from too (a
    hemisphere's rim, below which the rig goes on as if reflected).

    Held-out views then keep the targets' even spread (the held-out spiral), each moved into the
    largest gap between candidate views near it, never next to a candidate."""
    pool = np.asarray(pool, dtype=np.float64)
    cap = 2.0 * radius  # farther gaps choose nothing within reach, and bound each update
    gap = np.minimum(cKDTree(taken).query(pool)[0], cap) if len(taken) else np.full(len(pool), cap)
    tree, chosen = cKDTree(pool), []
    for target in targets:
        near = np.asarray(tree.query_ball_point(target, radius), dtype=np.int64)
        k = 64
        while (len(near) == 0 or gap[near].max() == 0) and len(near) < len(pool):
            near = np.atleast_1d(tree.query(target, k=min(k, len(pool)))[1])
            k *= 4
        score = gap[near] - 1e-9 * np.linalg.norm(pool[near] - target, axis=1)
        i = int(near[np.argmax(score)])
        chosen.append(i)
        # Later targets keep away from this one too (and from its mirror image).
        for point in [pool[i]] + ([] if mirror is None else list(mirror(pool[[i]]))):
            around = np.asarray(tree.query_ball_point(point, cap), dtype=np.int64)
            gap[around] = np.minimum(gap[around], np.linalg.norm(pool[around] - point, axis=1))
        gap[i] = 0.0
    return chosen


def _mirrored_below(dirs: np.ndarray, y_min: float) -> np.ndarray:
    """(N, 3) unit vectors ``dirs`` mirrored in elevation across the circle ``y = y_min``
    (the same azimuth, as far below it as they are above)."""
    elevation = np.arcsin(np.clip(dirs[:, 1], -1.0, 1.0))
    mirrored = 2.0 * math.asin(y_min) - elevation
    horizontal = np.hypot(dirs[:, 0], dirs[:, 2])
    scale = np.cos(mirrored) / np.maximum(horizontal, 1e-12)
    out = np.stack([dirs[:, 0] * scale, np.sin(mirrored), dirs[:, 2] * scale], axis=1)
    out[horizontal < 1e-12, 0] = np.cos(mirrored[horizontal < 1e-12])  # a pole: any azimuth
    return out


def _pool_size(n_candidates: int, n_heldout: int) -> int:
    """Points of the spiral that held-out views are picked from: fine beside the candidates' spacing."""
    return max(4096, 8 * (n_candidates + n_heldout))


def _cameras_around(center, radius, dirs_y_up, up, fov, width, height, near, far):
    """Cameras at ``center + radius * R dirs`` looking at ``center``; ``dirs`` are given in a Y-up frame."""
    center = np.asarray(center, dtype=np.float64)
    pos = center + radius * (np.asarray(dirs_y_up) @ up_frame(up).T)
    return [Camera(look_at(p, center, up), fov, width, height, near, far) for p in pos]


def fibonacci_sphere(n, center, radius, fov=40.0, width=64, height=64, offset=0.0, up=(0, 1, 0),
                     near=1e-3, far=1e4):
    """``n`` cameras on a sphere around ``center`` looking at it."""
    _check_count(n)
    return _cameras_around(center, radius, fibonacci_directions(n, offset), up, fov, width, height, near, far)


#: Lowest elevation (degrees) of the cameras of :func:`hemisphere`.
HEMISPHERE_MIN_ELEVATION = 5.0


def hemisphere(n, center, radius, fov=40.0, width=64, height=64, offset=0.0, up=(0, 1, 0),
               min_elevation=HEMISPHERE_MIN_ELEVATION, near=1e-3, far=1e4):
    """``n`` cameras on the upper hemisphere (towards ``up``), above ``min_elevation`` degrees."""
    _check_count(n)
    dirs = fibonacci_directions(n, offset, y_min=math.sin(math.radians(min_elevation)), y_max=1.0)
    return _cameras_around(center, radius, dirs, up, fov, width, height, near, far)


#: Degrees a ring of :func:`rings` rises per unit of ``offset``.
RING_OFFSET_ELEVATION = 15.0


def rings(n, center, radius, fov=40.0, width=64, height=64, offset=0.0, up=(0, 1, 0),
          elevations=(-20.0, 15.0, 45.0), near=1e-3, far=1e4):
    """``n`` cameras on rings at the given elevations (degrees) around the ``up`` axis.

    ``offset`` turns each ring by that fraction of its spacing and raises it by
    ``RING_OFFSET_ELEVATION * offset`` degrees: rigs with different offsets
    (candidates at 0, held-out views at 0.5) then never share a camera,
    whatever their counts.
    """
    _check_count(n)
    k = len(elevations)
    counts = [n // k + (1 if j < n % k else 0) for j in range(k)]
    dirs = []
    for j, (elev, m) in enumerate(zip(elevations, counts)):
        e = math.radians(elev + RING_OFFSET_ELEVATION * offset)
        az = 2 * math.pi * (np.arange(m) + 0.5 * offset + 0.25 * j) / max(m, 1)
        dirs += [[math.cos(e) * math.cos(a), math.sin(e), math.cos(e) * math.sin(a)] for a in az]
    return _cameras_around(center, radius, np.array(dirs), up, fov, width, height, near, far)


#: Size of the ellipsoid of :func:`interior` cameras: a fraction of the room's half extents.
INTERIOR_SPREAD = 0.4
#: Least distance from a generated interior camera to any surface, as a fraction of the
#: room's bounding-box diagonal: a room's fields see nothing closer to their cameras
#: (``mitsuba_active.field.room.ROOM_NEAR``).
INTERIOR_CLEARANCE = 0.055


def interior(n, bbox_min, bbox_max, fov=70.0, width=64, height=64, offset=0.0, spread=INTERIOR_SPREAD,
             near=1e-3, far=1e4, up=(0, 1, 0)):
    """``n`` cameras inside a room, each looking across it through the centre.

    Positions lie on an ellipsoid at ``spread`` times the half extents
    around the centre of the box, looking at the centre, so that every view
    sees the far walls.
    """
    _check_count(n)
    center, axes = _room_ellipsoid(bbox_min, bbox_max, spread)
    return _cameras_inside(center, axes, fibonacci_directions(n, offset), up, fov, width, height, near, far)


def room_for_camera(scene, points) -> np.ndarray:
    """(N,) bool: whether a camera inside ``scene`` may stand at each point (N, 3): not inside
    furniture (it would see nothing else) and, in a room (``scene.interior``), at least
    :data:`INTERIOR_CLEARANCE` of its diagonal from every surface (nearer, a room's fields see
    nothing). Inside an object's box (``--rig interior`` asked for) every place is near it."""
    free = scene.free_space(points)
    if scene.interior:
        free &= scene.clearance(points) >= interior_clearance(scene)
    return free


def interior_clearance(scene) -> float:
    """The least distance (scene units) from a camera inside ``scene`` to its surfaces."""
    return INTERIOR_CLEARANCE * float(np.linalg.norm(scene.bbox_max - scene.bbox_min))


def _room_ellipsoid(bbox_min, bbox_max, spread=INTERIOR_SPREAD):
    """Centre (3,) and semi-axes (3,) of the ellipsoid :func:`interior` cameras lie on."""
    lo, hi = np.asarray(bbox_min, dtype=np.float64), np.asarray(bbox_max, dtype=np.float64)
    return 0.5 * (lo + hi), spread * 0.5 * (hi - lo)


def _cameras_inside(center, axes, dirs, up, fov, width, height, near, far):
    """Cameras at ``center + axes * dirs`` (on an ellipsoid of semi-axes ``axes``) looking at ``center``."""
    pos = np.asarray(center, dtype=np.float64) + np.asarray(axes) * np.asarray(dirs)
    return [Camera(look_at(p, center, up), fov, width, height, near, far) for p in pos]


RIG_KINDS = ("auto", "sphere", "hemisphere", "rings", "interior", "xml")


def clip_range(radius: float, reach: float) -> tuple[float, float]:
    """Near and far clip distances (scene units) for cameras of a scene of
    this bounding ``radius`` that see at most ``reach`` far: 1e-3 and 1e4
    unless the scene is so small or so large that they would cut into it
    (the defaults stay, so existing ground truth keeps its cache keys)."""
    return min(1e-3, 1e-2 * radius), max(1e4, 2.0 * reach)


#: How much farther than touching the image's edge rigs around an object stand (1.05: 5 %).
FRAMING_MARGIN = 1.05


def framing_radius(scene) -> float:
    """Radius (scene units) of the sphere about the scene's centre that holds all of its geometry:
    the farthest vertex of its meshes, or corner of another shape's bounding box, from
    ``scene.center``. At most ``scene.radius``, that of its bounding box, whose empty corners
    (a rounded or a tilted object) it leaves out; a rig whose cameras see this sphere whole sees
    the whole scene from every direction."""
    centre, farthest = np.asarray(scene.center, dtype=np.float64), 0.0
    for shape in scene.mi_scene.shapes():
        if shape.is_mesh():  # Mitsuba keeps a mesh's vertices in world space
            points = np.array(shape.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
        else:
            box = shape.bbox()
            lo, hi = np.array(box.min, dtype=np.float64), np.array(box.max, dtype=np.float64)
            points = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        if len(points):
            farthest = max(farthest, float(np.linalg.norm(points - centre, axis=1).max()))
    # Rounding aside, never farther than the box's corners; a scene of no points keeps the box's sphere.
    return min(farthest, scene.radius) if farthest > 0 else scene.radius


def auto_rig(scene) -> tuple[str, str]:
    """The rig ``auto`` picks for a :class:`~mitsuba_active.scene.Scene`, and why (in words)."""
    if scene.interior:
        return "interior", scene.interior_reason
    if scene.floor:  # views from below a floor would show its underside and nothing else
        return "hemisphere", "an object on a floor, seen from above it"
    return "sphere", scene.interior_reason or "an object seen from outside"


def generated_rig(scene, rig: str) -> str:
    """The kind of rig that ``rig`` generates cameras of for ``scene``: ``auto`` and ``xml`` (whose
    held-out views need a kind) as :func:`auto_rig` picks, any other as named."""
    return auto_rig(scene)[0] if rig in ("auto", "xml") else rig


def scene_rigs(scene, rig="auto", n_candidates=100, n_heldout=20, width=64, height=None, fov=None):
    """Candidate and held-out cameras for a :class:`~mitsuba_active.scene.Scene`.

    ``rig``: ``sphere``, ``hemisphere`` and ``rings`` surround the scene's
    centre at a distance where the sphere about it that holds all of its
    geometry (:func:`framing_radius`) fills the view, within
    :data:`FRAMING_MARGIN`;
    ``interior`` places cameras inside a room; ``xml`` takes the XML's own
    sensors as candidates, with their poses, fields of view and clip
    distances (held-out views then come from a generated rig);
    ``auto`` picks ``interior`` for rooms, ``hemisphere`` for an object on a
    floor (a shape with the id ``floor``), else ``sphere``. Held-out views
    are of the same kind as the candidates (under ``xml``: of the rig ``auto``
    would pick) and lie in the gaps between the candidates' places on the rig
    (:func:`places_apart`), except under ``rings``, whose held-out rings
    are shifted in elevation and azimuth. None coincides with a candidate.

    Images are ``width`` pixels wide and ``height`` high; ``height`` defaults
    to ``width``, or under ``xml`` to the aspect ratio of the sensors' films.

    Returns ``(candidates, heldout)``, two lists of :class:`Camera`.
    """
    if rig not in RIG_KINDS:
        raise UserError(unknown_choice("rig", rig, RIG_KINDS))
    for what, n in (("candidate", n_candidates), ("held-out", n_heldout)):  # image sizes: Camera checks them
        if not is_whole(n) or n < 1:
            raise UserError(f"the number of {what} views must be a whole number >= 1, got {n!r}")
        if n > MAX_VIEWS:
            raise UserError(f"{n} {what} views are more than a rig makes (at most {MAX_VIEWS})")
    if fov is not None and not is_number(fov):
        raise UserError(f"the field of view must be a number of degrees, got {fov!r}")
    if rig == "xml":
        if not scene.sensors:
            raise UserError(f"{scene.path} has no perspective sensor to use as candidates")
        height = height or _film_height(scene.sensors, width)
    height = height or width
    generated = generated_rig(scene, rig)  # under xml, for held-out views of the right kind
    if generated == "interior":
        fov = 70.0 if fov is None else fov
        near, far = clip_range(scene.radius, 2.0 * scene.radius)
        (centre, axes), frame, band = _room_ellipsoid(scene.bbox_min, scene.bbox_max), np.eye(3), (-1.0, 1.0)
        at = lambda dirs: _cameras_inside(centre, axes, dirs, scene.up, fov, width, height, near, far)  # noqa: E731
        free = lambda dirs: room_for_camera(scene, centre + axes * dirs)  # noqa: E731

        def short(found, n, what):
            hint = ("ask for fewer views" if scene.interior else
                    f"{scene.path} is an object, not a room: use --rig sphere or hemisphere")
            near = f" or closer than {interior_clearance(scene):.3g} to a surface" if scene.interior else ""
            return UserError(f"the interior rig found room for {found} of the {n} {what} cameras inside "
                             f"{scene.path}, the rest being inside solid objects{near}; {hint}")

        def make(n, off):  # over-generated, then thinned out evenly over the whole spiral
            dirs = fibonacci_directions(4 * n, off)
            dirs = dirs[free(dirs)]
            if len(dirs) < n:
                raise short(len(dirs), n, "candidate" if off == 0.0 else "held-out")
            return at(dirs[np.linspace(0, len(dirs) - 1, n).round().astype(np.int64)])
    else:
        fov = 40.0 if fov is None else fov
        if not 0.0 < fov < 180.0:
            raise UserError(f"field of view must be in (0, 180) degrees, got {fov}")
        half_fov = math.radians(fov) / 2
        if height < width:  # wide images: the vertical field of view is the narrower one
            half_fov = math.atan(math.tan(half_fov) * height / width)
        # The farthest point of the geometry 5 % inside the narrower field of view, from any direction.
        radius = FRAMING_MARGIN * framing_radius(scene) / math.sin(half_fov)
        near, far = clip_range(scene.radius, radius + scene.radius)
        centre, axes, frame = scene.center, radius, up_frame(scene.up)
        band = (math.sin(math.radians(HEMISPHERE_MIN_ELEVATION)) if generated == "hemisphere" else -1.0, 1.0)
        at = lambda dirs: _cameras_around(centre, radius, dirs, scene.up, fov, width, height, near, far)  # noqa: E731
        free = None
        fn = {"sphere": fibonacci_sphere, "hemisphere": hemisphere, "rings": rings}[generated]
        make = lambda n, off: fn(n, scene.center, radius, fov, width, height, off, up=scene.up,  # noqa: E731
                                 near=near, far=far)
    if rig == "xml":
        if scene.sensors_off_centre:
            warnings.warn(f"{scene.sensors_off_centre} of the {len(scene.sensors)} sensors of {scene.path} have a "
                          "principal point offset (or a crop window off the film's centre), which rig 'xml' does "
                          "not keep: their views are centred", stacklevel=2)
        if scene.sensors_thin_lens:
            warnings.warn(f"{scene.sensors_thin_lens} of the {len(scene.sensors)} sensors of {scene.path} are "
                          "thin-lens cameras, which rig 'xml' renders as pinholes: no defocus", stacklevel=2)
        for i, c in enumerate(scene.sensors):  # the poses of views are rigid camera-to-world motions
            rigid_pose(c.to_world, f"the to_world of sensor {i} of {scene.path}")
        candidates = [c.with_resolution(width, height) for c in scene.sensors]
    else:
        candidates = make(n_candidates, 0.0)
    if generated == "rings":  # its held-out rings are shifted in elevation and azimuth
        heldout = make(n_heldout, 0.5)
    else:
        # Held-out views in the gaps between the candidates' places on the rig, as seen from its centre
        # (in the rig's own frame, where a hemisphere is the band above y_min).
        places = ((np.stack([c.position for c in candidates]) - centre) / axes) @ frame
        length = np.linalg.norm(places, axis=1, keepdims=True)
        away = length[:, 0] > 0  # a camera at the centre has no place on the rig
        places = places[away] / length[away]
        spiral = fibonacci_directions(_pool_size(len(candidates), n_heldout), 0.5, *band)
        # A hemisphere's rim: as if the rig went on below it, or held-out views crowd along it.
        mirror = (lambda points: _mirrored_below(points, band[0])) if band[0] > -1.0 else None
        taken = [places] + ([mirror(places)] if mirror else [])  # what held-out views keep away from
        if free is not None:  # and from furniture, as from candidates, or they crowd against it
            inside = ~free(spiral)
            taken.append(spiral[inside])
            spiral = spiral[~inside]
            if len(spiral) < n_heldout:
                raise short(len(spiral), n_heldout, "held-out")
        # Each a held-out spiral's point, moved within half its spacing into the largest gap.
        spacing = math.sqrt(2.0 * math.pi * (band[1] - band[0]) / n_heldout)  # radians, on the unit sphere
        targets = fibonacci_directions(n_heldout, 0.5, *band)
        heldout = at(spiral[places_apart(np.concatenate(taken), spiral, targets, spacing / 2, mirror)])
    check_disjoint(candidates, heldout)
    return candidates, heldout


def _film_height(sensors, width: int) -> int:
    """Image height for ``width`` at the one aspect ratio of the sensors' films
    (all candidates share one image size, so the films must agree)."""
    aspects = {Fraction(c.height, c.width) for c in sensors}
    if len(aspects) > 1:
        sizes = ", ".join(sorted({f"{c.width}x{c.height}" for c in sensors}))
        raise UserError(f"the scene's sensors have films of different aspect ratios ({sizes}); "
                        "rig 'xml' needs one, as all candidate views share one image size")
    return max(1, round(width * aspects.pop()))


def _check_count(n):
    if int(n) <= 0:
        raise ValueError(f"a rig needs at least one camera, got {n}")


def check_disjoint(candidates, heldout, tol=1e-6):
    """Raise if a held-out camera coincides with a candidate camera."""
    if not candidates or not heldout:
        return

    a = np.stack([c.to_world.ravel() for c in candidates])
    b = np.stack([c.to_world.ravel() for c in heldout])
    # The largest entry difference of any pair below tol, without a C x H x 16 array.
    if np.isfinite(cKDTree(a).query(b, p=np.inf, distance_upper_bound=tol)[0]).any():
        raise UserError("held-out cameras coincide with candidate cameras; use another rig offset")
