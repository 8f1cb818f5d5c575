"""Dubins paths: the shortest forward-only routes of a car with a least turning radius.

A pose is ``(x, y, theta)``: a point in the plane (scene units) and a
heading (radians, counter-clockwise from the x axis). Between two poses
the shortest path of a car that drives forward and turns no tighter than
radius ``r`` is one of six words (Dubins 1957): three pieces, each a left
turn ``L`` (counter-clockwise), a right turn ``R`` (clockwise) or a
straight ``S``, in the orders LSL, RSR, LSR, RSL, RLR and LRL. The
formulas are those of Shkel and Lumelsky (2001), in units of ``r``:
``d`` is the distance between the points over ``r``, ``alpha`` and
``beta`` the headings relative to the line between them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: The six words, each three pieces: L (left turn), S (straight), R (right turn).
WORDS = ("LSL", "RSR", "LSR", "RSL", "RLR", "LRL")
#: Largest heading change (radians) between the points sampled along a turn.
ARC_STEP = math.radians(5.0)
#: Rounding allowed in the words' formulas (units of the radius, radians): a piece of
#: length 0 must not come out as a full turn, nor a tangent case as no path.
EPS = 1e-9


def mod2pi(angle: float) -> float:
    """``angle`` (radians) in [0, 2 pi) (within :data:`EPS` of 2 pi: 0)."""
    a = math.fmod(angle, 2 * math.pi)
    a = a + 2 * math.pi if a < 0 else a
    return 0.0 if a > 2 * math.pi - EPS else a


@dataclass(frozen=True)
class DubinsPath:
    """One word's path from a start pose.

    Attributes:
        start: (x, y, theta): scene units, scene units, radians.
        word: the pieces' kinds, e.g. ``"LSR"``.
        pieces: the three pieces' lengths in scene units (a turn's: radius x angle).
        radius: the turning radius, scene units.
    """

    start: tuple
    word: str
    pieces: tuple
    radius: float

    @property
    def length(self) -> float:
        """Scene units."""
        return float(sum(self.pieces))

    def sample(self, step: float | None = None) -> np.ndarray:
        """(N, 3) float64 poses (x, y, theta) along the path, from its start to its end: both
        ends of each piece, and points no more than :data:`ARC_STEP` of heading apart along
        its turns (and ``step`` scene units apart along them all, where given)."""
        x, y, th = self.start
        out = [(x, y, th)]
        for kind, length in zip(self.word, self.pieces):
            if length <= 0:
                continue
            n = 1 if kind == "S" else max(1, math.ceil(length / self.radius / ARC_STEP))
            if step:
                n = max(n, math.ceil(length / step))
            for s in np.linspace(0, length, n + 1)[1:]:
                out.append(_move((x, y, th), kind, s, self.radius))
            x, y, th = _move((x, y, th), kind, length, self.radius)
            out[-1] = (x, y, th)
        return np.array(out, dtype=np.float64)

    @property
    def end(self) -> tuple:
        """(x, y, theta) where the path ends."""
        pose = self.start
        for kind, length in zip(self.word, self.pieces):
            pose = _move(pose, kind, length, self.radius)
        return pose


def _move(pose: tuple, kind: str, s: float, r: float) -> tuple:
    """The pose ``s`` scene units on from ``pose`` along a piece of ``kind`` of radius ``r``."""
    x, y, th = pose
    if kind == "S":
        return x + s * math.cos(th), y + s * math.sin(th), th
    turn = 1.0 if kind == "L" else -1.0
    phi = th + turn * s / r
    return x + turn * r * (math.sin(phi) - math.sin(th)), y - turn * r * (math.cos(phi) - math.cos(th)), phi


def _word(word: str, d: float, a: float, b: float) -> tuple | None:
    """The pieces (in units of the radius) of ``word`` for the normalised problem, or None where it has none."""
    sa, sb, ca, cb = math.sin(a), math.sin(b), math.cos(a), math.cos(b)
    c_ab = math.cos(a - b)
    if word == "LSL":
        p2 = 2 + d * d - 2 * c_ab + 2 * d * (sa - sb)
        if p2 < -EPS:
            return None
        tmp = math.atan2(cb - ca, d + sa - sb)
        return mod2pi(tmp - a), math.sqrt(max(p2, 0.0)), mod2pi(b - tmp)
    if word == "RSR":
        p2 = 2 + d * d - 2 * c_ab + 2 * d * (sb - sa)
        if p2 < -EPS:
            return None
        tmp = math.atan2(ca - cb, d - sa + sb)
        return mod2pi(a - tmp), math.sqrt(max(p2, 0.0)), mod2pi(tmp - b)
    if word == "LSR":
        p2 = -2 + d * d + 2 * c_ab + 2 * d * (sa + sb)
        if p2 < -EPS:
            return None
        p = math.sqrt(max(p2, 0.0))
        tmp = math.atan2(-ca - cb, d + sa + sb) - math.atan2(-2.0, p)
        return mod2pi(tmp - a), p, mod2pi(tmp - b)
    if word == "RSL":
        p2 = -2 + d * d + 2 * c_ab - 2 * d * (sa + sb)
        if p2 < -EPS:
            return None
        p = math.sqrt(max(p2, 0.0))
        tmp = math.atan2(ca + cb, d - sa - sb) - math.atan2(2.0, p)
        return mod2pi(a - tmp), p, mod2pi(b - tmp)
    if word == "RLR":
        c = (6 - d * d + 2 * c_ab + 2 * d * (sa - sb)) / 8
        if abs(c) > 1 + EPS:
            return None
        p = mod2pi(2 * math.pi - math.acos(min(max(c, -1.0), 1.0)))
        t = mod2pi(a - math.atan2(ca - cb, d - sa + sb) + p / 2)
        return t, p, mod2pi(a - b - t + p)
    if word == "LRL":
        c = (6 - d * d + 2 * c_ab + 2 * d * (sb - sa)) / 8
        if abs(c) > 1 + EPS:
            return None
        p = mod2pi(2 * math.pi - math.acos(min(max(c, -1.0), 1.0)))
        t = mod2pi(-a - math.atan2(ca - cb, d + sa - sb) + p / 2)
        return t, p, mod2pi(b - a - t + p)
    raise ValueError(f"no Dubins word {word!r}; the words are {', '.join(WORDS)}")


def dubins_paths(start, end, radius: float) -> list[DubinsPath]:
    """The paths of every word that joins pose ``start`` to pose ``end`` (each ``(x, y, theta)``,
    scene units and radians) with turns of ``radius`` scene units, shortest first."""
    if not radius > 0:
        raise ValueError(f"a Dubins path needs a positive turning radius, got {radius!r}")
    x0, y0, th0 = (float(v) for v in start)
    x1, y1, th1 = (float(v) for v in end)
    dx, dy = x1 - x0, y1 - y0
    phi = math.atan2(dy, dx) if dx or dy else 0.0
    d, a, b = math.hypot(dx, dy) / radius, mod2pi(th0 - phi), mod2pi(th1 - phi)
    paths = []
    for word in WORDS:
        pieces = _word(word, d, a, b)
        if pieces is not None:
            paths.append(DubinsPath((x0, y0, th0), word, tuple(radius * v for v in pieces), radius))
    return sorted(paths, key=lambda p: p.length)


def dubins_path(start, end, radius: float) -> DubinsPath:
    """The shortest path from pose ``start`` to pose ``end`` (see :func:`dubins_paths`)."""
    return dubins_paths(start, end, radius)[0]
