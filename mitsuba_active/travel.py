"""Travel: where a run's camera is, how far it has gone, and whether the next capture fits.

A run's camera starts at its first capture and moves between captures along
its embodiment's routes (:mod:`~mitsuba_active.embodiments`). Each capture
adds its route's length and time, plus a time per capture; the run stops
when the next capture would pass the travel budget (scene units) or the
mission-time budget (seconds). With a cost weight λ > 0 the planner's scores
are weighed against the travel: each pick maximises the utility (the
planner's scores, scaled to [0, 1] over the candidates left) less λ times
the route's length over the scene's diameter, as ActiveGS does; a batch is
then visited in a short tour (nearest next).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .checks import is_number, unknown_choice
from .embodiments import EMBODIMENTS, Embodiment, Route

#: The travel settings of :class:`~mitsuba_active.run.RunConfig`, their defaults (a record
#: without them ran as these) and their command-line help.
TRAVEL_SETTINGS = {
    "embodiment": ("teleport", "How the camera moves: " + ", ".join(EMBODIMENTS)
                   + " (teleport: every capture is free, as in the seed paper)."),
    "travel_budget": (None, "Distance the camera may travel, in scene units [no limit]."),
    "time_budget": (None, "Mission time in seconds: travel over --speed plus --capture-time a view [no limit]."),
    "speed": (1.0, "Camera speed in scene units per second."),
    "turning_radius": (0.0, "A ground base's least turning radius in scene units: it drives forward along Dubins "
                            "paths, facing where its camera looks at each pose (0: holonomic)."),
    "capture_time": (0.0, "Seconds each capture takes."),
    "cost_weight": (0.0, "Weight of the travel cost against the planner's utility (0: cost-blind)."),
    "along_the_way": (None, "Also capture a view every this many scene units along each route, looking at the "
                            "scene's centre; they count as views [off]."),
    "candidates_mode": ("pool", "pool: choose from the rig's fixed candidates; continuous: score a fresh sample of "
                                "reachable poses on the rig each round (as many as --candidates), refine around "
                                "the best, capture it (scenes only)."),
    "nearest": (0.75, "With --candidates-mode continuous around an object: the nearest a fresh pose comes to "
                      "the centre, as a share of the rig's distance (1: on the rig only); the interior rig's "
                      "poses stay on it."),
}
#: The settings whose value a record from before them ran as, where that is not the default.
TRAVEL_LEGACY = {"nearest": 1.0}

#: The ways a planner is offered poses (``candidates_mode``).
CANDIDATE_MODES = ("pool", "continuous")


def travel_problems(cfg) -> list[str]:
    """The messages refusing ``cfg``'s travel settings (none: they make a run)."""
    problems = []
    if not isinstance(cfg.embodiment, str) or cfg.embodiment not in EMBODIMENTS:
        problems.append(unknown_choice("embodiment", cfg.embodiment, EMBODIMENTS))
    for name in ("travel_budget", "time_budget"):
        value = getattr(cfg, name)
        if value is not None and not (is_number(value, finite=True) and value > 0):
            problems.append(f"{name} must be a positive number, got {value!r}")
    if not (is_number(cfg.speed, finite=True) and cfg.speed > 0):
        problems.append(f"the speed must be a positive number, got {cfg.speed!r}")
    if not (is_number(cfg.turning_radius, finite=True) and cfg.turning_radius >= 0):
        problems.append(f"turning_radius must be a finite number >= 0 (scene units), got {cfg.turning_radius!r}")
    elif cfg.turning_radius > 0 and cfg.embodiment != "ground":
        problems.append(f"turning_radius (--turning-radius) applies to a ground base, not the {cfg.embodiment} "
                        "(choose --embodiment ground)")
    if cfg.along_the_way is not None and not (is_number(cfg.along_the_way, finite=True) and cfg.along_the_way > 0):
        problems.append(f"along_the_way must be a positive spacing in scene units, got {cfg.along_the_way!r}")
    if not isinstance(cfg.candidates_mode, str) or cfg.candidates_mode not in CANDIDATE_MODES:
        problems.append(unknown_choice("candidates mode", cfg.candidates_mode, CANDIDATE_MODES))
    if not (is_number(cfg.nearest, finite=True) and 0 < cfg.nearest <= 1):
        problems.append(f"nearest (--nearest) must be a share of the rig's distance in (0, 1], got {cfg.nearest!r}")
    if cfg.candidates_mode == "continuous" and getattr(cfg, "rig", None) == "xml":
        problems.append("candidates_mode continuous (--candidates-mode) samples the rig's surface, and --rig xml "
                        "has none (choose a generated rig)")
    for name in ("capture_time", "cost_weight"):
        value = getattr(cfg, name)
        if not (is_number(value, finite=True) and value >= 0):
            problems.append(f"{name} must be a finite number >= 0, got {value!r}")
    if not problems and cfg.embodiment == "teleport":
        for name, flag in (("travel_budget", "--travel-budget"), ("cost_weight", "--cost-weight"),
                           ("along_the_way", "--along-the-way")):
            if getattr(cfg, name):  # it would change nothing: a teleport travels no distance
                problems.append(f"{name} ({flag}) applies to a moving embodiment; a teleport travels nowhere "
                                "(choose --embodiment drone)")
    if not problems and cfg.time_budget is not None and cfg.capture_time > cfg.time_budget:
        problems.append(f"no capture fits the time budget of {cfg.time_budget:g} s: each takes "
                        f"{cfg.capture_time:g} s (--capture-time)")
    return problems


@dataclass
class Stop:
    """Why a run's camera stopped before its view budget.

    Attributes:
        views: views captured when it stopped.
        reason: why, in words ("the next capture needs 2.3 scene units, and 0.4 are left").
    """

    views: int
    reason: str


class Journey:
    """A run's camera on its way: its position and the distance and time so far.

    ``positions``: (C, 3) float64 candidate camera positions (scene units);
    ``diameter``: the scene's diameter (scene units), the scale of travel costs;
    ``views``: (C, 3) float64 the candidates' unit viewing directions (None: any),
    which a base that turns to face them heeds.
    """

    def __init__(self, embodiment: Embodiment, cfg, positions: np.ndarray, diameter: float,
                 views: np.ndarray | None = None):
        self.embodiment, self.cfg = embodiment, cfg
        self.positions = np.asarray(positions, dtype=np.float64)
        self.views = None if views is None else np.asarray(views, dtype=np.float64).reshape(-1, 3)
        self.diameter = float(diameter)
        self.position: np.ndarray | None = None
        self.view: np.ndarray | None = None  # the camera's viewing direction where it is
        self.legs: list[dict] = []  # per capture: {"distance", "time"} so far (cumulative)
        self.stop: Stop | None = None

    @property
    def distance(self) -> float:
        return self.legs[-1]["distance"] if self.legs else 0.0

    @property
    def time(self) -> float:
        return self.legs[-1]["time"] if self.legs else 0.0

    @property
    def weighs_travel(self) -> bool:
        """Whether :meth:`weigh` chooses the picks again against the travel cost (a cost weight, and a place)."""
        return self.cfg.cost_weight > 0 and self.position is not None

    def route(self, index: int) -> Route:
        """The route from the camera's position to candidate ``index`` (none before the first capture)."""
        target = self.positions[index]
        if self.position is None:
            return Route(np.stack([target, target]), 0.0, 0.0)
        return self.embodiment.path(self.position, target, self.view, self._view(index))

    def _view(self, index: int) -> np.ndarray | None:
        return None if self.views is None else self.views[index]

    def fits(self, index: int) -> tuple[Route, str | None]:
        """The route to candidate ``index``, and why its capture does not fit the budgets (None: it fits)."""
        route = self.route(index)
        if not route.found:
            return route, f"the {self.embodiment.name} finds no clear route to candidate {index}"
        distance = self.distance + route.length
        time = self.time + route.time + self.cfg.capture_time
        budget, time_budget = self.cfg.travel_budget, self.cfg.time_budget
        if budget is not None and distance > budget * (1 + 1e-9):
            return route, (f"the next capture needs {route.length:.4g} scene units of travel, and "
                           f"{budget - self.distance:.4g} of the travel budget's {budget:g} are left")
        if time_budget is not None and time > time_budget * (1 + 1e-9):
            return route, (f"the next capture needs {route.time + self.cfg.capture_time:.4g} s, and "
                           f"{time_budget - self.time:.4g} of the time budget's {time_budget:g} s are left")
        return route, None

    def add(self, position: np.ndarray, view: np.ndarray | None = None) -> int:
        """Make ``position`` (3,), looking along ``view`` (3,; None: any), the next candidate's (one
        the run appended); its index."""
        self.positions = np.concatenate([self.positions, np.asarray(position, dtype=np.float64).reshape(1, 3)])
        if self.views is not None:  # NaN: no view, the heading is free
            view = np.full(3, np.nan) if view is None else np.asarray(view, dtype=np.float64)
            self.views = np.concatenate([self.views, view.reshape(1, 3)])
        return len(self.positions) - 1

    def advance(self, index: int, route: Route) -> None:
        """Move to candidate ``index`` along ``route`` and capture there."""
        self.position, self.view = self.positions[index], self._view(index)
        leg = {"distance": round(self.distance + route.length, 6),
               "time": round(self.time + route.time + self.cfg.capture_time, 6)}
        if self.embodiment.name != "teleport":  # the way it went, for the route plot
            leg["route"] = np.round(route.points, 5).tolist()
        self.legs.append(leg)

    def restore(self, captured: list[int], legs: list | None) -> None:
        """Take up a run's journey again: at its last capture, with its recorded legs (a record
        from before travel was kept ran as teleport: all zeros, or its capture times)."""
        if legs is None or len(legs) < len(captured):
            legs = [{"distance": 0.0, "time": round((n + 1) * self.cfg.capture_time, 6)}
                    for n in range(len(captured))]
        self.legs = [dict(leg) for leg in legs[:len(captured)]]
        self.position = self.positions[captured[-1]] if captured else None
        self.view = self._view(captured[-1]) if captured else None

    # -- cost-aware choice ------------------------------------------------------
    def weigh(self, picks: list[int], scores: np.ndarray | None, allowed: np.ndarray,
              positions: np.ndarray | None = None, views: np.ndarray | None = None) -> list[int]:
        """The batch to capture, in the order of a short tour.

        With a cost weight and the planner's ``scores`` (C,), the picks are
        chosen again, one at a time, by utility less weighted travel cost
        among ``allowed`` (C,) bool candidates (from the round's scores: a
        planner's own batch conditioning, as fisher's, is not kept); else the
        planner's picks stay. ``positions`` (C, 3): the candidates' positions when the planner was
        offered others than the journey's (continuous candidates), ``views`` (C, 3) their viewing directions.
        """
        if positions is None:
            positions, views = self.positions, self.views
        positions = np.asarray(positions, dtype=np.float64)
        if self.weighs_travel and scores is not None:
            weighed = self._weighed(len(picks), scores, allowed.copy(), self.cfg.cost_weight, positions, views)
            picks = weighed if len(weighed) == len(picks) else picks  # too few scored: the planner's stay
        return self._tour(picks, positions)

    def _weighed(self, batch: int, scores: np.ndarray, allowed: np.ndarray, lam: float,
                 positions: np.ndarray, views: np.ndarray | None) -> list[int]:
        utility = np.where(allowed & np.isfinite(scores), scores, np.nan)
        if np.isnan(utility).all():
            return []
        lo, hi = np.nanmin(utility), np.nanmax(utility)
        utility = (utility - lo) / (hi - lo) if hi > lo else np.where(np.isnan(utility), np.nan, 1.0)
        picks, here, facing = [], self.position, self.view
        for _ in range(batch):
            idx = np.nonzero(~np.isnan(utility))[0]
            if not len(idx):
                break
            routes = self.embodiment.paths(here, positions[idx], facing, None if views is None else views[idx])
            value = utility[idx] - lam * np.array([r.length for r in routes]) / self.diameter
            best = int(idx[np.argmax(value)])
            picks.append(best)
            utility[best] = np.nan
            here, facing = positions[best], None if views is None else views[best]
        return picks

    def _tour(self, picks: list[int], positions: np.ndarray) -> list[int]:
        """``picks`` reordered as a nearest-next tour from the camera's position (straight-line distances)."""
        if self.position is None or len(picks) < 2 or self.embodiment.name == "teleport":
            return list(picks)
        left, order, here = list(picks), [], self.position
        while left:
            k = int(np.argmin([np.linalg.norm(positions[i] - here) for i in left]))
            order.append(left.pop(k))
            here = positions[order[-1]]
        return order


def along_the_way(route: Route, spacing: float, speed: float) -> list[Route]:
    """``route`` cut every ``spacing`` scene units: the pieces from its start to each stop
    and, last, on to its end (a stop at the very end is the capture there, not one more).
    Each piece's end is a stop; ``speed`` (scene units per second) times them."""
    points = np.asarray(route.points, dtype=np.float64)
    if not route.found or route.length <= 0:
        return [route]
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    at = np.concatenate([[0.0], np.cumsum(seg)])  # arc length at each point
    stops = np.arange(1, int(np.ceil(route.length / spacing))) * spacing
    stops = stops[stops < route.length - 1e-9 * max(route.length, 1.0)]
    pieces, start_arc, start = [], 0.0, points[0]
    for s in list(stops) + [route.length]:
        k = int(np.clip(np.searchsorted(at, s, side="right") - 1, 0, len(seg) - 1))
        t = (s - at[k]) / seg[k] if seg[k] > 0 else 0.0
        end = points[k] + t * (points[k + 1] - points[k])
        inner = points[(at > start_arc + 1e-12) & (at < s - 1e-12)]
        piece = np.concatenate([[start], inner, [end]])
        pieces.append(Route(piece, s - start_arc, (s - start_arc) / speed))
        start_arc, start = s, end
    return pieces


def diameter_of(bbox_min, bbox_max) -> float:
    """The scene's diameter (scene units): its bounding box's diagonal."""
    d = float(np.linalg.norm(np.asarray(bbox_max, float) - np.asarray(bbox_min, float)))
    return d if d > 0 and math.isfinite(d) else 1.0


def stops_along(route: Route, spacing: float, speed: float, room: int) -> tuple[list[Route], Route]:
    """The pieces of ``route`` (:func:`along_the_way`) that end at the first ``room`` stops, and
    the rest of the route from the last of them to its end."""
    pieces = along_the_way(route, spacing, speed)
    stops = pieces[:-1][:max(room, 0)]
    rest = pieces[len(stops):]
    points = np.concatenate([rest[0].points] + [p.points[1:] for p in rest[1:]])
    length = float(sum(p.length for p in rest))
    return stops, Route(points, length, length / speed)
