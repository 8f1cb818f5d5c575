"""View sources: what the environment observes (:class:`ViewSource`), and a Mitsuba scene's (:class:`SceneSource`).

A dataset's, of captured frames, is :class:`~mitsuba_active.datasets.DatasetSource`;
:func:`~mitsuba_active.datasets.open_source` opens either kind by path.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from .cameras import Camera
from .field.grid import GridLayout
from .field.room import room_options
from .groundtruth import GroundTruth, View
from .rigs import check_disjoint, scene_rigs
from .scene import load_scene, scene_from_mitsuba


class ViewSource(Protocol):
    """What :class:`ActiveViewEnv` needs from a scene or a dataset."""

    candidates: list[Camera]
    heldout: list[Camera]
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    name: str
    has_distance: bool  #: whether views carry distances (a dataset without depth maps has none)

    def candidate_view(self, index: int) -> View: ...

    def heldout_view(self, index: int) -> View: ...

    def render(self, camera: Camera) -> View:
        """Capture an arbitrary camera; sources that cannot raise UserError."""


class SceneSource:
    """Views of a Mitsuba scene, rendered on demand and cached.

    Args:
        scene: a loaded :class:`~mitsuba_active.scene.Scene`.
        candidates, heldout: camera lists (see :func:`~mitsuba_active.rigs.scene_rigs`).
        spp: samples per pixel of the ground-truth renders.
        cache_dir: EXR cache folder (see :class:`~mitsuba_active.groundtruth.GroundTruth`);
            a scene built in Python has no files to key a cache by, and is never cached.
    """

    has_distance = True  # rendered: every view has its distances

    def __init__(self, scene, candidates, heldout, spp=64, cache_dir=None):
        check_disjoint(candidates, heldout)
        self.scene = scene
        self.name = scene.name
        self.candidates, self.heldout = list(candidates), list(heldout)
        self.bbox_min, self.bbox_max = scene.bbox_min, scene.bbox_max
        self.groundtruth = GroundTruth(scene, spp=spp, cache_dir=False if scene.content_hash is None else cache_dir)

    @classmethod
    def from_xml(cls, xml_path, rig="auto", n_candidates=100, n_heldout=20, resolution=64, fov=None,
                 spp=64, cache_dir=None):
        """Load a scene XML and make its rigs (:func:`~mitsuba_active.rigs.scene_rigs`).

        ``resolution`` is the image width in pixels; the height equals it, or
        under ``rig="xml"`` follows the aspect ratio of the scene's own films.
        """
        return cls.from_scene(load_scene(xml_path), rig, n_candidates, n_heldout, resolution, fov, spp, cache_dir)

    @classmethod
    def from_mitsuba(cls, scene, name="scene", rig="auto", n_candidates=100, n_heldout=20, resolution=64,
                     fov=None, spp=64):
        """A scene built in Python, a ``mitsuba.Scene`` or a scene dict, with
        rigs made as :meth:`from_xml` makes them. Its views are rendered
        whenever asked for (there are no files to key a cache by); ``name``
        names it in messages (see :func:`~mitsuba_active.scene.scene_from_mitsuba`).
        """
        return cls.from_scene(scene_from_mitsuba(scene, name), rig, n_candidates, n_heldout, resolution, fov, spp)

    @classmethod
    def from_scene(cls, scene, rig="auto", n_candidates=100, n_heldout=20, resolution=64, fov=None, spp=64,
                   cache_dir=None):
        """A loaded :class:`~mitsuba_active.scene.Scene` with rigs made by
        :func:`~mitsuba_active.rigs.scene_rigs`."""
        cands, held = scene_rigs(scene, rig, n_candidates, n_heldout, resolution, None, fov)
        return cls(scene, cands, held, spp=spp, cache_dir=cache_dir)

    def field_options(self, config=None, planner: bool = False) -> dict:
        """:class:`~mitsuba_active.field.FieldConfig` options the scene needs over
        ``config`` (the run's, or None) of an evaluation field or (``planner``) the planner's
        ensemble: a room's (:func:`~mitsuba_active.field.room.room_options`) where it is one and
        most candidate cameras stand inside its box; else none."""
        if not self.scene.interior:
            return {}
        if config is None:
            return room_options(self.candidates, self.bbox_min, self.bbox_max, planner=planner)
        finest = GridLayout.from_config(config).resolutions[-1]
        return room_options(self.candidates, self.bbox_min, self.bbox_max, config.distance_weight, planner, finest)

    def candidate_view(self, index: int) -> View:
        return self.groundtruth.render(self.candidates[index])

    def heldout_view(self, index: int) -> View:
        return self.groundtruth.render(self.heldout[index])

    def render(self, camera: Camera) -> View:
        return self.groundtruth.render(camera)

    def __deepcopy__(self, memo):
        # gymnasium's EnvSpec.make deep-copies make's arguments; a Mitsuba scene cannot be copied, nor need it be.
        return self
