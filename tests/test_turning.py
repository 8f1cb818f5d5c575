"""A ground base with a turning radius: Dubins lengths against analytic cases, collisions, bad input."""

import math

import numpy as np
import pytest
from click.testing import CliRunner

from mitsuba_active.cli import main
from mitsuba_active.dubins import dubins_path, dubins_paths
from mitsuba_active.embodiments import RING, Drone, Ground, polyline_length
from mitsuba_active.run import Run, RunConfig
from mitsuba_active.travel import Journey
from tests.conftest import tiny_source

MARGIN = 0.1
UP = np.array([0.0, 1.0, 0.0])


@pytest.fixture(scope="module")
def box():
    """A Mitsuba cube mesh, [-1, 1]^3."""
    from mitsuba_active.variant import set_variant

    set_variant()
    import mitsuba as mi

    return mi.load_dict({"type": "scene", "box": {"type": "cube"}})


def outside_box(points: np.ndarray) -> np.ndarray:
    """(N,) distances of ``points`` (N, 3) from the cube [-1, 1]^3 (0 inside)."""
    return np.linalg.norm(np.maximum(np.abs(points) - 1.0, 0.0), axis=1)


def heading(points: np.ndarray, at: int) -> np.ndarray:
    """Unit direction of the polyline ``points`` (N, 3) leaving its first point (at=0) or reaching its last (-1)."""
    d = points[1] - points[0] if at == 0 else points[-1] - points[-2]
    return d / np.linalg.norm(d)


@pytest.mark.parametrize("r", [0.5, 2.0])
def test_dubins_lengths_match_the_analytic_cases(r):
    assert dubins_path((1.0, 2.0, 0.3), (1.0 + 5 * math.cos(0.3), 2.0 + 5 * math.sin(0.3), 0.3), r).length \
        == pytest.approx(5.0)  # straight ahead
    u_turn = dubins_path((0.0, 0.0, 0.0), (0.0, 2 * r, math.pi), r)  # back along the parallel lane 2r to the left
    assert u_turn.length == pytest.approx(math.pi * r) and u_turn.word[0] == "L"
    assert dubins_path((0.0, 0.0, 0.0), (0.0, -2 * r, math.pi), r).length == pytest.approx(math.pi * r)
    # A point 4r behind, facing the same way: a half turn, 4r back, a half turn.
    assert dubins_path((0.0, 0.0, 0.0), (-4 * r, 0.0, 0.0), r).length == pytest.approx(2 * math.pi * r + 4 * r)
    # A quarter turn to the right: a quarter circle.
    assert dubins_path((0.0, 0.0, math.pi / 2), (r, r, 0.0), r).length == pytest.approx(0.5 * math.pi * r)


def test_every_dubins_word_ends_at_its_goal_and_the_shortest_comes_first():
    rng = np.random.default_rng(0)
    for _ in range(50):
        start, end, r = rng.uniform(-3, 3, 3), rng.uniform(-3, 3, 3), rng.uniform(0.2, 2.0)
        paths = dubins_paths(start, end, r)
        assert paths and [p.length for p in paths] == sorted(p.length for p in paths)
        assert paths[0].length >= np.linalg.norm(end[:2] - start[:2]) - 1e-9
        for p in paths:
            x, y, th = p.end
            assert np.allclose([x, y], end[:2], atol=1e-6) and abs(math.remainder(th - end[2], 2 * math.pi)) < 1e-6
            samples = p.sample()
            assert polyline_length(np.c_[samples[:, :2], np.zeros(len(samples))]) == pytest.approx(p.length, rel=2e-3)
    with pytest.raises(ValueError, match="positive turning radius"):
        dubins_paths((0, 0, 0), (1, 0, 0), 0.0)


def ring_of_poses(n: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` positions (n, 3) on a circle of ``radius`` in the plane y = 0, and their views (n, 3) at the centre."""
    angles = 2 * np.pi * (np.arange(n) + 0.25) / n
    positions = radius * np.stack([np.cos(angles), np.zeros(n), np.sin(angles)], axis=1)
    return positions, -positions / radius


def test_a_zero_turning_radius_drives_the_holonomic_routes(box):
    base = Ground(mi_scene=box, margin=MARGIN, up=UP, turning_radius=0.0)
    positions, views = ring_of_poses(6, 2.2)
    routes = base.paths(positions[0], positions, views[0], views)
    same = Drone.paths(base, positions[0], positions)  # the holonomic planner itself, in the base's plane
    assert len(routes) == len(same) and all(r.found for r in routes)
    for r, s in zip(routes, same):
        assert np.array_equal(r.points, s.points) and r.length == s.length
    assert max(r.length for r in routes) > np.linalg.norm(positions[3] - positions[0]) + 0.1  # around the box


def test_routes_with_a_turning_radius_keep_the_margin_and_face_the_views(box):
    r = 0.3
    base = Ground(speed=2.0, mi_scene=box, margin=MARGIN, up=UP, turning_radius=r)
    holonomic = Ground(speed=2.0, mi_scene=box, margin=MARGIN, up=UP)
    positions, views = ring_of_poses(6, 2.2)
    for start in (0, 2):
        routes = base.paths(positions[start], positions, views[start], views)
        flat = holonomic.paths(positions[start], positions)
        for k, (route, free) in enumerate(zip(routes, flat)):
            assert route.found, k
            p = route.points
            assert np.allclose(p[:, 1], 0.0) and np.allclose(p[[0, -1]], [positions[start], positions[k]])
            # The ring of rays keeps at least margin x cos(pi / RING) from the surface.
            assert outside_box(p).min() >= MARGIN * math.cos(math.pi / RING) - 1e-4, k
            assert route.length == pytest.approx(polyline_length(p), rel=2e-3)
            assert route.time == pytest.approx(route.length / 2.0)
            if k != start:
                assert route.length > free.length  # it must turn away from the box, and back to face it
                assert heading(p, 0) @ views[start] > math.cos(math.radians(6))  # leaves facing its camera's view
                assert heading(p, -1) @ views[k] > math.cos(math.radians(6))  # arrives facing the next one


def test_a_pose_too_close_to_turn_away_is_out_of_reach(box):
    base = Ground(mi_scene=box, margin=MARGIN, up=UP, turning_radius=0.4)
    near = np.array([-1.25, 0.0, 0.0])  # facing the box 0.25 away: a turn of radius 0.4 cannot clear it
    target = np.array([0.0, 0.0, -2.2])
    assert base.reachable(near[None])[0]
    assert not base.path(near, target, np.array([1.0, 0, 0]), np.array([0, 0, 1.0])).found
    assert base.path(near, target, np.array([0, 0, -1.0]), np.array([0, 0, 1.0])).found  # facing along the side
    journey = Journey(base, RunConfig(embodiment="ground", turning_radius=0.4), np.stack([near, target]), 4.0,
                      np.array([[1.0, 0, 0], [0, 0, 1.0]]))
    journey.advance(0, journey.route(0))
    route, why = journey.fits(1)
    assert not route.found and why == "the ground finds no clear route to candidate 1"


def test_a_run_with_a_turning_radius_records_dubins_legs(sphere_xml, tmp_path):
    source = tiny_source(sphere_xml, n_candidates=8, n_heldout=2, resolution=8)
    tiny = dict(budget=3, initial_views=1, ensemble=2, resolution=8, candidates=8, heldout=2, spp=4,
                eval_views=[3], initial_steps=5, steps_per_view=2, eval_steps=5, rays_per_candidate=8,
                field=dict(batch_rays=128, n_samples=8, render_batch=256))
    cfg = RunConfig(scene=str(sphere_xml), planner="rfe", embodiment="ground", turning_radius=0.2,
                    candidates_mode="continuous", **tiny)
    rec = Run(source, cfg, tmp_path / "r", progress=False, log=lambda m: None).execute()
    assert rec["config"]["turning_radius"] == 0.2 and len(rec["captured"]) == 3, rec.get("stopped")
    legs = rec["travel"]
    for n in range(1, 3):
        route = np.array(legs[n]["route"])
        gap = np.linalg.norm(route[-1] - route[0])
        added = legs[n]["distance"] - legs[n - 1]["distance"]
        assert len(route) > 2 and added > gap  # a curve, longer than the straight line
        assert polyline_length(route) == pytest.approx(added, rel=2e-3)


@pytest.mark.parametrize("args, needle", [
    (["--embodiment", "ground", "--turning-radius", "-0.5"], "turning_radius must be a finite number >= 0"),
    (["--embodiment", "drone", "--turning-radius", "0.5"], "turning_radius (--turning-radius) applies to a ground"),
    (["--turning-radius", "0.5"], "applies to a ground base, not the teleport"),
])
def test_a_bad_turning_radius_is_one_line_and_exit_2(spot_xml, tmp_path, args, needle):
    res = CliRunner().invoke(main, ["plan", str(spot_xml), "--candidates", "10", "--out", str(tmp_path / "o"), *args])
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert res.exit_code == 2 and len(lines) == 1 and needle in lines[0], res.output
    assert lines[0].startswith("mitsuba-active: error:") and "Traceback" not in res.output
    assert not (tmp_path / "o").exists()
