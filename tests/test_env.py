import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from mitsuba_active.env import ActiveViewEnv
from mitsuba_active.errors import UserError
from tests.conftest import tiny_source


@pytest.fixture(scope="module")
def source(spot_xml):
    return tiny_source(spot_xml, n_candidates=10, n_heldout=3, resolution=12)


def test_passes_gymnasium_env_checker(source):
    check_env(ActiveViewEnv(source, budget=4), skip_render_check=True)


def test_reset_step_mask_and_termination(source):
    env = ActiveViewEnv(source, budget=4)
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
    first, _ = env.reset(seed=0)
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
