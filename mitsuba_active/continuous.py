"""Continuous candidates: fresh poses on the rig's surface each round, and perturbations around a pose.

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
the geometry, or at a held-out view's place are dropped.
"""

from __future__ import annotations

import math

import numpy as np

from .cameras import Camera, look_at
from .planners.base import PlanningState, unseen
from .training import sparse_candidate_rays

#: Draws per wanted pose before the unreachable ones are dropped.
OVERSAMPLE = 4
#: Perturbations of a pose, and their spread as a share of the pool's angular spacing.
PERTURBATIONS = 6
PERTURB_SHARE = 0.5


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

    @staticmethod
    def _unit(v):
        return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300)

    def positions(self, t: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """(N, 3) scene units: the surface's points at band coordinates ``t``, ``phi`` (N,)."""
        s = np.sqrt(np.clip(1 - t ** 2, 0, 1))
        u = t[:, None] * self.up + s[:, None] * (np.cos(phi)[:, None] * self.e1 + np.sin(phi)[:, None] * self.e2)
        return self.centre + self.axes * u

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
    """

    def __init__(self, surface: RigSurface, embodiment, heldout: list[Camera], free_space=None):
        self.surface, self.embodiment, self.free_space = surface, embodiment, free_space
        self.heldout = np.stack([c.position for c in heldout]) if heldout else np.zeros((0, 3))
        # Farther than this from every held-out view's place: never one of its poses.
        self.apart = 1e-3 * float(np.abs(surface.axes).mean())

    def _fixed_t(self):
        height = getattr(self.embodiment, "height", None)
        return None if height is None else self.surface.height_t(height)

    def _keep(self, t, phi, n) -> list[Camera]:
        points = self.surface.positions(t, phi)
        height = getattr(self.embodiment, "height", None)
        if height is not None:  # exactly in the base's plane
            points = points - np.outer(points @ self.surface.up - height, self.surface.up)
        ok = self.embodiment.reachable(points)
        if self.free_space is not None:
            ok &= self.free_space(points)
        if len(self.heldout):
            gaps = np.linalg.norm(points[:, None] - self.heldout[None], axis=2).min(axis=1)
            ok &= gaps > self.apart
        return [self.surface.camera(p) for p in points[ok][:n]]

    def sample(self, rng: np.random.Generator, n: int) -> list[Camera]:
        """Up to ``n`` poses drawn uniformly over the band's area (fewer where few are reachable)."""
        m = OVERSAMPLE * n
        lo, hi = self.surface.band
        fixed = self._fixed_t()
        if fixed is None and getattr(self.embodiment, "height", None) is not None:
            return []  # the ground robot's plane misses the rig
        t = np.full(m, fixed) if fixed is not None else rng.uniform(lo, hi, m)
        return self._keep(t, rng.uniform(0, 2 * np.pi, m), n)

    def around(self, camera: Camera, rng: np.random.Generator, n: int = PERTURBATIONS) -> list[Camera]:
        """Up to ``n`` poses near ``camera``'s on the surface (a ground robot's: in its plane)."""
        s = self.surface
        u = s._unit((camera.position - s.centre) / s.axes)
        t0, phi0 = float(u @ s.up), math.atan2(float(u @ s.e2), float(u @ s.e1))
        sigma = PERTURB_SHARE * s.spacing
        m = OVERSAMPLE * n
        fixed = self._fixed_t()
        t = (np.full(m, fixed) if fixed is not None else
             np.clip(t0 + sigma * math.sqrt(max(1 - t0 ** 2, 0.0)) * rng.standard_normal(m), *s.band))
        phi = phi0 + sigma / max(math.sqrt(max(1 - t0 ** 2, 0.0)), 0.1) * rng.standard_normal(m)
        return self._keep(t, phi, n)


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


def choose_fresh(planner, journey, sampler: PoseSampler, state: PlanningState, owners: list[int],
                 taken: list[Camera], batch: int, rng: np.random.Generator, cfg):
    """One round of continuous candidates: the planner scores ``cfg.candidates`` fresh poses with the
    views captured (``taken``: the cameras of the distinct run indices ``owners``), then, where it
    scores, perturbations around its picks with them.

    Returns ``(chosen, scores)``: each pick a run index of ``owners`` (a view again) or a new
    :class:`~mitsuba_active.cameras.Camera`; ``chosen`` is None when no pose is reachable."""
    offers = sampler.sample(rng, cfg.candidates)
    if not offers:
        return None, None
    where = {i: k for k, i in enumerate(owners)}
    captured = [where[i] for i in state.captured]
    picks, scores = choose_among(planner, journey, state, taken, offers, captured, batch, cfg)
    shown = list(taken) + offers
    if scores is not None:  # a second look, around the picks
        chosen = [shown[i] for i in picks if i >= len(taken)]
        near = [c for cam in chosen for c in sampler.around(cam, rng)]
        if near:
            shown = list(taken) + chosen + near
            picks, scores = choose_among(planner, journey, state, taken, chosen + near, captured, batch, cfg)
    return [owners[i] if i < len(taken) else shown[i] for i in picks], scores
