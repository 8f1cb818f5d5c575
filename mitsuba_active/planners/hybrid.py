"""Unseen-surface disagreement: ensemble disagreement on surface no captured view has seen from near.

``coverage`` spreads viewing directions; ``rfe`` chases the ensemble's
disagreement. ``hybrid`` scores what a candidate would add to the captured
views: for each of its sparse rays, the point ``p`` where it meets a surface
(the ensemble's mean opacity above ``min_opacity``; at the members' mean
distance) or, where it meets none yet, leaves the box, and the angle at ``p`` between the candidate's centre and the
nearest captured camera that sees ``p`` (``p`` in its frustum, and no farther
than the ensemble's distance along that camera's ray to it, plus
``DEPTH_TOLERANCE``, on a coarse depth map): pi where none sees it. A ray's
worth is that angle's share of pi (raised to ``power``: 2 favours the largest
gaps), times ``1 + disagreement * v / v_mean``, where ``v`` is the members'
colour variance along the ray and ``v_mean`` its mean over all candidates'
rays. A candidate's score is the mean worth of its R rays: new
surface, or surface seen only from far, counts most where the members
disagree about it. Batches are greedy: each pick counts as captured (with
the ensemble's depths) when the next is scored.

With ``lookahead`` a candidate is scored by what it adds to every
candidate's view, not only its own: the worth its cameras' depth maps take
off all candidates' rays (each ray's worth falling to that of the angle
from the candidate, where the candidate sees the ray's point nearer in
angle than any captured camera), summed. The candidates stand in for the
views a capture is judged from, so the pick that leaves the least unseen
over all of them wins (greedy facility location; ``coverage`` instead
fills the single largest gap).

With ``cover`` and a run's budget, the picks are only views of a covering of
the candidates' directions planned for the whole budget
(:mod:`.covering`): the score decides the order in which they are
captured, and the largest gap at the budget stays as narrow as the plan's.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter

from ..cameras import camera_pixels, camera_rays
from ..checks import is_number, is_whole
from ..errors import UserError
from ..field import Ensemble
from .base import Planner, PlanningState, check_batch, greedy_top, register, unseen
from .covering import planned_mask
from .rfe import check_bootstrap

#: Share (of its own distance) by which a point may lie beyond the ensemble's
#: surface along a captured camera's ray and still count as seen by it.
DEPTH_TOLERANCE = 0.05


def project(camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel indices (N,) int64, row-major, of ``points`` (N, 3) in ``camera``'s
    image (through its lens, :func:`~mitsuba_active.cameras.camera_pixels`), and
    (N,) bool: in front of it and inside the image."""
    u, v, inside = camera_pixels(camera, points)
    ui = np.clip(np.where(inside, u, 0), 0, camera.width - 1).astype(np.int64)
    vi = np.clip(np.where(inside, v, 0), 0, camera.height - 1).astype(np.int64)
    return vi * camera.width + ui, inside


def box_exits(origins: np.ndarray, directions: np.ndarray, box_min, box_max) -> np.ndarray:
    """(...,) distance (scene units) along rays ``origins``, ``directions``
    (..., 3) to where they leave the box [``box_min``, ``box_max``]; inf where
    a ray misses it or leaves it behind its origin."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / directions
        t0, t1 = (np.asarray(box_min) - origins) * inv, (np.asarray(box_max) - origins) * inv
    near = np.nanmax(np.minimum(t0, t1), axis=-1)
    far = np.nanmin(np.maximum(t0, t1), axis=-1)
    return np.where((far >= np.maximum(near, 0.0)) & (far > 0), far, np.inf)


def farthest_around(depth: np.ndarray) -> np.ndarray:
    """(H, W) largest depth of each pixel's 3 x 3 neighbourhood in ``depth`` (H, W):
    a point near a coarse depth map's silhouette is not hidden by the pixel's
    nearer surface."""
    return maximum_filter(depth, size=3, mode="nearest")


def seen_cosines(points: np.ndarray, centres: np.ndarray, camera, depth: np.ndarray) -> np.ndarray:
    """(N,) cosine of the angle at each of ``points`` (N, 3) between the
    directions to ``centres`` (N, 3 or 3,) and to ``camera``; -1 where the
    camera does not see the point. ``depth``: (H*W,) distances along its
    pixels' rays to the first surface (inf where there is none), at the
    camera's resolution."""
    p = np.asarray(points, np.float64)
    to_c = np.broadcast_to(centres, p.shape) - p
    to_c = to_c / np.maximum(np.linalg.norm(to_c, axis=1, keepdims=True), 1e-12)
    pix, inside = project(camera, p)
    to_j = camera.position[None, :] - p
    dist = np.linalg.norm(to_j, axis=1)
    seen = inside & (dist <= depth[pix] * (1.0 + DEPTH_TOLERANCE))
    cos = np.einsum("ij,ij->i", to_c, to_j) / np.maximum(dist, 1e-12)
    return np.where(seen, cos, -1.0)


def unseen_angles(points: np.ndarray, centre: np.ndarray, cameras: list, depths: list) -> np.ndarray:
    """(N,) angle (radians, in [0, pi]) at each of ``points`` (N, 3) between the
    direction to ``centre`` (3,) and the nearest direction to a camera of
    ``cameras`` that sees the point (see :func:`seen_cosines`, ``depths`` one
    per camera); pi where none does."""
    best = np.full(len(points), -1.0)
    for cam, depth in zip(cameras, depths):
        best = np.maximum(best, seen_cosines(points, centre, cam, depth))
    return np.arccos(np.clip(best, -1.0, 1.0))


@register
class HybridPlanner(Planner):
    """Score candidates by ensemble disagreement on surface the captured views have not seen from near.

    Options:
        disagreement: weight of the members' colour variance (relative to its
            mean) on a ray's unseen angle; 0 scores unseen surface alone.
        min_opacity: a ray meets a surface where the members' mean opacity
            exceeds this.
        depth_resolution: pixels across the captured cameras' depth maps
            (rendered by the ensemble) that decide which points they see.
        bootstrap: the members' resampling of the captured rays, as rfe's.
        power: exponent of a ray's unseen angle (as a share of pi).
        lookahead: 1 scores what a candidate adds to every candidate's rays;
            0 only to its own.
        cover: 1 (the default) picks only among the views of a covering of
            the candidates' directions planned for the run's budget
            (:func:`~mitsuba_active.planners.covering.planned_cover`): the
            score orders the planned views; 0 (or a budget the planner is
            not told) picks among all.
    """

    name = "hybrid"
    needs_ensemble = True
    min_members = 2

    def __init__(self, disagreement: float = 1.0, min_opacity: float = 0.5, depth_resolution: int = 16,
                 bootstrap: str = "none", power: float = 1.0, lookahead: int = 0, cover: int = 1):
        if not (is_number(disagreement, finite=True) and disagreement >= 0
                and is_number(min_opacity, finite=True) and 0 <= min_opacity < 1
                and is_whole(depth_resolution) and 1 <= depth_resolution <= 256
                and is_number(power, finite=True) and 0 < power <= 8
                and is_whole(lookahead) and lookahead in (0, 1) and is_whole(cover) and cover in (0, 1)):
            raise UserError(f"hybrid needs disagreement >= 0, min_opacity in [0, 1), a whole number "
                            f"depth_resolution in [1, 256], power in (0, 8], lookahead 0 or 1 and cover 0 or 1, "
                            f"got {disagreement!r}, {min_opacity!r}, {depth_resolution!r}, {power!r}, {lookahead!r}, "
                            f"{cover!r}")
        self.disagreement, self.min_opacity = float(disagreement), float(min_opacity)
        self.depth_resolution, self.bootstrap = int(depth_resolution), check_bootstrap(bootstrap)
        self.power, self.lookahead, self.cover = float(power), int(lookahead), int(cover)

    def options(self):
        return {"disagreement": self.disagreement, "min_opacity": self.min_opacity,
                "depth_resolution": self.depth_resolution, "bootstrap": self.bootstrap, "power": self.power,
                "lookahead": self.lookahead, "cover": self.cover}

    def make_field(self, bbox_min, bbox_max, n_members, config, seed):
        return Ensemble(bbox_min, bbox_max, n_members=n_members, config=config, seed=seed, bootstrap=self.bootstrap)

    def _depth_views(self, ensemble, cameras) -> list:
        """Each of ``cameras`` at the depth maps' resolution and its (H*W,)
        distances to the first surface (inf: none), rendered in one call."""
        smalls = [cam.with_resolution(self.depth_resolution, max(1, round(self.depth_resolution * cam.height
                                                                           / cam.width))) for cam in cameras]
        if not smalls:
            return []
        rays = [camera_rays(small) for small in smalls]
        pred = ensemble.predict(np.concatenate([o for o, _ in rays]), np.concatenate([d for _, d in rays]))
        depth = np.where(pred["opacity"] > self.min_opacity, pred["distance_mean"], np.inf)
        out, start = [], 0
        for small in smalls:
            n = small.width * small.height
            out.append((small, farthest_around(depth[start:start + n].reshape(small.height, small.width)).ravel()))
            start += n
        return out

    def select(self, state: PlanningState, batch: int):
        allowed = unseen(state)
        check_batch(allowed, batch)
        self.check_state(state)
        origins, directions = state.candidate_rays
        c, r = origins.shape[:2]
        pred = state.ensemble.predict(origins.reshape(-1, 3), directions.reshape(-1, 3))
        hit = (pred["opacity"] > self.min_opacity).reshape(c, r)
        # A ray that meets no surface yet looks as far as the box: unseen there, it may hold surface.
        exits = box_exits(origins, directions, state.ensemble.bbox_min, state.ensemble.bbox_max)
        surface = hit | np.isfinite(exits)
        distance = np.where(hit, pred["distance_mean"].reshape(c, r), np.nan_to_num(exits, posinf=0.0))
        points = (origins + directions * distance[..., None]).astype(np.float64)
        var = pred["rgb_var"].reshape(c, r, 3).sum(axis=2)
        mean_var = float(var[surface].mean()) if surface.any() else 0.0
        gain = 1.0 + self.disagreement * var / mean_var if mean_var > 0 else np.ones_like(var)
        # Each surface point's best cosine over the captured cameras, raised as picks join them.
        owner, ray = np.nonzero(surface)
        pts, centres = points[owner, ray], np.stack([state.candidates[i].position for i in range(c)])[owner]
        worth_gain = gain[owner, ray]
        best = np.full(len(owner), -1.0)
        for view in self._depth_views(state.ensemble, [state.candidates[j] for j in dict.fromkeys(state.captured)]):
            best = np.maximum(best, seen_cosines(pts, centres, *view))
        if self.lookahead:
            return self._lookahead(state, batch, allowed, pts, centres, worth_gain, best, r)
        picks, first = [], None
        for _ in range(batch):
            scores = np.bincount(owner, weights=self._worth(best, worth_gain), minlength=c) / r
            first = scores if first is None else first
            pick = greedy_top(scores, self._within_cover(state, picks, allowed), 1)[0]
            picks.append(pick)
            allowed[pick] = False
            if len(picks) < batch:
                view, = self._depth_views(state.ensemble, [state.candidates[pick]])
                best = np.maximum(best, seen_cosines(pts, centres, *view))
        return picks, first

    def _within_cover(self, state: PlanningState, picks: list, allowed: np.ndarray) -> np.ndarray:
        """``allowed`` (C,) bool, narrowed with ``cover`` to the views planned for the budget beside ``picks``."""
        planned = planned_mask(state, picks) if self.cover else None
        return allowed if planned is None else allowed & planned

    def _worth(self, cos, gain):
        """(..., P) worth of rays whose points' nearest seeing camera lies at
        cosine ``cos`` (..., P), with disagreement factors ``gain`` (P,)."""
        return (np.arccos(np.clip(cos, -1.0, 1.0)) / np.pi) ** self.power * gain

    def _lookahead(self, state, batch, allowed, pts, centres, gain, best, r):
        """Greedy picks by the worth each candidate takes off all candidates'
        R rays (see the module's docstring); returns the picks and the first
        pick's scores, each candidate's mean loss of worth a ray."""
        c = len(state.candidates)
        ids = np.flatnonzero(allowed)
        # (A, P) cosines at every ray's point from each allowed candidate that sees it.
        seen = np.stack([seen_cosines(pts, centres, *view)
                         for view in self._depth_views(state.ensemble, [state.candidates[i] for i in ids])])
        picks, first = [], None
        for _ in range(batch):
            scores = np.zeros(c)  # captured or out of reach: nothing to add
            now = self._worth(best, gain)
            scores[ids] = (now[None, :] - self._worth(np.maximum(best[None, :], seen), gain)).sum(axis=1) / (c * r)
            first = scores if first is None else first
            pick = greedy_top(scores, self._within_cover(state, picks, allowed), 1)[0]
            picks.append(pick)
            allowed[pick] = False
            best = np.maximum(best, seen[np.searchsorted(ids, pick)])
        return picks, first
