"""Embodiments: how a camera gets from one pose to the next, and what it costs.

An embodiment says which camera positions it can reach and the route
between two of them: its points, its length (scene units) and its time
(seconds, at the embodiment's speed). ``teleport`` is the seed paper's
protocol: every capture is free. ``drone`` flies freely, keeping a safety
margin from every surface of the Mitsuba scene, along the shortest route
it finds: the straight segment when that is clear, else a shortest path
over a visibility graph of waypoints offset from the scene's surfaces,
shortened by cutting corners wherever the cut is clear. ``ground`` is a
wheeled base in the plane across the scene's up axis at the height of its
start pose: holonomic, it moves as the drone does; with a turning radius
it is a car that drives forward along Dubins paths (:mod:`.dubins`),
facing where its camera looks at each pose (its camera is fixed to it;
a camera looking straight up or down leaves the heading free, and the
base then faces along the straight line to the other pose).

Collisions are ray casts through the scene: a segment is clear when its
axis and eight lines around it, at the margin's distance, meet no surface;
a point is clear when it lies in free space (not inside a closed object)
with no surface within the margin.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import mitsuba as mi
import numpy as np
from scipy.sparse.csgraph import dijkstra

from .checks import unknown_choice
from .dubins import DubinsPath, dubins_paths
from .errors import UserError
from .rigs import fibonacci_directions
from .scene.probes import first_hits

#: A drone's safety margin, as a share of the scene's bounding radius.
MARGIN_SHARE = 0.05
#: Surface points sampled for a drone's waypoints, and their offsets along the
#: normals in margins: near the inflated surface, where shortest routes bend.
SURFACE_SAMPLES = 256
WAYPOINT_OFFSETS = (1.25, 2.0, 4.0)
#: Lines around a segment's axis cast for its clearance.
RING = 8


@dataclass(frozen=True)
class Route:
    """A route between two camera positions.

    Attributes:
        points: (N, 3) float64 scene units, from the start to the end (N >= 2).
        length: its length in scene units (inf: no route was found).
        time: seconds it takes at the embodiment's speed.
    """

    points: np.ndarray
    length: float
    time: float

    @property
    def found(self) -> bool:
        return bool(np.isfinite(self.length))


def polyline_length(points: np.ndarray) -> float:
    """Length (scene units) of a polyline through ``points`` (N, 3)."""
    return float(np.linalg.norm(np.diff(np.asarray(points, dtype=np.float64), axis=0), axis=1).sum())


@dataclass
class Embodiment:
    """The interface of every embodiment: reachable positions and the routes between them.

    Attributes:
        speed: scene units per second.
    """

    name: ClassVar[str] = ""
    speed: float = 1.0

    def reachable(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: whether the camera can be at each of ``points`` (N, 3)."""
        raise NotImplementedError

    def paths(self, start: np.ndarray, targets: np.ndarray, start_view: np.ndarray | None = None,
              target_views: np.ndarray | None = None) -> list[Route]:
        """The routes from ``start`` (3,) to each of ``targets`` (T, 3). ``start_view`` (3,) and
        ``target_views`` (T, 3) are the cameras' unit viewing directions at them (None: any),
        which only a base that must turn to face them heeds."""
        raise NotImplementedError

    def start(self, position: np.ndarray) -> None:
        """Set out from ``position`` (3,): the first capture's."""

    def path(self, a: np.ndarray, b: np.ndarray, a_view: np.ndarray | None = None,
             b_view: np.ndarray | None = None) -> Route:
        """The route from ``a`` (3,) to ``b`` (3,), the cameras there looking along ``a_view``, ``b_view``
        (3,) (None: any)."""
        b_views = None if b_view is None else np.asarray(b_view, dtype=np.float64)[None]
        return self.paths(a, np.asarray(b, dtype=np.float64)[None], a_view, b_views)[0]

    def _route(self, points) -> Route:
        points = np.asarray(points, dtype=np.float64)
        length = polyline_length(points)
        return Route(points, length, length / self.speed)


@dataclass
class Teleport(Embodiment):
    """The seed paper's camera: it reaches any pose at once, at no cost."""

    name: ClassVar[str] = "teleport"

    def reachable(self, points):
        return np.ones(len(np.atleast_2d(points)), dtype=bool)

    def paths(self, start, targets, start_view=None, target_views=None):
        start = np.asarray(start, dtype=np.float64)
        return [Route(np.stack([start, t]), 0.0, 0.0) for t in np.asarray(targets, dtype=np.float64)]


@dataclass
class Drone(Embodiment):
    """Free flight in 3-D with a safety margin, along the shortest clear route.

    Attributes:
        mi_scene: the ``mitsuba.Scene`` whose surfaces block the way.
        margin: least distance (scene units) kept from every surface.
    """

    name: ClassVar[str] = "drone"
    mi_scene: object = None
    margin: float = 0.0
    _waypoints: np.ndarray | None = field(default=None, repr=False)
    _graph: np.ndarray | None = field(default=None, repr=False)
    _links: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        if self.mi_scene is None or not self.margin > 0:
            raise ValueError("a drone needs a scene and a positive margin")

    # -- ray casts --------------------------------------------------------------
    def _blocked(self, origins: np.ndarray, directions: np.ndarray, lengths: np.ndarray) -> np.ndarray:
        """(N,) bool: whether rays (origins, unit directions (N, 3)) meet a surface within ``lengths`` (N,)."""
        o, d = (np.asarray(a, dtype=np.float32) for a in (origins, directions))
        ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, j]) for j in range(3)]),
                       mi.Vector3f(*[mi.Float(d[:, j]) for j in range(3)]))
        ray.maxt = mi.Float(np.asarray(lengths, dtype=np.float32))
        return np.array(self.mi_scene.ray_test(ray), dtype=bool).reshape(len(o))

    def reachable(self, points):
        points = np.atleast_2d(np.asarray(points, dtype=np.float64))
        n = len(points)
        axes = np.concatenate([np.eye(3), -np.eye(3)])
        hit, front = first_hits(self.mi_scene, np.repeat(points, 6, 0), np.tile(axes, (n, 1)))
        inside = (hit & ~front).reshape(n, 6).any(axis=1)
        dirs = fibonacci_directions(32)
        near = self._blocked(np.repeat(points, len(dirs), 0), np.tile(dirs, (n, 1)),
                             np.full(n * len(dirs), self.margin)).reshape(n, -1).any(axis=1)
        return ~inside & ~near

    def clear(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(N,) bool: whether the segments from ``a`` to ``b`` (N, 3) keep the margin from every surface
        (their ends are not checked: see :meth:`reachable`)."""
        a, b = np.atleast_2d(a).astype(np.float64), np.atleast_2d(b).astype(np.float64)
        d = b - a
        length = np.linalg.norm(d, axis=1)
        ok = length > 0
        d[ok] /= length[ok, None]
        d[~ok] = (1.0, 0.0, 0.0)
        # Two unit vectors across each segment.
        helper = np.where(np.abs(d[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        u = np.cross(d, helper)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        v = np.cross(d, u)
        angles = 2 * np.pi * np.arange(RING) / RING
        offsets = [np.zeros_like(u)] + [self.margin * (np.cos(t) * u + np.sin(t) * v) for t in angles]
        origins = np.concatenate([a + o for o in offsets])
        blocked = self._blocked(origins, np.tile(d, (len(offsets), 1)), np.tile(length, len(offsets)))
        return ~blocked.reshape(len(offsets), -1).any(axis=0)

    # -- the visibility graph -----------------------------------------------------
    def waypoints(self) -> np.ndarray:
        """(W, 3) clear points offset from the scene's surfaces along their normals (both sides)."""
        if self._waypoints is None:
            self._waypoints = self._make_waypoints()
            w = self._waypoints
            i, j = np.triu_indices(len(w), 1)
            graph = np.full((len(w), len(w)), np.inf)
            ok = self.clear(w[i], w[j])
            lengths = np.linalg.norm(w[i] - w[j], axis=1)
            graph[i[ok], j[ok]] = graph[j[ok], i[ok]] = lengths[ok]
            self._graph = graph
        return self._waypoints

    def _make_waypoints(self) -> np.ndarray:
        shapes = list(self.mi_scene.shapes())
        areas = np.array([float(np.asarray(s.surface_area()).ravel()[0]) for s in shapes])
        counts = np.maximum(1, np.round(SURFACE_SAMPLES * areas / max(areas.sum(), 1e-30))).astype(int)
        rng = np.random.default_rng(0)
        points = []
        for shape, k in zip(shapes, counts):
            uv = rng.random((k, 2)).astype(np.float32)
            ps = shape.sample_position(0.0, mi.Point2f(mi.Float(uv[:, 0]), mi.Float(uv[:, 1])))
            p = np.array(ps.p, dtype=np.float64).reshape(3, -1).T
            n = np.array(ps.n, dtype=np.float64).reshape(3, -1).T
            for s in WAYPOINT_OFFSETS:
                points += [p + s * self.margin * n, p - s * self.margin * n]
        points = np.concatenate(points)
        return points[self.reachable(points)]

    def paths(self, start, targets, start_view=None, target_views=None):
        start = np.asarray(start, dtype=np.float64)
        targets = np.atleast_2d(np.asarray(targets, dtype=np.float64))
        direct = self.clear(np.broadcast_to(start, targets.shape), targets)
        if direct.all():
            return [self._route([start, t]) for t in targets]

        w = self.waypoints()
        nw, nt = len(w), len(targets)
        # Nodes: the waypoints, then the targets, then the start.
        graph = np.full((nw + nt + 1, nw + nt + 1), np.inf)
        graph[:nw, :nw] = self._graph
        for k, t in enumerate(targets):
            graph[nw + k, :nw] = graph[:nw, nw + k] = self._link(t)
        graph[-1, :nw] = graph[:nw, -1] = self._link(start, cache=False)
        gaps = np.linalg.norm(targets - start, axis=1)
        graph[-1, nw:nw + nt] = np.where(direct, gaps, np.inf)
        graph[np.isinf(graph)] = 0  # csgraph: 0 is no edge
        dist, pred = dijkstra(graph, directed=False, indices=nw + nt, return_predecessors=True)
        points = np.concatenate([w, targets])  # the graph's nodes but the start
        routes = []
        for k, t in enumerate(targets):
            if direct[k]:
                routes.append(self._route([start, t]))
            elif not np.isfinite(dist[nw + k]):
                routes.append(Route(np.stack([start, t]), np.inf, np.inf))
            else:
                chain, node = [], nw + k
                while node != nw + nt:
                    chain.append(node)
                    node = pred[node]
                # A shortest way may pass through another target, a clear point too.
                nodes = np.concatenate([[start], points[list(reversed(chain[1:]))], [t]])
                routes.append(self._route(self._shortcut(nodes)))
        return routes

    def _link(self, point: np.ndarray, cache: bool = True) -> np.ndarray:
        """(W,) lengths of the clear segments from ``point`` to the waypoints (inf: blocked)."""
        key = tuple(np.round(point, 9))
        if cache and key in self._links:
            return self._links[key]
        w = self.waypoints()
        ok = self.clear(np.broadcast_to(point, w.shape), w)
        link = np.where(ok, np.linalg.norm(w - point, axis=1), np.inf)
        if cache:
            self._links[key] = link
        return link

    def _shortcut(self, nodes: np.ndarray) -> np.ndarray:
        """The polyline ``nodes`` (N, 3) with each corner cut that is clear: from each
        kept point, on to the farthest later one it sees."""
        kept, i = [nodes[0]], 0
        while i < len(nodes) - 1:
            later = np.arange(i + 1, len(nodes))
            ok = self.clear(np.broadcast_to(nodes[i], (len(later), 3)), nodes[later])
            ok[0] = True  # the graph's own edge
            i = int(later[np.nonzero(ok)[0].max()])
            kept.append(nodes[i])
        return np.stack(kept)


@dataclass
class Ground(Drone):
    """A wheeled base: the camera keeps the height of its start pose along ``up``.

    Holonomic without a turning radius; with one, a car that drives forward
    only, along the shortest Dubins path (:mod:`.dubins`) that keeps the
    margin between poses, facing at each pose where its camera looks
    horizontally. Where no path is clear it drives the holonomic route's
    polyline (its corners cut), a Dubins path from corner to corner, facing
    at each corner along the bisector of the lines that meet there; where
    that too meets a surface, the pose is out of reach.

    Attributes:
        up: (3,) unit up axis of the scene.
        height: the camera's height along ``up`` (scene units; None: set by :meth:`start`).
        turning_radius: the least radius of its turns (scene units; 0: holonomic, it turns in place).
    """

    name: ClassVar[str] = "ground"
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    height: float | None = None
    turning_radius: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        if not (np.isfinite(self.turning_radius) and self.turning_radius >= 0):
            raise ValueError(f"a turning radius must be a finite number >= 0, got {self.turning_radius!r}")
        self.up = np.asarray(self.up, dtype=np.float64) / np.linalg.norm(self.up)
        # The plane's axes, u then v counter-clockwise about up: a left turn is a positive angle.
        helper = np.eye(3)[int(np.argmin(np.abs(self.up)))]
        self._u = np.cross(self.up, helper)
        self._u /= np.linalg.norm(self._u)
        self._v = np.cross(self.up, self._u)

    def start(self, position):
        if self.height is None:
            self.height = float(np.dot(position, self.up))

    def _in_plane(self, points: np.ndarray) -> np.ndarray:
        return np.abs(points @ self.up - self.height) <= 0.01 * self.margin

    def reachable(self, points):
        points = np.atleast_2d(np.asarray(points, dtype=np.float64))
        if self.height is None:
            return super().reachable(points)
        return self._in_plane(points) & super().reachable(points)

    def paths(self, start, targets, start_view=None, target_views=None):
        start = np.asarray(start, dtype=np.float64)
        targets = np.atleast_2d(np.asarray(targets, dtype=np.float64))
        self.start(start)
        if not self._in_plane(start[None])[0]:
            raise ValueError(f"a ground route starts at the base's height {self.height}, not at {start}")
        off = ~self._in_plane(targets)  # another height: the base cannot get there
        if self.turning_radius > 0:
            routes = self._dubins_routes(start, targets, start_view, target_views, ~off)
        else:
            routes = super().paths(start, targets)
        return [Route(np.stack([start, t]), np.inf, np.inf) if o else r for r, o, t in zip(routes, off, targets)]

    # -- a base with a turning radius ---------------------------------------------
    def _flat(self, points: np.ndarray) -> np.ndarray:
        """(N, 2) scene units: ``points`` (N, 3) in the plane's axes."""
        return np.stack([points @ self._u, points @ self._v], axis=1)

    def _lift(self, poses: np.ndarray) -> np.ndarray:
        """(N, 3) scene units: plane poses (N, 3) (x, y, heading) at the base's height."""
        return self.height * self.up + poses[:, :1] * self._u + poses[:, 1:2] * self._v

    def _heading(self, view, chord: np.ndarray) -> float:
        """The base's heading (radians in the plane) facing ``view`` (3,) horizontally; along
        ``chord`` (2,) where there is no view (None or NaN) or it looks straight up or down."""
        if view is not None:
            f = self._flat(np.asarray(view, dtype=np.float64)[None])[0]
            if np.hypot(*f) > 1e-6:  # False for NaN too
                return float(np.arctan2(f[1], f[0]))
        return float(np.arctan2(chord[1], chord[0]))

    def _first_clear(self, options: list[list[DubinsPath]]) -> list[DubinsPath | None]:
        """For each list of paths (shortest first), the first whose sampled curve keeps the margin
        (None: none does); the lists' paths of one rank are cast together."""
        chosen: list[DubinsPath | None] = [None] * len(options)
        left, rank = [k for k, o in enumerate(options) if o], 0
        while left:
            curves = [self._lift(options[k][rank].sample()) for k in left]
            ok = self.clear(np.concatenate([c[:-1] for c in curves]), np.concatenate([c[1:] for c in curves]))
            ends = np.cumsum([len(c) - 1 for c in curves])
            clear = [bool(part.all()) for part in np.split(ok, ends[:-1])]
            for k, good in zip(left, clear):
                if good:
                    chosen[k] = options[k][rank]
            rank += 1
            left = [k for k, good in zip(left, clear) if not good and rank < len(options[k])]
        return chosen

    def _legs(self, nodes: np.ndarray, first_view, last_view) -> list[list[DubinsPath]]:
        """Each leg's Dubins paths, shortest first, along the polyline ``nodes`` (N, 3): facing
        ``first_view`` and ``last_view`` at its ends, along the bisector at its corners."""
        flat = self._flat(nodes)
        chords = np.diff(flat, axis=0)
        units = chords / np.maximum(np.linalg.norm(chords, axis=1, keepdims=True), 1e-300)
        headings = [self._heading(first_view, chords[0])]
        for k in range(1, len(flat) - 1):
            b = units[k - 1] + units[k]
            headings.append(float(np.arctan2(*(b if np.hypot(*b) > 1e-9 else units[k])[::-1])))
        headings.append(self._heading(last_view, chords[-1]))
        return [dubins_paths((*flat[k], headings[k]), (*flat[k + 1], headings[k + 1]), self.turning_radius)
                for k in range(len(flat) - 1)]

    def _dubins_routes(self, start, targets, start_view, target_views, wanted: np.ndarray) -> list[Route]:
        """The Dubins routes from ``start`` (3,) to the ``wanted`` (T,) bool of ``targets`` (T, 3)
        (the others: not found)."""
        views = [None] * len(targets) if target_views is None else list(target_views)
        none = [Route(np.stack([start, t]), np.inf, np.inf) for t in targets]
        picks = self._first_clear([self._legs(np.stack([start, t]), start_view, views[k])[0] if wanted[k] else []
                                   for k, t in enumerate(targets)])
        routes = [self._dubins_route([p], start, t) if p else none[k] for k, (p, t) in enumerate(zip(picks, targets))]
        blocked = [k for k in range(len(targets)) if wanted[k] and picks[k] is None]
        if not blocked:
            return routes
        # Around the geometry: the holonomic route's corners, Dubins paths between them.
        chains = super().paths(start, targets[blocked])
        legs = {k: self._legs(r.points, start_view, views[k]) for k, r in zip(blocked, chains) if r.found}
        flat = [paths for k in legs for paths in legs[k]]
        picked = iter(self._first_clear(flat))
        for k in legs:
            mine = [next(picked) for _ in legs[k]]
            if all(mine):
                routes[k] = self._dubins_route(mine, start, targets[k])
        return routes

    def _dubins_route(self, legs: list[DubinsPath], start: np.ndarray, target: np.ndarray) -> Route:
        """The route along ``legs`` from ``start`` to ``target`` (3,): its sampled curve, its Dubins length."""
        points = np.concatenate([self._lift(p.sample())[(0 if k == 0 else 1):] for k, p in enumerate(legs)])
        if len(points) < 2:  # no way to go: it is there, facing the right way
            points = np.stack([start, target])
        points[0], points[-1] = start, target
        length = float(sum(p.length for p in legs))
        return Route(points, length, length / self.speed)

    def _make_waypoints(self) -> np.ndarray:
        # The drone's waypoints dropped onto the plane, and a grid over the scene's extent in it.
        flat = super()._make_waypoints()
        flat = flat - np.outer(flat @ self.up - self.height, self.up)
        lo, hi = (np.asarray(b, dtype=np.float64) for b in (self.mi_scene.bbox().min, self.mi_scene.bbox().max))
        centre, reach = 0.5 * (lo + hi), 0.75 * np.linalg.norm(hi - lo)
        u, v = self._u, self._v
        t = np.linspace(-reach, reach, 24)
        a, b = np.meshgrid(t, t)
        base = centre - (centre @ self.up - self.height) * self.up
        grid = base + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
        points = np.concatenate([flat, grid])
        return points[super().reachable(points)]


EMBODIMENTS = {cls.name: cls for cls in (Teleport, Drone, Ground)}


def make_embodiment(name: str, scene=None, speed: float = 1.0, turning_radius: float = 0.0) -> Embodiment:
    """The embodiment ``name`` in ``scene`` (a :class:`~mitsuba_active.scene.Scene`, or None for a
    dataset, which has no geometry to fly around), a ground base's with ``turning_radius`` (scene
    units); UserError for an unknown one, or a turning radius for another."""
    if name not in EMBODIMENTS:
        raise UserError(unknown_choice("embodiment", name, EMBODIMENTS))
    if turning_radius and name != "ground":
        raise UserError(f"a turning radius applies to the ground embodiment, not the {name}")
    if name == "teleport":
        return Teleport(speed=speed)
    if scene is None:
        raise UserError(f"the {name} embodiment moves through a scene's geometry; a dataset has none "
                        "(use --embodiment teleport)")
    if name == "ground":
        return Ground(speed=speed, mi_scene=scene.mi_scene, margin=MARGIN_SHARE * scene.radius, up=scene.up,
                      turning_radius=turning_radius)
    return Drone(speed=speed, mi_scene=scene.mi_scene, margin=MARGIN_SHARE * scene.radius)
