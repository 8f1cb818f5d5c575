"""Continuous candidates: fresh poses on and inside the rig's surface each round, and perturbations around a pose.

The rig's surface is fitted to its candidate pool: the point every camera
looks at (least squares over their optical axes) and an axis-aligned
ellipsoid around it through their positions (a sphere for the sphere,
hemisphere and rings rigs, the room's ellipsoid for the interior rig),
over the band of heights along the up axis that the pool spans. A pose on
it is a point of that band, ``(t, phi)``: ``t`` its unit direction's
component along up and ``phi`` its azimuth; its camera looks at the centre
with the pool's intrinsics. Samples are uniform over the band's area. A
ground robot keeps its camera's height: its poses are on the ellipse where
the surface meets its plane. Poses out of the embodiment's reach, inside
the geometry, or at a held-out view's place are dropped, and so are those
nearer a captured view than the pool's cameras are to each other (its
median nearest-neighbour angle), as near as the pool's own candidates come.
A camera that can fly may also come nearer the centre than the rig does,
where the object fills more of its view: with ``nearest`` below 1, each
pose's distance from the centre is drawn between that share of the
surface's and the surface's own (uniformly), and perturbations vary it too.

A planner's score of a pose is an estimate from a few hundred rays, and a
noisy one: the best of many such scores is largely the luckiest draw. So
a round's first look (the fresh sample, scored as pool candidates are)
only shortlists; its best few and perturbations around them are scored
again on two fresh draws of pixels, the same pixels for all of them, and a
perturbation replaces its pose only where its lead passes the noise that
the two draws' disagreement shows. A journey that weighs travel takes the
first look's picks, weighed against travel over the whole sample.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import norm

from .cameras import Camera, look_at
from .planners.base import PlanningState, greedy_top, unseen
from .training import sparse_candidate_rays

#: Draws per wanted pose before the unreachable ones are dropped.
OVERSAMPLE = 4
#: Perturbations of a pose, and their spread as a share of the pool's angular spacing.
PERTURBATIONS = 6
PERTURB_SHARE = 0.5
#: The spread of a perturbation's distance from the centre (a share of the rig's), per radian of its angular spread.
RADIAL_SHARE = 0.5
#: The chance that noise alone lets some near pose replace a pose of the second look (the leads'
#: threshold is set for it over all the near poses compared).
FALSE_LEAD = 0.1
#: The first look's best poses (at least the batch) that the second look scores again, with the poses near them.
SECOND_LOOK = 4


def looked_at(cameras: list[Camera]) -> np.ndarray:
    """(3,) the point nearest all the cameras' optical axes (least squares)."""
    p = np.stack([c.position for c in cameras])
    f = np.stack([c.forward for c in cameras])
    f = f / np.linalg.norm(f, axis=1, keepdims=True)
    proj = np.eye(3)[None] - f[:, :, None] * f[:, None, :]  # (N, 3, 3): across each axis
    a, b = proj.sum(axis=0), np.einsum("nij,nj->i", proj, p)
    return np.linalg.lstsq(a, b, rcond=None)[0]


class RigSurface:
    """The surface a rig's cameras lie on, to draw poses from.

    Args:
        pool: the rig's candidate cameras (at least 4, around one centre).
        up: (3,) the scene's up axis.
    """

    def __init__(self, pool: list[Camera], up):
        self.ref = pool[0]
        self.up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
        self.centre = looked_at(pool)
        d = np.stack([c.position for c in pool]) - self.centre
        # Axis-aligned ellipsoid through the positions: sum_k d_k^2 / a_k^2 = 1, linear in 1 / a_k^2.
        w = np.linalg.lstsq(d ** 2, np.ones(len(d)), rcond=None)[0]
        r = float(np.linalg.norm(d, axis=1).mean())
        self.axes = 1.0 / np.sqrt(w) if (w > 0).all() and np.isfinite(w).all() else np.full(3, r)
        units = self._unit(d / self.axes)
        t = units @ self.up
        self.band = (float(t.min()), float(t.max()))
        helper = np.eye(3)[int(np.argmin(np.abs(self.up)))]
        self.e1 = np.cross(self.up, helper)
        self.e1 /= np.linalg.norm(self.e1)
        self.e2 = np.cross(self.up, self.e1)
        #: Radians between neighbouring pool cameras on the unit sphere (the band's area over the pool).
        self.spacing = math.sqrt(2 * math.pi * max(self.band[1] - self.band[0], 1e-3) / len(pool))
        #: Radians: the median angle from a pool camera to its nearest neighbour (on the unit surface).
        # A k-d tree, not the C x C angles: a large pool's would not fit in memory.
        chord = cKDTree(units).query(units, k=2)[0][:, 1]  # inf for a pool of one: the angle is pi
        self.gap = float(np.median(2.0 * np.arcsin(np.minimum(chord, 2.0) / 2.0)))

    @staticmethod
    def _unit(v):
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)

    def angles(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(N, M) radians between the surface directions of points ``a`` (N, 3) and ``b`` (M, 3)."""
        ua, ub = (self._unit((np.asarray(x, dtype=np.float64) - self.centre) / self.axes) for x in (a, b))
        return np.arccos(np.clip(ua @ ub.T, -1.0, 1.0))

    def positions(self, t: np.ndarray, phi: np.ndarray, scale: np.ndarray | None = None) -> np.ndarray:
        """(N, 3) scene units: the surface's points at band coordinates ``t``, ``phi`` (N,), each moved
        towards the centre to ``scale`` (N,) of its distance where given."""
        s = np.sqrt(np.clip(1 - t ** 2, 0, 1))
        u = t[:, None] * self.up + s[:, None] * (np.cos(phi)[:, None] * self.e1 + np.sin(phi)[:, None] * self.e2)
        if scale is not None:
            u = u * np.asarray(scale, dtype=np.float64)[:, None]
        return self.centre + self.axes * u

    def scale(self, position: np.ndarray) -> float:
        """The share of the surface's distance from the centre at which ``position`` (3,) lies."""
        return float(np.linalg.norm((np.asarray(position, dtype=np.float64) - self.centre) / self.axes))

    def height_t(self, height: float) -> float | None:
        """The band coordinate ``t`` of the plane at ``height`` along up (None: the plane misses the band)."""
        a_up = float(np.abs(self.axes) @ np.abs(self.up))
        t = (height - float(self.centre @ self.up)) / a_up
        return t if self.band[0] - 1e-9 <= t <= self.band[1] + 1e-9 else None

    def camera(self, position: np.ndarray) -> Camera:
        """The pool's kind of camera at ``position`` (3,), looking at the centre."""
        r = self.ref
        return Camera(look_at(position, self.centre, self.up), r.fov, r.width, r.height, r.near, r.far)


class PoseSampler:
    """Reachable poses on a rig's surface for an embodiment, away from the held-out views.

    Args:
        surface: the :class:`RigSurface`.
        embodiment: its ``reachable`` and (a ground robot's) ``height`` decide where the camera can be.
        heldout: held-out cameras, whose places no pose takes.
        free_space: ``(N, 3) -> (N,) bool``, points not inside the geometry (None: all are).
        nearest: the least share of the surface's distance from the centre a pose comes to, in (0, 1]
            (1: every pose on the surface).
    """

    def __init__(self, surface: RigSurface, embodiment, heldout: list[Camera], free_space=None,
                 nearest: float = 1.0):
        if not 0.0 < nearest <= 1.0:
            raise ValueError(f"nearest must be in (0, 1], got {nearest!r}")
        self.surface, self.embodiment, self.free_space = surface, embodiment, free_space
        self.nearest = float(nearest)
        self.heldout = np.stack([c.position for c in heldout]) if heldout else np.zeros((0, 3))
        # Farther than this from every held-out view's place: never one of its poses.
        self.apart = 1e-3 * float(np.abs(surface.axes).mean())

    def _fixed_t(self):
        height = getattr(self.embodiment, "height", None)
        return None if height is None else self.surface.height_t(height)

    def _keep(self, t, phi, n, avoid=None, scale=None) -> list[Camera]:
        points = self.surface.positions(t, phi, scale)
        height = getattr(self.embodiment, "height", None)
        if height is not None:  # exactly in the base's plane
            points = points - np.outer(points @ self.surface.up - height, self.surface.up)
        ok = self.embodiment.reachable(points)
        if self.free_space is not None:
            ok &= self.free_space(points)
        if len(self.heldout):
            gaps = np.linalg.norm(points[:, None] - self.heldout[None], axis=2).min(axis=1)
            ok &= gaps > self.apart
        if avoid is not None and len(avoid) and ok.any():
            # The pool's gap from the captured views; nearer only where no pose is that far.
            near = self.surface.angles(points, avoid).min(axis=1)
            for floor in self.surface.gap * 0.5 ** np.arange(4):
                if (ok & (near >= floor)).any():
                    ok &= near >= floor
                    break
        return [self.surface.camera(p) for p in points[ok][:n]]

    def sample(self, rng: np.random.Generator, n: int, avoid: np.ndarray | None = None) -> list[Camera]:
        """Up to ``n`` poses drawn uniformly over the band's area (fewer where few are reachable), at
        least the pool's gap from the captured positions ``avoid`` (K, 3) where any are."""
        m = OVERSAMPLE * n
        lo, hi = self.surface.band
        fixed = self._fixed_t()
        if fixed is None and getattr(self.embodiment, "height", None) is not None:
            return []  # the ground robot's plane misses the rig
        t = np.full(m, fixed) if fixed is not None else rng.uniform(lo, hi, m)
        phi = rng.uniform(0, 2 * np.pi, m)
        # Drawn only where it varies: runs on the surface alone keep their draws.
        scale = rng.uniform(self.nearest, 1.0, m) if self.nearest < 1.0 else None
        return self._keep(t, phi, n, avoid, scale)

    def around(self, camera: Camera, rng: np.random.Generator, n: int = PERTURBATIONS,
               avoid: np.ndarray | None = None) -> list[Camera]:
        """Up to ``n`` poses near ``camera``'s (a ground robot's: in its plane), as near the centre as
        :meth:`sample`'s may be and apart from ``avoid`` as they are."""
        s = self.surface
        u = s._unit((camera.position - s.centre) / s.axes)
        t0, phi0 = float(u @ s.up), math.atan2(float(u @ s.e2), float(u @ s.e1))
        sigma = PERTURB_SHARE * s.spacing
        m = OVERSAMPLE * n
        fixed = self._fixed_t()
        t = (np.full(m, fixed) if fixed is not None else
             np.clip(t0 + sigma * math.sqrt(max(1 - t0 ** 2, 0.0)) * rng.standard_normal(m), *s.band))
        phi = phi0 + sigma / max(math.sqrt(max(1 - t0 ** 2, 0.0)), 0.1) * rng.standard_normal(m)
        scale = None
        if self.nearest < 1.0:
            spread = RADIAL_SHARE * sigma
            scale = np.clip(s.scale(camera.position) + spread * rng.standard_normal(m), self.nearest, 1.0)
        return self._keep(t, phi, n, avoid, scale)


def choose_among(planner, journey, state: PlanningState, shown_first: list[Camera], offers: list[Camera],
                 captured: list[int], batch: int, cfg):
    """The planner's ``batch`` picks, weighed against travel (:meth:`~mitsuba_active.travel.Journey.weigh`),
    among the cameras ``shown_first`` (the distinct views captured, whose positions in that list
    ``captured`` gives in capture order) and ``offers``; ``(picks, scores)``, both over the cameras shown."""
    cams = list(shown_first) + list(offers)
    shown = PlanningState(cams, list(captured), state.ensemble, None, state.rng)
    if planner.needs_ensemble:
        shown.candidate_rays = sparse_candidate_rays(cams, cfg.rays_per_candidate, cfg.seed + 1)
    picks, scores = planner.checked_select(shown, batch)
    picks = journey.weigh(picks, scores, unseen(shown), positions=np.stack([c.position for c in cams]),
                          views=np.stack([c.forward for c in cams]))
    return picks, scores


def refined_scores(planner, state: PlanningState, taken: list[Camera], captured: list[int],
                   parents: list[Camera], near: list[Camera], owner: list[int], rng: np.random.Generator, cfg):
    """(P + N,) scores of the ``parents`` (P) and the poses ``near`` them (N; ``owner`` (N,): each one's
    parent): the mean of two fresh draws of pixels common to all of them. One pose per parent
    keeps its score, the others are NaN: its best near pose whose lead over it passes the threshold
    that noise alone (its size read from how the two draws disagree on the leads) would pass in
    :data:`FALSE_LEAD` of rounds over the N leads compared; else the parent itself."""
    cams = list(taken) + list(parents) + list(near)
    draws = []
    for _ in range(2):
        shown = PlanningState(cams, list(captured), state.ensemble, None, state.rng)
        if planner.needs_ensemble:
            shown.candidate_rays = sparse_candidate_rays(cams, cfg.rays_per_candidate, rng, same_pixels=True)
        draws.append(np.asarray(planner.checked_select(shown, 1)[1], dtype=np.float64)[len(taken):])
    a, b = draws
    p, up = len(parents), np.asarray(owner, dtype=np.int64)
    mean = (a + b) / 2
    lead_a, lead_b = a[p:] - a[up], b[p:] - b[up]  # (N,) each draw's lead of a near pose over its parent
    # A draw's lead has variance mean((lead_a - lead_b)^2) / 2; the mean of two, half that.
    noise = math.sqrt(float(np.mean((lead_a - lead_b) ** 2)) / 4) if len(lead_a) else 0.0
    sigmas = float(norm.isf(FALSE_LEAD / max(len(lead_a), 1)))
    better = np.flatnonzero(np.isfinite(lead_a + lead_b) & ((lead_a + lead_b) / 2 > sigmas * noise))
    keep = np.arange(p)
    for k in range(p):
        mine = better[up[better] == k]
        if len(mine):
            keep[k] = p + mine[np.argmax(mean[p + mine])]
    out = np.full(len(mean), np.nan)
    out[keep] = mean[keep]
    return out


def choose_fresh(planner, journey, sampler: PoseSampler, state: PlanningState, owners: list[int],
                 taken: list[Camera], batch: int, rng: np.random.Generator, cfg):
    """One round of continuous candidates: the planner scores ``cfg.candidates`` fresh poses with the
    views captured (``taken``: the cameras of the distinct run indices ``owners``), then, where it
    scores, its picks and next best (:data:`SECOND_LOOK` in all) again, and perturbations around them,
    which replace a pose only where they beat it (:func:`refined_scores`); the picks are the best
    of that second look, or where ``journey`` weighs travel, the first look's weighed picks. Fresh and
    perturbed poses keep the pool's gap from the captured views.

    Returns ``(chosen, scores)``: each pick a run index of ``owners`` (a view again) or a new
    :class:`~mitsuba_active.cameras.Camera`; ``chosen`` is None when no pose is reachable."""
    avoid = np.stack([c.position for c in taken]) if taken else None
    offers = sampler.sample(rng, cfg.candidates, avoid)
    if not offers:
        return None, None
    where = {i: k for k, i in enumerate(owners)}
    captured = [where[i] for i in state.captured]
    picks, scores = choose_among(planner, journey, state, taken, offers, captured, batch, cfg)
    shown = list(taken) + offers
    if scores is None or journey.weighs_travel:
        # Weighed against travel over the whole sample, as a pool's are: over a second look's few near-best
        # poses their utilities would span [0, 1] alone and outweigh the travel cost.
        return [owners[i] if i < len(taken) else shown[i] for i in picks], scores
    # A second look at the first look's picks and next best, and around them, scored on fresh pixels:
    # a pose's first score chose it, so it is biased upwards (more so the more poses were scored).
    fresh = np.r_[np.zeros(len(taken), bool), np.ones(len(offers), bool)] & ~np.isnan(scores)
    best = greedy_top(scores, fresh, min(max(batch, SECOND_LOOK), int(fresh.sum())))
    parents = [shown[i] for i in dict.fromkeys([i for i in picks if i >= len(taken)] + best)]
    parents = parents[:max(batch, SECOND_LOOK)]
    near, owner = [], []
    for k, cam in enumerate(parents):
        around = sampler.around(cam, rng, avoid=avoid)
        near += around
        owner += [k] * len(around)
    shown = list(taken) + parents + near
    scores = np.r_[np.full(len(taken), np.nan),
                   refined_scores(planner, state, taken, captured, parents, near, owner, rng, cfg)]
    allowed = np.r_[np.zeros(len(taken), bool), np.ones(len(shown) - len(taken), bool)]
    picks = greedy_top(scores, allowed, min(batch, len(parents)))
    picks = journey.weigh(picks, scores, allowed & ~np.isnan(scores), positions=np.stack([c.position for c in shown]),
                          views=np.stack([c.forward for c in shown]))
    return [owners[i] if i < len(taken) else shown[i] for i in picks], scores
