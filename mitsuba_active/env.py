"""The gym-style environment: actions are candidate cameras, observations are views.

:class:`ActiveViewEnv` is a ``gymnasium.Env`` over a *view source*: anything
with ``candidates`` and ``heldout`` camera lists, scene bounds, and a way
to observe a candidate (see :class:`~.sources.ViewSource`). :class:`~.sources.SceneSource`
renders a Mitsuba scene on demand, so it can also capture arbitrary poses;
a pre-captured dataset source only looks its views up.

``import mitsuba_active`` registers it with gymnasium as
:data:`mitsuba_active.ENV_ID`: ``gymnasium.make("mitsuba_active/ActiveView-v0",
scene="scene.xml", budget=10)`` makes it with :func:`make_env`. Its reward is
0 unless one of :mod:`mitsuba_active.rewards` is asked for: reconstruction
quality is measured by the evaluation protocol (:mod:`mitsuba_active.run`).
"""

from __future__ import annotations

import dataclasses
import inspect
import os
from collections.abc import Mapping

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from .cameras import Camera, rigid_pose
from .checks import is_whole
from .datasets import open_source
from .errors import RepeatedView, UserError
from .groundtruth import View
from .imageio_utils import to_uint8
from .rewards import Reward, make_reward
from .sources import SceneSource, ViewSource


class ActiveViewEnv(gym.Env):
    """Choose views of a scene one at a time, under a view budget.

    * action: index of a candidate camera, ``Discrete(n_candidates)``;
    * observation: ``{"rgb": (H,W,3) float32 in [0,1], "distance": (H,W)
      float32 (0 where nothing is hit), "mask": (H,W) int8 hit mask,
      "pose": (4,4) float32 camera-to-world (Mitsuba convention)}``;
      all zeros and an identity pose before the first view;
    * ``info``: ``"intrinsics"`` (3,3) pixel intrinsics of the observation's
      camera (candidates may differ in field of view; candidate 0's before
      any capture), ``"action_mask"`` (n_candidates,)
      int8 with 1 for views not yet captured (``action_space.sample(mask=...)``
      draws among them), ``"captured"`` (list of indices), ``"views_left"``;
    * an episode starts with nothing captured, or with
      ``reset(options={"initial_views": k})`` k random distinct candidates;
    * terminated once ``budget`` views have been captured (initial views
      count); never truncated (``gymnasium.make``'s ``max_episode_steps`` may).

    ``capture_pose`` captures any 4x4 pose when the source can render.

    Parameters
    ----------

    .. list-table::
       :widths: 20 15 65

       * - source
         - :class:`ViewSource`
         - The scene or dataset whose candidate views are the actions.
       * - budget
         - int
         - Views captured in an episode, initial views included (default: 20).
       * - reward
         - str or :class:`~mitsuba_active.rewards.Reward`
         - What a step's reward measures (default: ``"none"``):

           - ``"none"``: 0.
           - ``"coverage"``: the fraction of the held-out views' surface points
             that the new view sees and no earlier view of the episode saw;
             unitless, in [0, 1]; 0 for a view captured again.
           - ``"uncertainty"``: the drop in an ensemble's colour variance over
             the new view's sparse rays when it trains on the view;
             squared sRGB units, in [-0.25, 0.25], positive on average.
           - ``"psnr"``: the gain in held-out PSNR, in dB, of a fresh field
             trained on the views so far. Expensive: each step trains a field
             from scratch (``steps`` steps, 1500 by default) and renders every
             held-out view.

           See :mod:`mitsuba_active.rewards` for their settings. The rewards
           that train fields are reproducible to ~1e-6 relative, not bit for
           bit: ``gymnasium.make`` then gives a ``nondeterministic`` spec.
       * - reward_options
         - dict
         - The named reward's settings, e.g. ``{"steps": 300}`` for ``"psnr"``.
       * - allow_repeats
         - bool
         - Whether a step may capture a candidate again (it spends budget:
           a planner that samples with replacement does so); if not (the
           default), such a step raises :class:`~mitsuba_active.errors.RepeatedView`,
           a ``ValueError``.
       * - render_mode
         - str or None
         - ``"rgb_array"``: :meth:`render` gives the latest view (of the last
           reset or step) as (H,W,3) uint8, black before the first; None
           (the default): :meth:`render` gives None.
    """

    # A video of an episode (gymnasium's RecordVideo) shows one view a second.
    metadata = {"render_modes": ["rgb_array"], "render_fps": 1}
    _spec = None

    def __init__(self, source: ViewSource, budget: int = 20, *, reward: str | Reward = "none",
                 reward_options: Mapping | None = None, allow_repeats: bool = False, render_mode: str | None = None):
        n = len(source.candidates)
        if n == 0:
            raise UserError("the environment has no candidate views")
        if not is_whole(budget) or budget <= 0:
            raise UserError(f"the view budget must be a positive whole number, got {budget!r}")
        if budget > n:
            raise UserError(f"the view budget ({budget}) is larger than the number of candidate views ({n})")
        sizes = {(c.height, c.width) for c in source.candidates}
        if len(sizes) != 1:
            raise UserError(f"candidate views must share one resolution, got {sorted(sizes)}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise UserError(f"unknown render_mode {render_mode!r}; the environment renders 'rgb_array' "
                            "(the latest view), or nothing with None")
        if not isinstance(allow_repeats, (bool, np.bool_)):
            raise UserError(f"allow_repeats must be True or False, got {allow_repeats!r}")
        if isinstance(reward, Reward):
            if reward_options is not None:
                raise UserError("reward_options are the settings of a reward given by name; "
                                f"the {reward.name} reward given is made already")
        else:
            reward = make_reward(reward, reward_options)
        (h, w), = sizes
        self.source, self.budget, self.shape = source, int(budget), (h, w)
        self.allow_repeats, self.render_mode = bool(allow_repeats), render_mode
        self.action_space = spaces.Discrete(n)
        self.observation_space = spaces.Dict({
            "rgb": spaces.Box(0.0, 1.0, (h, w, 3), np.float32),
            "distance": spaces.Box(0.0, np.inf, (h, w), np.float32),
            "mask": spaces.Box(0, 1, (h, w), np.int8),
            "pose": spaces.Box(-np.inf, np.inf, (4, 4), np.float32),
        })
        self.captured: list[int] = []
        self.views: list[View] = []
        reward.bind(source)
        self.reward = reward

    # -- gymnasium API -------------------------------------------------------
    def reset(self, *, seed=None, options=None):
        """Start over; ``options={"initial_views": k}`` captures k distinct random candidates first (default 0)."""
        if seed is not None and not (is_whole(seed) and seed >= 0):
            raise UserError(f"the seed must be a whole number of at least 0 (or None), got {seed!r}")
        super().reset(seed=None if seed is None else int(seed))  # gymnasium takes Python ints only
        if options is not None and not isinstance(options, Mapping):
            raise UserError("reset options must be a dict such as {'initial_views': 2}, "
                            f"not {type(options).__name__}")
        unknown = sorted(set(options or {}) - {"initial_views"}, key=str)
        if unknown:
            raise UserError(f"unknown reset option {', '.join(map(repr, unknown))}; the one option is 'initial_views'")
        k = (options or {}).get("initial_views", 0)
        if not is_whole(k) or not 0 <= k <= self.budget:
            raise UserError(f"initial views ({k!r}) must be a whole number between 0 and the budget ({self.budget})")
        self.captured, self.views = [], []
        for i in self.np_random.choice(self.action_space.n, size=k, replace=False):
            self._capture(int(i))
        self.reward.start(self.views)
        if self.views:
            return self._obs(self.views[-1]), self._info(self.views[-1].camera)
        blank = {"rgb": np.zeros((*self.shape, 3), np.float32), "distance": np.zeros(self.shape, np.float32),
                 "mask": np.zeros(self.shape, np.int8), "pose": np.eye(4, dtype=np.float32)}
        return blank, self._info(self.source.candidates[0])

    def step(self, action):
        """Capture candidate ``action``: returns ``(obs, reward, terminated, truncated, info)``.

        The reward is the constructor's ``reward`` of the new view (0 with
        ``"none"``); ``terminated`` once ``budget`` views are captured; never
        truncated. A candidate captured already is refused
        (:class:`~mitsuba_active.errors.RepeatedView`) unless ``allow_repeats``,
        and then uses up budget again.
        """
        if not self._is_candidate_index(action):
            raise UserError(f"invalid action {action!r}; expected a candidate index (a whole number) "
                            f"in [0, {self.action_space.n})")
        if self.terminated:
            raise UserError("the view budget is spent; call reset()")
        self._check_new([action], self.captured)
        view = self._capture(int(action))
        reward = float(self.reward.gain(self.views))
        return self._obs(view), reward, self.terminated, False, self._info(view.camera)

    def render(self):
        """The latest view of a reset or step as (H,W,3) uint8 sRGB (black before the first) under
        ``render_mode="rgb_array"``; None without a render mode. ``capture_pose``'s views are not shown."""
        if self.render_mode is None:
            return None
        rgb = self.views[-1].rgb if self.views else np.zeros((*self.shape, 3), np.float32)
        return to_uint8(rgb)  # as the run's PNGs of its views

    @property
    def spec(self):
        """The gymnasium spec that ``gymnasium.make`` gave it (else None), ``nondeterministic``
        where the reward is not bit for bit reproducible (``Reward.deterministic``)."""
        return self._spec

    @spec.setter
    def spec(self, spec):
        if spec is not None and not self.reward.deterministic:
            spec = dataclasses.replace(spec, nondeterministic=True)
        self._spec = spec

    # -- beyond gymnasium ----------------------------------------------------
    @property
    def terminated(self) -> bool:
        return len(self.captured) >= self.budget

    def capture_pose(self, pose: np.ndarray) -> dict:
        """Capture an arbitrary camera-to-world pose (Mitsuba convention) with candidate 0's intrinsics.

        The view is returned as an observation but not added to the captured set.
        A pose that is a candidate's or held-out camera's up to single
        precision (an observation's ``pose`` is float32) gives that camera's view.
        ``pose`` must be a rigid motion, 4x4 or 3x4 (else UserError, see
        :func:`~mitsuba_active.cameras.rigid_pose`).
        """
        pose = rigid_pose(pose, "the pose")
        # Single precision: 1e-6 on the rotation, relative to the position's size on the position.
        tol = 1e-6 * max(1.0, float(np.abs(pose[:3, 3]).max()))
        known = [c for c in self.source.candidates + self.source.heldout
                 if np.allclose(c.to_world[:3, :3], pose[:3, :3], rtol=0, atol=1e-6)
                 and np.allclose(c.to_world[:3, 3], pose[:3, 3], rtol=0, atol=tol)]
        ref = self.source.candidates[0]
        cam = known[0] if known else Camera(pose, ref.fov, ref.width, ref.height, ref.near, ref.far)
        return self._obs(self.source.render(cam))

    def add_candidate(self, camera: Camera) -> int:
        """Make ``camera`` one more candidate, rendered by the source when captured; its index.
        The source's candidate list grows: give the environment a source of its own."""
        if (camera.height, camera.width) != self.shape:
            raise ValueError(f"a new candidate must be {self.shape[1]}x{self.shape[0]} pixels as the others, "
                             f"not {camera.width}x{camera.height}")
        self.source.candidates.append(camera)
        self.action_space = spaces.Discrete(len(self.source.candidates))
        return len(self.source.candidates) - 1

    def restore(self, captured: list[int]) -> None:
        """Start over with exactly these candidates captured, in order (to resume a run);
        repeats only where ``allow_repeats``."""
        bad = [i for i in captured if not self._is_candidate_index(i)]
        if bad:
            raise UserError(f"cannot restore captured views {bad!r}: expected candidate indices (whole numbers) "
                            f"in [0, {self.action_space.n})")
        if len(captured) > self.budget:
            raise UserError(f"cannot restore {len(captured)} captured views: more than the budget ({self.budget})")
        self._check_new(captured, [])
        self.captured, self.views = [], []
        for i in captured:
            self._capture(int(i))
        self.reward.start(self.views)

    def _is_candidate_index(self, value) -> bool:
        # gymnasium's Discrete takes True for 1 and "3" for nothing: name them as given.
        return not isinstance(value, (bool, np.bool_)) and self.action_space.contains(value)

    def _check_new(self, indices, captured) -> None:
        """RepeatedView unless ``indices``, captured after ``captured``, repeat none (or repeats are allowed)."""
        if self.allow_repeats:
            return
        taken = set(captured)
        for i in indices:
            if int(i) in taken:
                raise RepeatedView(f"candidate {int(i)} is captured already (info['action_mask'] is 0 there); "
                                   "make the environment with allow_repeats=True to capture views again")
            taken.add(int(i))

    def _capture(self, index: int) -> View:
        view = self.source.candidate_view(index)
        self.captured.append(index)
        self.views.append(view)
        return view

    def _obs(self, view: View) -> dict:
        return {"rgb": view.rgb.astype(np.float32), "distance": view.distance.astype(np.float32),
                "mask": view.mask.astype(np.int8), "pose": view.camera.to_world.astype(np.float32)}

    def _info(self, camera: Camera) -> dict:
        mask = np.ones(self.action_space.n, dtype=np.int8)
        mask[self.captured] = 0
        return {"intrinsics": camera.intrinsics(), "action_mask": mask,
                "captured": list(self.captured), "views_left": self.budget - len(self.captured)}


def make_env(scene, **options) -> ActiveViewEnv:
    """The environment that ``gymnasium.make("mitsuba_active/ActiveView-v0", scene=..., ...)`` makes.

    ``scene`` is a scene XML, a transforms.json or a dataset folder
    (:func:`~mitsuba_active.datasets.open_source`), a ``mitsuba.Scene`` or
    a scene dict (:meth:`SceneSource.from_mitsuba`), or a view source made
    already. ``options`` are :class:`ActiveViewEnv`'s (``budget``,
    ``reward``, ...) and the view source's (``n_candidates``,
    ``resolution``, ``spp``, ...; none for a view source made already).
    """
    env_names = set(inspect.signature(ActiveViewEnv).parameters) - {"source"}
    env_options = {k: options.pop(k) for k in list(options) if k in env_names}
    if isinstance(scene, (str, os.PathLike)):
        source = open_source(scene, **options)
    elif hasattr(scene, "candidate_view"):
        if options:
            raise UserError(f"the view source {getattr(scene, 'name', '')!r} is made already: its settings "
                            f"{', '.join(sorted(options))} do not apply")
        source = scene
    elif isinstance(scene, dict) or type(scene).__module__.split(".")[0] == "mitsuba":
        source = SceneSource.from_mitsuba(scene, **options)
    else:
        raise UserError("scene must be a scene XML, a transforms.json or a dataset folder, a mitsuba.Scene or "
                        f"a scene dict, or a view source; got {type(scene).__name__}")
    return ActiveViewEnv(source, **env_options)


# gymnasium.make reads its creator's render modes, e.g. to collect frames for render_mode="rgb_array_list".
make_env.metadata = ActiveViewEnv.metadata
