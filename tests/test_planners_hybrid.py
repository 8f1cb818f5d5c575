"""The ensemble's bootstrap, rfe's options and the hybrid planner (unseen-surface disagreement)."""

import numpy as np
import pytest

from mitsuba_active.cameras import camera_rays
from mitsuba_active.errors import UserError
from mitsuba_active.planners import PlanningState, make_planner
from mitsuba_active.planners.hybrid import project, unseen_angles
from mitsuba_active.rigs import _cameras_around, fibonacci_sphere, interior
from mitsuba_active.run import sparse_candidate_rays

CANDS = fibonacci_sphere(12, [0, 0, 0], 3.0, 40.0, 8, 8)
DIRS = np.stack([c.forward for c in CANDS])


class Sphere:
    """A stand-in ensemble that sees a unit sphere; its members' colours
    differ by ``var(points)`` at the surface points (N, 3)."""

    n_members = 2
    bbox_min, bbox_max = np.full(3, -1.5), np.full(3, 1.5)

    def __init__(self, var):
        self.var = var

    def predict(self, o, d):
        o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
        b, c = (o * d).sum(1), (o * o).sum(1) - 1.0
        hit = b * b - c > 0
        t = np.where(hit, -b - np.sqrt(np.maximum(b * b - c, 0.0)), 0.0)
        var = np.where(hit, self.var(o + d * t[:, None]), 0.0)
        return dict(opacity=hit.astype(np.float32), distance_mean=t.astype(np.float32),
                    rgb_var=np.repeat(var[:, None], 3, axis=1).astype(np.float32))


def test_a_point_projects_onto_the_pixel_whose_ray_meets_it():
    cam = CANDS[3]
    o, d = camera_rays(cam)
    pix, inside = project(cam, o + 2.5 * d)
    assert inside.all() and np.array_equal(pix, np.arange(cam.width * cam.height))
    _, inside = project(cam, o - 2.5 * d)  # behind the camera
    assert not inside.any()


def test_a_point_hidden_behind_a_nearer_surface_counts_as_unseen():
    cam = CANDS[0]
    point = cam.position + 2.0 * cam.forward
    free = np.full(cam.width * cam.height, np.inf)
    centre = cam.position + np.array([0.0, 0.0, 0.0])
    assert unseen_angles(point[None], centre, [cam], [free])[0] == pytest.approx(0.0, abs=1e-6)
    wall = np.full(cam.width * cam.height, 1.0)  # a surface 1 unit in front of the camera hides it
    assert unseen_angles(point[None], centre, [cam], [wall])[0] == pytest.approx(np.pi)
    assert unseen_angles(point[None], centre, [], [])[0] == pytest.approx(np.pi)


def test_hybrid_prefers_an_uncovered_uncertain_view_to_a_covered_one():
    rays = sparse_candidate_rays(CANDS, 64, 0)
    near, far = int(np.argsort(-(DIRS @ DIRS[0]))[1]), int(np.argmin(DIRS @ DIRS[0]))
    # The members disagree everywhere, a little more on the side no view has seen.
    unsure = Sphere(lambda p: np.where(p @ DIRS[0] > 0, 0.2, 0.1))
    picks, scores = make_planner("hybrid").select(PlanningState(CANDS, [0], unsure, rays), 1)
    assert scores[far] > scores[near] and DIRS[picks[0]] @ DIRS[0] < 0
    assert scores[0] < 0.05 * scores.max()  # the captured view adds nothing
    # Among views equally far from the captured one, the more uncertain wins.
    side = np.flatnonzero(np.abs(DIRS @ DIRS[0]) < 0.35)
    a, b = side[0], side[-1]
    lean = Sphere(lambda p: np.where(p @ -DIRS[a] > 0.5, 1.0, 0.01))
    _, scores = make_planner("hybrid").select(PlanningState(CANDS, [0], lean, rays), 1)
    _, plain = make_planner("hybrid", disagreement=0).select(PlanningState(CANDS, [0], lean, rays), 1)
    assert scores[a] - scores[b] > plain[a] - plain[b]


def test_hybrid_batches_count_their_own_picks_as_captured():
    rays = sparse_candidate_rays(CANDS, 64, 0)
    state = PlanningState(CANDS, [0], Sphere(lambda p: np.full(len(p), 0.01)), rays)
    picks, scores = make_planner("hybrid").checked_select(state, 3)
    assert len(set(picks)) == 3 and 0 not in picks
    # The second pick is not next to the first (its surface is seen from near by then).
    assert DIRS[picks[1]] @ DIRS[picks[0]] < max(DIRS[j] @ DIRS[picks[0]] for j in range(12) if j not in (0, picks[0]))


def test_hybrid_lookahead_prefers_a_view_that_serves_many_candidates_to_a_lone_one():
    """One view captured on +x; seven candidates crowd about +z, one stands
    alone on -x. A view's own unseen surface favours the lone one; what it
    adds to every candidate's view favours the crowd."""
    crowd = [(np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a))
             for a, b in [(0.0, 0.0)] + [(0.25, k * np.pi / 3) for k in range(6)]]
    dirs = np.array([(1.0, 0.0, 0.0)] + crowd + [(-1.0, 0.0, 0.0)])
    cams = _cameras_around(np.zeros(3), 3.0, dirs, (0, 1, 0), 40.0, 8, 8, 1e-3, 1e4)
    state = PlanningState(cams, [0], Sphere(lambda p: np.full(len(p), 0.01)), sparse_candidate_rays(cams, 64, 0))
    lone = len(cams) - 1
    assert make_planner("hybrid").select(state, 1)[0] == [lone]
    picks, scores = make_planner("hybrid", lookahead=1).checked_select(state, 2)
    assert 1 <= picks[0] <= 7 and scores[0] == 0.0 and scores[picks[0]] > 1.5 * scores[lone]
    # The crowd's surface is seen from near by then: the lone view goes next.
    assert picks[1] == lone


class EmptyRoom:
    """A stand-in ensemble that has found no surface yet in a room (the box)."""

    n_members = 2
    bbox_min, bbox_max = np.zeros(3), np.full(3, 4.0)

    def predict(self, o, d):
        n = len(o)
        return dict(opacity=np.zeros(n, np.float32), distance_mean=np.zeros(n, np.float32),
                    rgb_var=np.zeros((n, 3), np.float32))


def test_hybrid_looks_where_no_camera_has_looked_when_no_surface_is_known_yet():
    """Inside a room whose walls the ensemble has not found, rays count up to
    the box: a view of walls no camera has seen beats one beside a captured view."""
    room = EmptyRoom()
    cams = interior(24, room.bbox_min, room.bbox_max, width=8, height=8)
    fwd = np.stack([c.forward for c in cams])
    first = int(np.argmax(fwd[:, 0]))
    others = [i for i in range(len(cams)) if i != first]
    beside = max(others, key=lambda i: fwd[i] @ fwd[first] - 0.1 * np.linalg.norm(cams[i].position - cams[first].position))
    away = int(np.argmin(fwd @ fwd[first]))
    rays = sparse_candidate_rays(cams, 32, 0)
    _, scores = make_planner("hybrid").select(PlanningState(cams, [first], room, rays), 1)
    assert scores[away] > 0.9 and scores[away] > scores[beside] + 0.2 and scores[first] < 0.05


def test_hybrid_and_rfe_options_are_checked():
    for bad in (dict(disagreement=-1), dict(min_opacity=1.0), dict(depth_resolution=0), dict(bootstrap="pixels"),
                dict(power=0), dict(lookahead=2), dict(lookahead=0.5), dict(lookahead=True)):
        with pytest.raises(UserError, match="hybrid|bootstrap"):
            make_planner("hybrid", **bad)
    for bad in (dict(min_opacity=-0.1), dict(bootstrap="all")):
        with pytest.raises(UserError):
            make_planner("rfe", **bad)
    assert make_planner("rfe", bootstrap="views").options()["bootstrap"] == "views"


def test_rfe_scores_only_rays_above_min_opacity():
    rays = sparse_candidate_rays(CANDS, 16, 0)
    # Disagreement on the background alone: rfe with min_opacity ignores it.
    class Fog(Sphere):
        def predict(self, o, d):
            out = super().predict(o, d)
            out["rgb_var"] = np.where(out["opacity"][:, None] > 0, 0.0, np.ones((1, 3))).astype(np.float32)
            return out

    fog = Fog(lambda p: np.zeros(len(p)))
    _, all_rays = make_planner("rfe").select(PlanningState(CANDS, [0], fog, rays), 1)
    _, surface = make_planner("rfe", min_opacity=0.5).select(PlanningState(CANDS, [0], fog, rays), 1)
    assert all_rays.max() > 0 and np.all(surface == 0)


def _ensemble(bootstrap, members=3):
    from mitsuba_active.field import Ensemble, FieldConfig

    config = FieldConfig(n_levels=1, log2_table_size=10, batch_rays=64, n_samples=8)
    return Ensemble([-1] * 3, [1] * 3, n_members=members, config=config, seed=0, bootstrap=bootstrap)


def test_bootstrapped_members_weigh_the_rays_each_their_own_way():
    views = np.repeat(np.array([[3.0, 0, 0], [0, 3.0, 0], [0, 0, 3.0]], np.float32), 50, axis=0)
    idx = np.arange(len(views))
    off = _ensemble("none").ray_weights(views, idx)
    assert np.array_equal(off, np.ones((3, len(views))))  # without bootstrap every member sees every ray
    rays = _ensemble("rays").ray_weights(views, idx)
    assert rays.shape == (3, 150) and np.array_equal(rays[0], np.ones(150))  # the first member sees all
    # The others, Poisson(1) counts: some rays left out, some twice, each member its own.
    assert np.array_equal(rays, np.round(rays)) and abs(rays[1:].mean() - 1.0) < 0.2
    assert 0.2 < (rays[1:] == 0).mean() < 0.55 and (rays[1:] >= 2).any()
    assert not np.array_equal(rays[1], rays[2])
    big = np.repeat(views, 200, axis=0)
    per_view = _ensemble("views", 40).ray_weights(big, np.arange(len(big)))
    for v in range(3):  # one weight per view and member
        assert np.all(per_view[:, 10000 * v:10000 * (v + 1)] == per_view[:, 10000 * v:10000 * v + 1])
    assert 0.15 < (per_view[1:] == 0).mean() < 0.6 and not np.array_equal(per_view[1], per_view[2])
    # A ray's weights do not depend on the rays set after it, nor on the ensemble's size.
    assert np.array_equal(_ensemble("rays", 2).ray_weights(views[:10], idx[:10]), rays[:2, :10])


def test_a_bootstrapped_ensemble_trains_and_keeps_its_resampling(tmp_path):
    from mitsuba_active.field import Ensemble

    ens = _ensemble("views", 2)
    rng = np.random.default_rng(0)
    o = np.repeat(rng.normal(size=(4, 3)).astype(np.float32) + [0, 0, 4], 32, axis=0)
    d = np.tile(np.float32([0, 0, -1]), (len(o), 1))
    ens.set_rays(o, d, rng.random((len(o), 3)), None, np.zeros(len(o), bool))
    assert np.isfinite(ens.train(3)).all()
    ens.save(tmp_path / "e.npz")
    back = Ensemble.load(tmp_path / "e.npz")
    assert back.bootstrap == "views" and np.array_equal(back.ray_weights(o, np.arange(len(o))),
                                                        ens.ray_weights(o, np.arange(len(o))))
    with pytest.raises(UserError, match="bootstrap must be one of none, rays, views"):
        _ensemble("pixels")
