"""Views along the way and continuous candidates: spacing, reachability, held-out disjointness, resume."""


import numpy as np
import pytest
from click.testing import CliRunner

from mitsuba_active.cameras import Camera
from mitsuba_active.cli import main
from mitsuba_active.continuous import PoseSampler, RigSurface
from mitsuba_active.errors import UserError
from mitsuba_active.embodiments import Route, make_embodiment
from mitsuba_active.record import ALONG_THE_WAY, CONTINUOUS, along_the_way_views, run_cameras
from mitsuba_active.rigs import check_disjoint
from mitsuba_active.run import Run, RunConfig, read_record
from mitsuba_active.travel import along_the_way
from tests.conftest import tiny_source

TINY = dict(initial_views=1, ensemble=2, resolution=8, candidates=8, heldout=2, spp=4, initial_steps=5,
            steps_per_view=2, eval_steps=5, rays_per_candidate=8, field=dict(batch_rays=128, n_samples=8,
                                                                              render_batch=256))


def quiet(source, cfg, out):
    return Run(source, cfg, out, progress=False, log=lambda m: None).execute()


def interrupted(monkeypatch, rounds: int):
    """Make runs stop (KeyboardInterrupt) once they have saved ``rounds`` rounds."""
    save = Run._save_round

    def save_then_stop(self):
        save(self)
        if len(self.record["rounds"]) >= rounds:
            raise KeyboardInterrupt

    monkeypatch.setattr(Run, "_save_round", save_then_stop)


def test_a_route_is_cut_every_spacing():
    route = Route(np.array([[0.0, 0, 0], [1, 0, 0], [1, 2.5, 0]]), 3.5, 7.0)
    pieces = along_the_way(route, 1.0, speed=0.5)
    ends = np.array([p.points[-1] for p in pieces])
    assert np.allclose(ends, [[1, 0, 0], [1, 1, 0], [1, 2, 0], [1, 2.5, 0]])
    assert [p.length for p in pieces] == pytest.approx([1, 1, 1, 0.5])
    assert [p.time for p in pieces] == pytest.approx([2, 2, 2, 1])
    assert np.allclose(pieces[1].points, [[1, 0, 0], [1, 1, 0]])  # the corner is the first piece's end
    assert len(along_the_way(route, 3.5, speed=1.0)) == 1  # a stop at the very end is the capture itself


def test_views_along_the_way_are_spaced_and_counted(sphere_xml, tmp_path, monkeypatch):
    source = tiny_source(sphere_xml, n_candidates=8, n_heldout=2, resolution=8)
    spacing = 1.0
    cfg = RunConfig(scene=str(sphere_xml), planner="rfe", embodiment="drone", along_the_way=spacing, budget=8,
                    eval_views=[8], **TINY)
    rec = quiet(source, cfg, tmp_path / "r")
    along = along_the_way_views(rec)
    assert len(rec["captured"]) == 8 and along  # the budget counts them
    assert 0 not in along and 7 not in along  # the start and the last capture are the planner's
    legs = rec["travel"]
    cams = run_cameras(rec)
    for n in along:  # each a spacing on from the capture before, on the route
        assert legs[n]["distance"] - legs[n - 1]["distance"] == pytest.approx(spacing, abs=1e-4)
        here = Camera.from_dict(cams[rec["captured"][n]])
        assert np.allclose(here.position, legs[n]["route"][-1], atol=1e-4)
        assert abs(here.forward @ (source.scene.center - here.position)) == pytest.approx(
            np.linalg.norm(source.scene.center - here.position), rel=1e-5)  # looking at the centre
    assert all(a["kind"] in (ALONG_THE_WAY,) for a in rec["added"])
    assert (tmp_path / "r" / "camera_views.png").is_file()
    read_record(tmp_path / "r" / "run.json")
    # Interrupted after its first round and resumed, the run captures the same views.
    assert len(rec["rounds"]) >= 2
    interrupted(monkeypatch, rounds=1)
    with pytest.raises(KeyboardInterrupt):
        quiet(tiny_source(sphere_xml, n_candidates=8, n_heldout=2, resolution=8), cfg, tmp_path / "i")
    monkeypatch.undo()
    assert len(read_record(tmp_path / "i" / "run.json")["captured"]) < 8
    again = quiet(tiny_source(sphere_xml, n_candidates=8, n_heldout=2, resolution=8), cfg, tmp_path / "i")
    assert again["captured"] == rec["captured"] and again["added"] == rec["added"]


def test_new_poses_need_a_moving_camera_and_a_scene(spot_xml, tmp_path):
    from tests.test_datasets import write_dataset

    data = write_dataset(tmp_path / "data", n=12)
    runner = CliRunner()
    for scene, args, needle in (
            (spot_xml, ["--along-the-way", "0.2"], "along_the_way (--along-the-way) applies to a moving"),
            (spot_xml, ["--along-the-way", "-1", "--embodiment", "drone"], "along_the_way must be a positive"),
            (spot_xml, ["--candidates-mode", "continuous", "--rig", "xml"], "--rig xml has none"),
            (spot_xml, ["--candidates-mode", "continuous", "--embodiment", "drone", "--nearest", "1.2"],
             "nearest (--nearest) must be a share"),
            (spot_xml, ["--embodiment", "drone", "--nearest", "0.8"], "--nearest applies to continuous candidates"),
            (data, ["--candidates-mode", "continuous", "--heldout", "2", "--budget", "4"], "only a scene can")):
        res = runner.invoke(main, ["plan", str(scene), "--out", str(tmp_path / "o"), *args])
        assert res.exit_code == 2 and needle in res.output and "Traceback" not in res.output, res.output
        assert len(res.output.strip().splitlines()) == 1, res.output
        assert not (tmp_path / "o").exists()
    res = runner.invoke(main, ["plan", str(spot_xml), "--candidates-mode", "sideways"])
    assert res.exit_code == 2 and "sideways" in res.output


def test_continuous_candidates_are_reachable_and_apart_from_the_heldout_views(sphere_xml):
    source = tiny_source(sphere_xml, n_candidates=20, n_heldout=4, resolution=8)
    surface = RigSurface(source.candidates, source.scene.up)
    radius = np.linalg.norm(source.candidates[0].position - source.scene.center)
    assert np.allclose(surface.centre, source.scene.center, atol=1e-6)
    assert np.allclose(surface.axes, radius, rtol=1e-6)
    drone = make_embodiment("drone", source.scene)
    sampler = PoseSampler(surface, drone, source.heldout, source.scene.free_space)
    cams = sampler.sample(np.random.default_rng(0), 30)
    pos = np.stack([c.position for c in cams])
    assert len(cams) == 30 and drone.reachable(pos).all()
    assert np.allclose(np.linalg.norm(pos - surface.centre, axis=1), radius)
    assert np.linalg.norm(pos, axis=1).min() > 0.5  # outside the ball
    check_disjoint(cams, source.heldout)
    assert not np.allclose(pos, np.stack([c.position for c in sampler.sample(np.random.default_rng(1), 30)]))
    near = sampler.around(cams[0], np.random.default_rng(2))
    gaps = np.linalg.norm(np.stack([c.position for c in near]) - cams[0].position, axis=1)
    assert near and gaps.max() < 0.5 * radius * surface.spacing * 4
    # A rig shrunk inside the ball: every pose is inside it, and none is offered.
    inside = RigSurface(source.candidates, source.scene.up)
    inside.axes = np.full(3, 0.3)
    assert PoseSampler(inside, drone, source.heldout, source.scene.free_space).sample(
        np.random.default_rng(0), 10) == []
    # A ground robot's poses stay at its height.
    ground = make_embodiment("ground", source.scene)
    ground.start(source.candidates[3].position)
    flat = PoseSampler(surface, ground, source.heldout).sample(np.random.default_rng(0), 10)
    assert flat and np.allclose([c.position @ source.scene.up for c in flat], ground.height)


def test_a_resumed_continuous_run_captures_the_same_cameras(sphere_xml, tmp_path, monkeypatch):
    source = tiny_source(sphere_xml, n_candidates=8, n_heldout=2, resolution=8)
    cfg = RunConfig(scene=str(sphere_xml), planner="rfe", embodiment="drone", candidates_mode="continuous",
                    budget=4, eval_views=[4], **TINY)
    rec = quiet(source, cfg, tmp_path / "a")
    cams = run_cameras(rec)
    assert len(rec["captured"]) == 4 and all(i >= 8 for i in rec["captured"][1:])
    assert all(a["kind"] == CONTINUOUS for a in rec["added"])
    taken = [Camera.from_dict(cams[i]) for i in rec["captured"]]
    check_disjoint(taken, source.heldout)
    drone = make_embodiment("drone", source.scene)
    assert drone.reachable(np.stack([c.position for c in taken])).all()
    # Interrupted after its second round and resumed: the same cameras.
    interrupted(monkeypatch, rounds=2)
    with pytest.raises(KeyboardInterrupt):
        quiet(tiny_source(sphere_xml, n_candidates=8, n_heldout=2, resolution=8), cfg, tmp_path / "b")
    monkeypatch.undo()
    assert len(read_record(tmp_path / "b" / "run.json")["captured"]) == 3
    again = quiet(tiny_source(sphere_xml, n_candidates=8, n_heldout=2, resolution=8), cfg, tmp_path / "b")
    assert again["captured"] == rec["captured"] and run_cameras(again) == cams


def test_continuous_poses_come_nearer_than_the_rig_down_to_the_share_asked(sphere_xml):
    from mitsuba_active.run import config_differences

    source = tiny_source(sphere_xml, n_candidates=20, n_heldout=4, resolution=8)
    surface = RigSurface(source.candidates, source.scene.up)
    drone = make_embodiment("drone", source.scene)
    sampler = PoseSampler(surface, drone, source.heldout, source.scene.free_space, nearest=0.6)
    cams = sampler.sample(np.random.default_rng(0), 40)
    share = np.array([surface.scale(c.position) for c in cams])
    assert len(cams) == 40 and share.min() >= 0.6 - 1e-9 and share.max() <= 1 + 1e-9
    assert (share < 0.8).sum() >= 10 and (share > 0.8).sum() >= 10  # spread over the whole range
    assert drone.reachable(np.stack([c.position for c in cams])).all()
    for cam in cams:  # each still looks at the centre
        to_centre = surface.centre - cam.position
        assert np.allclose(cam.forward, to_centre / np.linalg.norm(to_centre), atol=1e-6)
    parent = min(cams, key=lambda c: surface.scale(c.position))
    near = [surface.scale(c.position) for c in sampler.around(parent, np.random.default_rng(1))]
    assert near and min(near) >= 0.6 - 1e-9 and max(near) < surface.scale(parent.position) + 0.3
    with pytest.raises(ValueError, match="nearest"):
        PoseSampler(surface, drone, source.heldout, nearest=0.0)
    for bad in (0, 1.5, "near"):
        with pytest.raises(UserError, match="nearest"):
            RunConfig(scene=str(sphere_xml), nearest=bad).validate()
    # A record from before this setting sampled the rig's surface alone.
    cfg = {**TINY, "scene": "s.xml", "planner": "rfe", "candidates_mode": "continuous"}
    assert config_differences(cfg, {**cfg, "nearest": 1.0}) == []
    assert config_differences(cfg, {**cfg, "nearest": 0.75}) == ["nearest: 1.0 -> 0.75"]
    # A pool's run is the same run whatever the setting: an older one goes on (and bench keeps it).
    pool = {**cfg, "candidates_mode": "pool"}
    assert config_differences(pool, {**pool, "nearest": 0.75}) == []


def test_a_rooms_continuous_poses_stay_on_its_rig_and_an_objects_come_nearer(sphere_xml, shared_data, tmp_path):
    room = shared_data / "mitsuba" / "cbox" / "cbox.xml"
    for xml, nearest in ((room, 1.0), (sphere_xml, 0.75)):
        cfg = RunConfig(scene=str(xml), planner="rfe", embodiment="drone", candidates_mode="continuous",
                        budget=4, eval_views=[4], **TINY)
        run = Run(tiny_source(xml, n_candidates=8, n_heldout=2, resolution=8), cfg, tmp_path / xml.stem,
                  progress=False, log=lambda m: None)
        assert run.sampler.nearest == nearest
