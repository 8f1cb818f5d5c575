"""Moving cameras: routes against analytic lengths, collisions, budgets and the cost-aware choice."""

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from mitsuba_active.cli import main
from mitsuba_active.embodiments import RING, Drone, Ground, Teleport, polyline_length
from mitsuba_active.errors import UserError
from mitsuba_active.run import Run, RunConfig, read_record
from mitsuba_active.travel import Journey
from tests.conftest import tiny_source

MARGIN = 0.1


@pytest.fixture(scope="module")
def ball():
    """A drone around a sphere of radius 1 at the origin."""
    from mitsuba_active.variant import set_variant

    set_variant()
    import mitsuba as mi

    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere", "radius": 1.0}})
    return Drone(speed=2.0, mi_scene=scene, margin=MARGIN)


def around_sphere(rho: float, distance: float) -> float:
    """Shortest route between antipodal points ``distance`` from the centre of a sphere of radius
    ``rho``: two tangents and the great-circle arc between their feet."""
    return 2 * math.sqrt(distance**2 - rho**2) + rho * (math.pi - 2 * math.acos(rho / distance))


def closest_approach(points: np.ndarray) -> float:
    """Least distance from the origin of the polyline through ``points`` (N, 3)."""
    a, b = points[:-1], points[1:]
    d = b - a
    t = np.clip(-(a * d).sum(1) / np.maximum((d * d).sum(1), 1e-30), 0, 1)
    return float(np.linalg.norm(a + t[:, None] * d, axis=1).min())


def test_a_clear_straight_line_is_the_route(ball):
    a, b = np.array([-3.0, 2.0, 0.5]), np.array([3.0, 2.0, -0.5])
    route = ball.path(a, b)
    assert len(route.points) == 2 and route.length == pytest.approx(np.linalg.norm(b - a))
    assert route.time == pytest.approx(route.length / ball.speed)


@pytest.mark.parametrize("distance", [3.0, 1.6])
def test_the_route_around_a_sphere_is_the_shortest_one(ball, distance):
    a, b = np.array([-distance, 0, 0]), np.array([distance, 0, 0])
    route = ball.path(a, b)
    # The ring of rays keeps at least margin x cos(pi / RING) from the surface, at most the margin.
    inner = 1.0 + MARGIN * math.cos(math.pi / RING)
    assert around_sphere(inner, distance) - 1e-6 <= route.length <= 1.02 * around_sphere(1.0 + MARGIN, distance)
    assert route.length == pytest.approx(polyline_length(route.points))
    assert np.allclose(route.points[[0, -1]], [a, b])
    assert closest_approach(route.points) >= inner - 1e-3


def test_routes_never_pass_through_the_object(ball):
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(12, 3))
    starts = 2.5 * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    for start, route in zip(starts, ball.paths(starts[0], starts)):
        assert route.found and closest_approach(route.points) > 1.0 + 0.5 * MARGIN


def test_reachable_positions_keep_the_margin(ball):
    points = np.array([[0, 0, 0], [0, 0.5, 0], [1.05, 0, 0], [1.2, 0, 0], [0, 0, -3]])
    assert ball.reachable(points).tolist() == [False, False, False, True, True]


def test_a_ground_base_drives_around_the_object_at_its_height(ball):
    base = Ground(speed=1.0, mi_scene=ball.mi_scene, margin=MARGIN, up=np.array([0.0, 1.0, 0.0]))
    base.start(np.array([-1.6, 0.0, 0.0]))
    route = base.path(np.array([-1.6, 0.0, 0.0]), np.array([1.6, 0.0, 0.0]))
    inner = 1.0 + MARGIN * math.cos(math.pi / RING)
    # In its plane the sphere is a circle: the same tangents and arc, less closely followed on a sparser graph.
    assert around_sphere(inner, 1.6) - 1e-6 <= route.length <= 1.05 * around_sphere(1.0 + MARGIN, 1.6)
    assert np.allclose(route.points[:, 1], 0.0) and closest_approach(route.points) >= inner - 1e-3
    assert not base.path(np.array([-1.6, 0.0, 0.0]), np.array([1.6, 0.5, 0.0])).found  # another height
    assert base.reachable(np.array([[0.0, 0.0, 2.0], [0.0, 0.5, 2.0], [0.0, 0.0, 1.05]])).tolist() == [True, False,
                                                                                                        False]


def test_teleport_costs_nothing():
    route = Teleport().path(np.zeros(3), np.ones(3))
    assert route.length == 0 and route.time == 0


class Walk(Teleport):
    """Straight lines at speed 2: a drone in empty space."""

    name = "walk"

    def __init__(self):
        super().__init__(speed=2.0)

    def paths(self, start, targets, start_view=None, target_views=None):
        return [self._route([start, t]) for t in targets]


def test_budgets_stop_at_the_capture_that_no_longer_fits():
    positions = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 2]])

    cfg = RunConfig(travel_budget=2.5, time_budget=None, capture_time=0.5)
    j = Journey(Walk(), cfg, positions, diameter=1.0)
    fits = []
    for i in range(4):
        route, why = j.fits(i)
        fits.append(why is None)
        if why is None:
            j.advance(i, route)
    assert fits == [True, True, True, False] and j.distance == pytest.approx(2.0)
    assert j.time == pytest.approx(2.0 / 2 + 3 * 0.5)
    cfg = RunConfig(time_budget=1.9, capture_time=0.5)
    j = Journey(Walk(), cfg, positions, diameter=1.0)
    # 0.5, then 0.5 + 0.5 + 0.5 = 1.5, then 1.5 + 0.5 + 0.5 = 2.5 > 1.9
    assert [j.fits(i)[1] is None and (j.advance(i, j.fits(i)[0]) or True) for i in range(3)] == [True, True, False]


def test_the_cost_weight_trades_utility_for_travel():
    positions = np.array([[0.0, 0, 0], [0.1, 0, 0], [5, 0, 0], [0.2, 0, 0]])
    scores = np.array([-np.inf, 0.9, 1.0, 0.0])
    allowed = np.array([False, True, True, True])
    for lam, expected in ((0.0, [2]), (0.5, [1]), (0.05, [2])):
        j = Journey(Walk(), RunConfig(cost_weight=lam), positions, diameter=5.0)
        j.position = positions[0]
        assert j.weigh([2], scores, allowed) == expected, lam
    j = Journey(Walk(), RunConfig(cost_weight=0.5), positions, diameter=5.0)
    j.position = positions[0]
    assert j.weigh([3, 2], None, allowed) == [3, 2]  # no scores: the planner's picks, nearest first
    assert j.weigh([2, 3], None, allowed) == [3, 2]


def test_a_drone_run_records_its_travel(spot_xml, tmp_path):
    source = tiny_source(spot_xml, n_candidates=8, n_heldout=2, resolution=8)
    tiny = dict(budget=4, initial_views=1, ensemble=2, resolution=8, candidates=8, heldout=2, spp=4,
                eval_views=[2, 4], initial_steps=5, steps_per_view=2, eval_steps=5, rays_per_candidate=8,
                field=dict(batch_rays=128, n_samples=8, render_batch=256))
    out = tmp_path / "r"
    cfg = RunConfig(scene=str(source.scene.path), planner="rfe", embodiment="drone", **tiny)
    rec = Run(source, cfg, out, progress=False, log=lambda m: None).execute()
    legs = rec["travel"]
    assert len(legs) == 4 and legs[0]["distance"] == 0
    assert np.all(np.diff([leg["distance"] for leg in legs]) > 0)  # each capture is somewhere new
    # Each leg at least the straight line between the captures.
    pos = np.array([source.candidates[i].to_world[:3, 3] for i in rec["captured"]])
    assert np.all(np.diff([leg["distance"] for leg in legs]) >= np.linalg.norm(np.diff(pos, axis=0), axis=1) - 1e-4)
    assert [m["travel_distance"] for m in rec["metrics"]] == [legs[1]["distance"], legs[3]["distance"]]
    header = (out / "metrics.csv").read_text().splitlines()[0]
    assert header.endswith("travel_distance,mission_time")
    # Each leg's route runs from the last capture to the next, as long as the distance it adds.
    for n in range(1, 4):
        route = np.array(legs[n]["route"])
        assert np.allclose(route[[0, -1]], pos[n - 1:n + 1], atol=1e-4)
        assert polyline_length(route) == pytest.approx(legs[n]["distance"] - legs[n - 1]["distance"], abs=1e-3)
    assert (out / "psnr_travel.png").is_file() and (out / "route.png").is_file()
    # A travel budget just short of the third capture's route stops the run after two views.
    budget = 0.5 * (legs[1]["distance"] + legs[2]["distance"])
    cfg2 = RunConfig(scene=str(source.scene.path), planner="rfe", embodiment="drone", travel_budget=budget, **tiny)
    rec2 = Run(source, cfg2, tmp_path / "b", progress=False, log=lambda m: None).execute()
    assert rec2["finished"] and len(rec2["captured"]) == 2 and rec2["stopped"]["views"] == 2
    assert rec2["captured"] == rec["captured"][:2] and [m["views"] for m in rec2["metrics"]] == [2]
    read_record(tmp_path / "b" / "run.json")  # a stopped run's record loads
    # A record from before travel was kept resumes as teleport.
    old = json.loads((out / "run.json").read_text())
    for key in ("embodiment", "travel_budget", "time_budget", "speed", "capture_time", "cost_weight"):
        del old["config"][key]
    (out / "run.json").write_text(json.dumps(old))
    teleport = RunConfig(scene=str(source.scene.path), planner="rfe", **tiny)
    assert Run(source, teleport, out, progress=False, log=lambda m: None).execute()["finished"]
    with pytest.raises(UserError, match="embodiment: 'teleport' -> 'drone'"):
        Run(source, cfg, out, progress=False, log=lambda m: None).execute()


def test_bad_travel_settings_are_refused(spot_xml, tmp_path):
    with pytest.raises(UserError, match="no capture fits the time budget"):
        RunConfig(time_budget=1.0, capture_time=2.0).validate()
    runner = CliRunner()
    for args, needle in ([["--embodiment", "submarine"], "submarine"],
                         [["--travel-budget", "-1"], "travel_budget must be a positive number"],
                         [["--time-budget", "1", "--capture-time", "2"], "no capture fits the time budget"],
                         [["--cost-weight", "0.5"], "cost_weight (--cost-weight) applies to a moving embodiment"]):
        res = runner.invoke(main, ["plan", str(spot_xml), "--candidates", "10", "--out", str(tmp_path / "o"), *args])
        assert res.exit_code == 2 and needle in res.output and "Traceback" not in res.output, res.output
        assert not (tmp_path / "o").exists()


def test_a_start_pose_inside_the_geometry_is_refused(sphere_xml, tmp_path):
    from mitsuba_active.env import SceneSource
    from mitsuba_active.rigs import fibonacci_sphere
    from mitsuba_active.scene import load_scene

    scene = load_scene(sphere_xml)
    inside = fibonacci_sphere(3, [0, 0, 0], 0.2, 45.0, 8, 8)  # within the ball of radius 0.5
    src = SceneSource(scene, inside, fibonacci_sphere(2, [0, 0, 0], 1.8, 45.0, 8, 8), spp=4, cache_dir=False)
    cfg = RunConfig(scene=str(sphere_xml), embodiment="drone", budget=2, initial_views=1, candidates=3, heldout=2,
                    resolution=8, spp=4, eval_views=[2], eval_steps=5, initial_steps=5, steps_per_view=2,
                    rays_per_candidate=8, field=dict(batch_rays=128, n_samples=8, render_batch=256))
    with pytest.raises(UserError, match="the start pose, candidate .* lies inside the geometry"):
        Run(src, cfg, tmp_path / "r", progress=False, log=lambda m: None).execute()
    assert not (tmp_path / "r" / "run.json").exists()


class _Walled(Drone):
    """A drone whose only obstacle is a wall at x = 0 that a clear point at its top (|x| <= 0.25) crosses."""

    def _make_waypoints(self):
        return np.array([[-0.5, 1.0, 0.0], [0.5, 1.0, 0.0]])

    def clear(self, a, b):
        side = lambda p: np.where(np.abs(p[:, 0]) > 0.25, np.sign(p[:, 0]), 0.0)  # noqa: E731
        a, b = np.atleast_2d(a), np.atleast_2d(b)
        return side(a) * side(b) >= 0


def test_a_route_may_pass_through_another_target(ball):
    walled = _Walled(speed=1.0, mi_scene=ball.mi_scene, margin=MARGIN)
    start, over, far = np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.2, 0.0]), np.array([1.0, 0.0, 0.0])
    to_over, to_far = walled.paths(start, np.stack([over, far]))
    assert to_over.length == pytest.approx(np.linalg.norm(over - start))
    # The waypoints do not see each other: the way to the far side crosses at the other target.
    assert any(np.allclose(p, over) for p in to_far.points)
    assert np.allclose(to_far.points[[0, -1]], [start, far])
    assert to_far.length == pytest.approx(polyline_length(to_far.points))


def test_a_drone_passes_over_candidates_it_cannot_get_to(spot_xml, tmp_path, monkeypatch):
    from mitsuba_active.embodiments import Route

    source = tiny_source(spot_xml, n_candidates=10, n_heldout=2, resolution=8)
    where = np.array([c.to_world[:3, 3] for c in source.candidates])
    near, walled = [3, 5], 6  # too near the geometry; reachable, but no route gets there
    reachable, paths = Drone.reachable, Drone.paths

    def reachable_but_near(self, points):
        points = np.atleast_2d(points)
        return reachable(self, points) & ~np.isclose(points[:, None], where[near][None]).all(axis=2).any(axis=1)

    def paths_but_walled(self, start, targets, *views):
        routes = paths(self, start, targets, *views)
        return [Route(r.points, np.inf, np.inf) if np.allclose(t, where[walled]) else r
                for t, r in zip(np.atleast_2d(targets), routes)]

    monkeypatch.setattr(Drone, "reachable", reachable_but_near)
    monkeypatch.setattr(Drone, "paths", paths_but_walled)
    tiny = dict(initial_views=1, resolution=8, candidates=10, heldout=2, spp=4, eval_steps=5,
                field=dict(batch_rays=128, n_samples=8, render_batch=256))
    for planner in ("even", "random", "coverage"):
        cfg = RunConfig(scene=str(source.scene.path), planner=planner, embodiment="drone", budget=7, seed=3,
                        eval_views=[7], **tiny)
        rec = Run(source, cfg, tmp_path / planner, progress=False, log=lambda m: None).execute()
        assert len(rec["captured"]) == 7 and not rec.get("stopped"), planner
        assert not set(rec["captured"][1:]) & {*near, walled}, (planner, rec["captured"])
    # More views than the drone can get to: the run stops where none is left, not with an error.
    cfg = RunConfig(scene=str(source.scene.path), planner="even", embodiment="drone", budget=9, eval_views=[9],
                    **tiny)
    rec = Run(source, cfg, tmp_path / "more", progress=False, log=lambda m: None).execute()
    assert rec["finished"] and rec["stopped"]["views"] == 7 and "no candidate left" in rec["stopped"]["reason"]
