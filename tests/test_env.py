import re
from types import SimpleNamespace

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from mitsuba_active.env import ActiveViewEnv
from mitsuba_active.errors import UserError
from tests.conftest import tiny_source, two_sensor_xml


@pytest.fixture(scope="module")
def source(spot_xml):
    return tiny_source(spot_xml, n_candidates=10, n_heldout=3, resolution=12)


def test_passes_gymnasium_env_checker(source):
    check_env(ActiveViewEnv(source, budget=4), skip_render_check=True)


def test_reset_step_mask_and_termination(source):
    env = ActiveViewEnv(source, budget=4, allow_repeats=True)
    assert env.reset(seed=3)[1]["captured"] == []  # an episode starts with nothing captured
    obs, info = env.reset(seed=3, options={"initial_views": 2})
    assert len(info["captured"]) == 2 and len(set(info["captured"])) == 2
    assert info["action_mask"].sum() == 8 and info["views_left"] == 2
    assert info["intrinsics"].shape == (3, 3)
    assert obs["rgb"].shape == (12, 12, 3) and obs["pose"].shape == (4, 4)
    assert np.allclose(obs["pose"], source.candidates[info["captured"][-1]].to_world)
    free = int(np.flatnonzero(info["action_mask"])[0])
    obs, reward, terminated, truncated, info = env.step(free)
    assert not terminated and info["action_mask"][free] == 0
    obs, reward, terminated, truncated, info = env.step(free)  # a repeat spends budget
    assert terminated and not truncated and reward == 0.0
    with pytest.raises(UserError):
        env.step(0)
    # Seeded resets choose the same initial views.
    assert env.reset(seed=3, options={"initial_views": 2})[1]["captured"] == ActiveViewEnv(source, 4).reset(
        seed=3, options={"initial_views": 2})[1]["captured"]


def test_capture_arbitrary_pose(source):
    env = ActiveViewEnv(source, budget=2)
    first, _ = env.reset(seed=0, options={"initial_views": 1})
    pose = source.heldout[0].to_world
    obs = env.capture_pose(pose)
    assert np.allclose(obs["pose"], pose)
    assert np.allclose(obs["rgb"], source.heldout_view(0).rgb)
    assert len(env.captured) == 1
    # An observation's float32 pose is still that camera: the same view, noise and all.
    assert first["pose"].dtype == np.float32
    assert np.array_equal(env.capture_pose(first["pose"])["rgb"], first["rgb"])


def test_zero_initial_views_gives_a_blank_observation(source):
    obs, info = ActiveViewEnv(source, budget=2).reset(seed=0, options={"initial_views": 0})
    assert info["captured"] == [] and obs["rgb"].max() == 0


def test_impossible_budgets(source):
    with pytest.raises(UserError, match="larger than the number of candidate"):
        ActiveViewEnv(source, budget=11)
    with pytest.raises(UserError):
        ActiveViewEnv(source, budget=0)
    with pytest.raises(UserError):
        ActiveViewEnv(source, budget=2).reset(options={"initial_views": 3})
    for budget in ("3", 2.5):
        with pytest.raises(UserError, match="budget must be a positive whole number"):
            ActiveViewEnv(source, budget=budget)


@pytest.mark.parametrize("options, message", [
    ({"initial_view": 2}, "unknown reset option 'initial_view'"),  # a typo would silently give 1 view
    ({"initial_views": 1.5}, r"initial views \(1.5\) must be a whole number"),
    ({"initial_views": None}, r"initial views \(None\) must be a whole number"),
    (["initial_views"], r"reset options must be a dict .* not list"),
])
def test_reset_options_are_checked(source, options, message):
    with pytest.raises(UserError, match=message):
        ActiveViewEnv(source, budget=2).reset(seed=0, options=options)


@pytest.mark.parametrize("pose, message", [
    (lambda p: p.ravel(), r"must be 4x4, got shape \(16,\)"),
    (lambda p: p @ np.diag([2.0, 2.0, 2.0, 1.0]), "not a rigid motion"),
    (lambda p: p @ np.diag([-1.0, 1.0, 1.0, 1.0]), "not a rigid motion"),  # mirrored
    (lambda p: np.full((4, 4), np.nan), "non-finite"),
    (lambda p: p + np.outer([0, 0, 0, 1.0], [0.5, 0, 0, 0]), "bottom row"),
])
def test_capture_pose_refuses_what_is_no_camera_pose(source, pose, message):
    env = ActiveViewEnv(source, budget=2)
    with pytest.raises(UserError, match=message):
        env.capture_pose(pose(source.heldout[0].to_world))
    # 3x4 is a pose with its bottom row left out.
    assert np.allclose(env.capture_pose(source.heldout[0].to_world[:3])["rgb"], source.heldout_view(0).rgb)


def test_capture_pose_snaps_only_to_the_same_camera(tmp_path):
    """In a large scene (positions ~1e6) a pose turned by 30 degrees is a new
    camera, not the candidate it shares a position with."""
    from mitsuba_active.env import SceneSource

    xml = tmp_path / "big.xml"
    xml.write_text('<scene version="3.0.0"><shape type="sphere"><float name="radius" value="1e6"/></shape>'
                   '<emitter type="constant"/></scene>')
    src = SceneSource.from_xml(xml, n_candidates=4, n_heldout=2, resolution=8, spp=1, cache_dir=False)
    env = ActiveViewEnv(src, budget=2)
    env.reset(seed=0)
    pose = src.candidates[0].to_world.copy()
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    pose[:3, :3] = pose[:3, :3] @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    assert np.allclose(env.capture_pose(pose)["pose"], pose, atol=1e-3)
    assert np.allclose(env.capture_pose(src.candidates[0].to_world.astype(np.float32))["pose"],
                       src.candidates[0].to_world, atol=1e-3)


def test_xml_rig_keeps_the_authors_sensors_and_info_describes_each_view(tmp_path):
    src = tiny_source(two_sensor_xml(tmp_path), n_heldout=2, resolution=16, rig="xml")
    first, second = src.candidates
    # The films' 2:1 aspect, the first sensor's vertical 30 degrees and its clip distances.
    assert {(c.width, c.height) for c in src.candidates + src.heldout} == {(16, 8)}
    vertical_fov = 2 * np.degrees(np.arctan(np.tan(np.radians(first.fov) / 2) / 2))
    assert vertical_fov == pytest.approx(30.0, abs=1e-3) and second.fov == pytest.approx(50.0, abs=1e-3)
    assert (first.near, first.far) == pytest.approx((0.5, 100.0))
    env = ActiveViewEnv(src, budget=2)
    obs, info = env.reset(seed=0, options={"initial_views": 0})
    assert obs["rgb"].shape == (8, 16, 3)
    for index, camera in ((1, second), (0, first)):
        info = env.step(index)[4]
        assert np.allclose(info["intrinsics"], camera.intrinsics())
    assert not np.allclose(first.intrinsics(), second.intrinsics())


def test_xml_rig_refuses_sensors_of_different_shapes(tmp_path):
    with pytest.raises(UserError, match="different aspect ratios.*32x32, 48x24"):
        tiny_source(two_sensor_xml(tmp_path, second_film="32x32"), n_heldout=2, resolution=16, rig="xml")


def test_wide_images_keep_the_whole_object_in_view(sphere_xml):
    from mitsuba_active.rigs import scene_rigs
    from mitsuba_active.scene import load_scene

    scene = load_scene(sphere_xml)
    for width, height in ((48, 16), (16, 48), (16, 16)):
        candidates, _ = scene_rigs(scene, "sphere", 6, 2, width, height)
        for cam in candidates:
            half_x = np.radians(cam.fov) / 2
            half_y = np.arctan(np.tan(half_x) * height / width)
            # The ball's radius: 0.5, its vertices' (its bounding box's corners lie farther, and out of view).
            seen = np.arcsin(0.5 / np.linalg.norm(cam.position - scene.center))
            assert seen < min(half_x, half_y)


BALL_XML = '<scene version="3.0.0"><shape type="sphere"/><emitter type="constant"/></scene>'
BALL_DICT = {"type": "scene", "ball": {"type": "sphere"}, "light": {"type": "constant"}}


def test_a_scene_built_in_python_is_a_view_source(tmp_path, monkeypatch):
    import mitsuba as mi

    from mitsuba_active.env import SceneSource

    monkeypatch.setenv("MITSUBA_ACTIVE_CACHE", str(tmp_path / "cache"))
    (tmp_path / "ball.xml").write_text(BALL_XML)
    kw = dict(n_candidates=4, n_heldout=2, resolution=12, spp=4)
    from_file = SceneSource.from_xml(tmp_path / "ball.xml", **kw)
    for scene in (BALL_DICT, mi.load_dict(BALL_DICT)):
        source = SceneSource.from_mitsuba(scene, name="ball", **kw)
        assert source.name == "ball" and source.scene.content_hash is None
        # A name names no file: it is kept whole.
        assert SceneSource.from_mitsuba(scene, name="lab/ball_r0.3", **kw).name == "lab/ball_r0.3"
        assert np.allclose(source.bbox_min, from_file.bbox_min) and np.allclose(source.bbox_max, from_file.bbox_max)
        obs, info = ActiveViewEnv(source, budget=2).reset(seed=0, options={"initial_views": 1})
        view = from_file.candidate_view(info["captured"][0])
        assert np.array_equal(obs["distance"], view.distance)  # the same cameras see the same ball
        assert abs(float(obs["rgb"].mean()) - float(view.rgb.mean())) < 0.05
    # Nothing on disk keys a scene in memory: its views are never cached.
    cached = sorted((tmp_path / "cache").rglob("*.exr"))
    assert len(cached) == 1  # the XML's view (the same index both times), none of the Python scenes'
    # A run records its scene by its file: one built in Python is refused, whatever name it is given.
    from mitsuba_active.run import Run, RunConfig

    cfg = RunConfig(scene="ball", planner="even", budget=2, initial_views=1, candidates=4, heldout=2,
                    resolution=12, spp=4, eval_views=(2,))
    with pytest.raises(UserError, match="scene='ball' \\(the source's: 'ball', built in Python"):
        Run(source, cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("scene, message", [
    (42, "takes a mitsuba.Scene or a scene dict, got int"),
    ({"type": "sphere"}, "got a dict of a .* \\(its 'type' must be 'scene'\\)"),
    ({"type": "scene", "ball": {"type": "no-such-shape"}}, "Mitsuba cannot load the scene dict ball: "),
    ({"type": "scene", "light": {"type": "constant"}}, "scene ball has no shapes"),
])
def test_a_scene_built_in_python_that_is_no_scene_is_refused(scene, message):
    from mitsuba_active.scene import scene_from_mitsuba

    with pytest.raises(UserError, match=message):
        scene_from_mitsuba(scene, name="ball")


def test_a_scene_of_another_variant_is_named_so():
    import mitsuba as mi

    from mitsuba_active.scene import scene_from_mitsuba

    with mi.variant_context("scalar_rgb"):
        scene = mi.load_dict(BALL_DICT)
    with pytest.raises(UserError, match=f"a mitsuba.Scene of another Mitsuba variant; load it with '{mi.variant()}'"):
        scene_from_mitsuba(scene, name="ball")


def test_a_scene_dict_given_for_an_xml_says_how_to_read_it():
    from mitsuba_active.env import SceneSource

    with pytest.raises(UserError, match="got dict; a scene built in Python .* scene_from_mitsuba "
                                        "\\(a view source of it: SceneSource.from_mitsuba\\)"):
        SceneSource.from_xml(BALL_DICT)


@pytest.mark.parametrize("kw, message", [
    (dict(n_candidates=7.5), "number of candidate views must be a whole number >= 1, got 7.5"),
    (dict(n_heldout="2"), "number of held-out views must be a whole number >= 1, got '2'"),
    (dict(resolution=2.5), "image width and height must be whole numbers of pixels"),
    (dict(fov="40"), "field of view must be a number of degrees, got '40'"),
    (dict(spp=4.7), "samples per pixel must be a whole number in [1, 65536], got 4.7"),
])
def test_view_source_settings_of_the_wrong_type_are_named(kw, message):
    from mitsuba_active.env import SceneSource

    with pytest.raises(UserError, match=re.escape(message)):
        SceneSource.from_mitsuba(BALL_DICT, **{**dict(n_candidates=4, n_heldout=2, resolution=8, spp=1), **kw})


@pytest.mark.parametrize("action", [True, "3", 2.5, -1])
def test_actions_that_are_no_candidate_index_are_named_as_given(source, action):
    env = ActiveViewEnv(source, budget=3)
    env.reset(seed=0)
    with pytest.raises(UserError, match=f"invalid action {re.escape(repr(action))}; expected a candidate index"):
        env.step(action)


@pytest.mark.parametrize("captured, message", [
    ([-1, 2], r"cannot restore captured views \[-1\]: expected candidate indices .* in \[0, 10\)"),
    ([2.7], r"cannot restore captured views \[2.7\]"), ([99], r"\[99\]"),
    ([1, 2, 3, 4, 5], "cannot restore 5 captured views: more than the budget \\(4\\)"),
])
def test_restore_checks_what_it_restores(source, captured, message):
    env = ActiveViewEnv(source, budget=4, allow_repeats=True)
    with pytest.raises(UserError, match=message):
        env.restore(captured)
    env.restore([np.int64(3), 3])  # numpy indices and repeats are captures
    assert env.captured == [3, 3] and all(type(i) is int for i in env.captured)


def test_reset_takes_numpy_seeds_and_refuses_others(source):
    env = ActiveViewEnv(source, budget=3)
    assert env.reset(seed=np.int64(5), options={"initial_views": 2})[1]["captured"] == \
        env.reset(seed=5, options={"initial_views": 2})[1]["captured"]
    for seed in (1.5, -1, "3"):
        with pytest.raises(UserError, match="the seed must be a whole number of at least 0"):
            env.reset(seed=seed)


# -- gymnasium registration, rendering, repeats and rewards ---------------------------

#: The rewards' fields at their smallest: seconds for a whole check_env.
TINY_FIELD = {"batch_rays": 256, "n_samples": 16}
TINY_REWARDS = {
    "none": None, "coverage": None,
    "uncertainty": {"members": 2, "initial_steps": 20, "steps_per_view": 10, "rays_per_candidate": 16,
                    "field": TINY_FIELD},
    "psnr": {"steps": 20, "field": TINY_FIELD},
}


def test_gymnasium_make_builds_the_environment(source, spot_xml):
    import gymnasium

    from mitsuba_active import ENV_ID
    from mitsuba_active.env import make_env

    env = gymnasium.make(ENV_ID, scene=spot_xml, budget=2, n_candidates=4, n_heldout=2, resolution=8, spp=1,
                         cache_dir=False, reward="coverage")
    assert isinstance(env.unwrapped, ActiveViewEnv) and env.unwrapped.reward.name == "coverage"
    assert env.unwrapped.action_space.n == 4 and env.observation_space["rgb"].shape == (8, 8, 3)
    # A view source made already, gymnasium's wrappers, and its time limit.
    env = gymnasium.make(ENV_ID, scene=source, budget=3, max_episode_steps=1)
    assert env.unwrapped.source is source
    env.reset(seed=0)
    assert env.step(0)[3] is True  # truncated by the time limit
    with pytest.raises(gymnasium.error.ResetNeeded):  # OrderEnforcing
        gymnasium.make(ENV_ID, scene=source, budget=2).step(0)
    frames = gymnasium.make(ENV_ID, scene=source, budget=2, render_mode="rgb_array_list")
    frames.reset(seed=0)
    frames.step(4)
    assert [f.shape for f in frames.render()] == [(12, 12, 3)] * 2
    with pytest.raises(UserError, match="view source 'spot' is made already: its settings resolution"):
        make_env(source, resolution=16)
    with pytest.raises(UserError, match="scene must be a scene XML, .* got int"):
        make_env(3)


def test_render_gives_the_latest_view(source):
    env = ActiveViewEnv(source, budget=3, render_mode="rgb_array")
    env.reset(seed=0)
    black = env.render()
    assert black.shape == (12, 12, 3) and black.dtype == np.uint8 and black.max() == 0
    for action in (2, 7):
        obs = env.step(action)[0]
        frame = env.render()
        assert frame.dtype == np.uint8 and np.array_equal(frame, np.round(obs["rgb"] * 255).astype(np.uint8))
    env.capture_pose(source.heldout[0].to_world)  # not a step: the frame stays
    assert np.array_equal(env.render(), frame) and frame.max() > 0
    assert ActiveViewEnv(source, budget=2).render() is None
    assert ActiveViewEnv.metadata["render_modes"] == ["rgb_array"]
    with pytest.raises(UserError, match="unknown render_mode 'human'; the environment renders 'rgb_array'"):
        ActiveViewEnv(source, budget=2, render_mode="human")


def test_a_captured_view_is_refused_unless_repeats_are_allowed(source):
    from mitsuba_active.errors import RepeatedView

    env = ActiveViewEnv(source, budget=4)
    info = env.reset(seed=0, options={"initial_views": 2})[1]
    taken = info["captured"][0]
    with pytest.raises(ValueError, match=f"candidate {taken} is captured already") as caught:
        env.step(taken)
    assert isinstance(caught.value, RepeatedView) and env.captured == info["captured"]  # no budget spent
    with pytest.raises(RepeatedView):
        env.restore([1, 1])
    assert env.captured == info["captured"]  # refused before anything changed
    repeats = ActiveViewEnv(source, budget=4, allow_repeats=True)
    repeats.restore([1, 1])
    assert repeats.step(1)[4]["captured"] == [1, 1, 1]


def test_coverage_rewards_newly_seen_surface(source):
    env = ActiveViewEnv(source, budget=4, reward="coverage", allow_repeats=True)
    env.reset(seed=0)
    forward = np.stack([c.forward for c in source.candidates])
    first, back = 0, int(np.argmin(forward @ forward[0]))  # the candidate looking the most the other way
    rewards = [env.step(a)[1] for a in (first, first, back)]
    assert 0 < rewards[0] <= 1 and rewards[1] == 0.0 and rewards[2] > 0.1
    assert sum(rewards) <= 1


def test_uncertainty_and_psnr_rewards_are_gains(source):
    for name in ("uncertainty", "psnr"):
        env = ActiveViewEnv(source, budget=3, reward=name, reward_options=TINY_REWARDS[name])
        env.reset(seed=0)
        rewards = [env.step(a)[1] for a in (0, 5, 9)]
        assert np.isfinite(rewards).all() and np.mean(rewards) > 0, (name, rewards)
        assert rewards[0] > 0, (name, rewards)  # the first view: from an untrained field


@pytest.mark.parametrize("reward, allow_repeats, render_mode", [
    ("none", False, None), ("none", True, "rgb_array"), ("coverage", False, "rgb_array"),
    ("coverage", True, None), ("uncertainty", False, None), ("uncertainty", True, "rgb_array"),
    ("psnr", False, "rgb_array"), ("psnr", True, None),
])
def test_gymnasium_checks_every_option(source, reward, allow_repeats, render_mode):
    import gymnasium

    from mitsuba_active import ENV_ID

    env = gymnasium.make(ENV_ID, scene=source, budget=3, reward=reward, reward_options=TINY_REWARDS[reward],
                         allow_repeats=allow_repeats, render_mode=render_mode)
    # Rewards of trained fields are equal to ~1e-6, not bit for bit: the spec says so.
    assert env.spec.nondeterministic is (reward in ("uncertainty", "psnr"))
    check_env(env.unwrapped)  # with its spec: every render mode and a second environment too


@pytest.mark.parametrize("kw, message", [
    (dict(reward="ssim"), "unknown reward 'ssim'; choose one of 'none', 'coverage', 'uncertainty', 'psnr'"),
    (dict(reward="psnr", reward_options={"step": 5}), "unknown option 'step' of the psnr reward; its settings "
                                                     "are steps, field_preset, field, seed"),
    (dict(reward="none", reward_options={"seed": 1}), "unknown option 'seed' of the none reward; it has no"),
    (dict(reward="uncertainty", reward_options={"members": 1}), "members must be a whole number in \\[2, 64\\]"),
    (dict(reward="psnr", reward_options={"field": {"n_sample": 8}}), "unknown field option n_sample"),
    (dict(reward="coverage", reward_options=[1]), "reward options must be a dict of settings, not list"),
    (dict(allow_repeats="no"), "allow_repeats must be True or False, got 'no'"),
])
def test_reward_settings_are_checked(source, kw, message):
    with pytest.raises(UserError, match=message):
        ActiveViewEnv(source, budget=2, **kw)


def test_a_reward_object_takes_no_reward_options(source):
    from mitsuba_active.rewards import CoverageReward

    env = ActiveViewEnv(source, budget=2, reward=CoverageReward(seed=3))
    assert env.reward.options() == {"seed": 3}
    with pytest.raises(UserError, match="reward_options are the settings of a reward given by name"):
        ActiveViewEnv(source, budget=2, reward=CoverageReward(), reward_options={"seed": 1})
    without_depth = SimpleNamespace(**vars(source), has_distance=False)
    with pytest.raises(UserError, match="the coverage reward needs distances, and spot has no depth maps"):
        ActiveViewEnv(without_depth, budget=2, reward="coverage")
