"""Probes of a loaded scene's geometry: first hits, and whether it is a room.

A room is seen from inside: from the middle of its bounds, surfaces
surround a camera in most directions. An object is seen from outside, also
when it is hollow (a cup, a vase) or has a hole through it (a nut, a
washer, a pipe). :func:`classify` tells them apart by casting rays from
probe points spread through the scene's bounding box, and says why.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..rigs import fibonacci_directions

#: Rays cast from each probe point, spread evenly over the sphere.
PROBE_RAYS = 512
#: Share of a probe's rays that must hit for surfaces to surround it.
SURROUNDED = 0.75
#: Share of the hits that must meet front faces for a probe to lie in free space.
FRONT_FACING = 0.8
#: Fewest rays (and share of the other side's) that make an opening on the
#: far side of a probe: a through-hole lets rays out both ways.
OPENING_RAYS = 2
OPENING_SHARE = 0.05
#: The six axis directions, probed too: a bore too narrow for the spread
#: rays to find is found along the axis it was modelled on.
AXES = np.concatenate([np.eye(3), -np.eye(3)])


@dataclass(frozen=True)
class Enclosure:
    """Whether a scene is a room seen from inside, and why.

    Attributes:
        interior: True for a room.
        reason: why, in words that follow "it is" / "it is not" a room
            (for messages such as "rig interior: ...").
    """

    interior: bool
    reason: str


def _intersect(mi_scene, origins: np.ndarray, directions: np.ndarray):
    """The rays (origins and directions (N, 3), scene units) as a ``mi.Ray3f``, and their first intersections."""
    o, d = (np.asarray(a, dtype=np.float32) for a in (origins, directions))
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, j]) for j in range(3)]),
                   mi.Vector3f(*[mi.Float(d[:, j]) for j in range(3)]))
    return ray, mi_scene.ray_intersect(ray)


def hit_distances(mi_scene, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(N,) float64: how far each ray (origins and unit directions (N, 3),
    scene units) travels to its first surface; inf where it meets none."""
    _, si = _intersect(mi_scene, origins, directions)
    return np.where(np.array(si.is_valid()), np.array(si.t, dtype=np.float64), np.inf)


def first_hits(mi_scene, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) bool arrays ``hit`` and ``front``: whether each ray (origins and
    directions (N, 3), scene units) meets a surface, and whether the first
    one faces it."""
    ray, si = _intersect(mi_scene, origins, directions)
    hit = np.array(si.is_valid())
    return hit, np.array(dr.dot(si.n, ray.d) < 0) & hit


def _through(escapes: np.ndarray, axes_out: np.ndarray) -> bool:
    """True when the rays that got out of a surrounded probe leave on two
    opposite sides, as through a hole, not through one opening.

    ``escapes``: (m, 3) directions of the spread rays that got out;
    ``axes_out``: (6,) bool, which of :data:`AXES` got out.
    """
    if (axes_out[:3] & axes_out[3:]).any():
        return True
    if len(escapes) < 2 * OPENING_RAYS:
        return False
    axis = np.linalg.eigh(escapes.T @ escapes)[1][:, -1]  # the openings' main direction
    along = escapes @ axis
    ahead, behind = int((along > 0.5).sum()), int((along < -0.5).sum())
    return min(ahead, behind) >= max(OPENING_RAYS, OPENING_SHARE * max(ahead, behind))


def classify(mi_scene, bbox_min, bbox_max, up=(0.0, 1.0, 0.0), n=PROBE_RAYS) -> Enclosure:
    """Whether the scene is a room to be seen from inside.

    Rays go out from 27 probe points spread through the box
    (``bbox_min``, ``bbox_max``: (3,) scene units). A probe whose rays first
    meet back faces lies inside a closed object (a pillar, a table) and is
    skipped. A free probe is surrounded when most of its rays hit, and
    mostly front faces: so it is in a room, and also in the bore of a nut or
    a pipe, or the hollow of a cup. The rays that get out tell them apart:
    out of a hole they leave on two opposite sides; a container opens
    upwards (along ``up``); a room is closed, or open at one side (as the
    Cornell box is at its front), or has walls that show their backs to
    rays from outside (a room of one-sided walls, also without a ceiling).
    """
    lo, hi = np.asarray(bbox_min, dtype=np.float64), np.asarray(bbox_max, dtype=np.float64)
    steps = np.array([0.25, 0.5, 0.75])
    probes = lo + np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), -1).reshape(-1, 3) * (hi - lo)
    d = fibonacci_directions(n)
    both = np.concatenate([d, AXES])
    hit, front = (a.reshape(len(probes), -1) for a in first_hits(mi_scene, np.repeat(probes, len(both), 0),
                                                                    np.tile(both, (len(probes), 1))))
    (hit, axis_hit), front = np.split(hit, [n], axis=1), front[:, :n]
    hits, fronts = hit.sum(axis=1), front.sum(axis=1)
    free = hits - fronts <= 0.5 * hits
    surrounded = free & (hits > SURROUNDED * n) & (fronts > FRONT_FACING * hits)
    if not surrounded.any() or surrounded.sum() < 0.5 * free.sum():
        return Enclosure(False, "an object seen from outside: surfaces surround little of the space in its bounds")
    escaped = [d[~h] for h in hit[surrounded]]
    if sum(_through(e, ~a) for e, a in zip(escaped, axis_hit[surrounded])) > 0.5 * len(escaped):
        return Enclosure(False, "an object with a hole through it: rays from inside the hole get out "
                                "on two opposite sides")
    escapes = np.concatenate(escaped)
    if not len(escapes) or (escapes @ np.asarray(up, dtype=np.float64)).sum() <= 0.5 * len(escapes):
        return Enclosure(True, "a room seen from inside: surfaces surround the middle of its bounds, "
                               "closed or open at one side")
    # From outside: rays from a sphere around the box towards points spread through it.
    m = 512
    origins = 0.5 * (lo + hi) + np.linalg.norm(hi - lo) * fibonacci_directions(m)
    targets = lo + np.random.default_rng(0).random((m, 3)) * (hi - lo)
    toward = (targets - origins) / np.linalg.norm(targets - origins, axis=1, keepdims=True)
    out_hit, out_front = first_hits(mi_scene, origins, toward)
    if (out_hit & ~out_front).sum() > 0.5 * out_hit.sum():
        return Enclosure(True, "a room seen from inside: its walls open upwards and face inwards")
    return Enclosure(False, "a hollow object seen from outside: its hollow opens upwards, as a cup's does")
