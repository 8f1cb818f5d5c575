"""Rooms seen from inside: the empty-room start and the options rooms get."""

import mitsuba as mi
import numpy as np
import pytest

from .conftest import tiny_source
from mitsuba_active.errors import UserError
from mitsuba_active.field import Ensemble, FieldConfig
from mitsuba_active.field.grid import GridLayout
from mitsuba_active.field.samples import sample_along_rays
from mitsuba_active.field.room import (ROOM_DISTANCE_OPTIONS, ROOM_OPTIONS, ROOM_PLANNER_OPTIONS, cameras_inside,
                                       room_options)
from mitsuba_active.run import RunConfig, source_field_config


def test_samples_start_near_away_from_the_origin():
    lo, hi = np.zeros(3), np.array([2.0, 1.0, 2.0])
    o, d = np.array([[1.0, 0.5, 1.0], [-1.0, 0.5, 1.0]]), np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    for near in (0.0, 0.1):
        ens = Ensemble(lo, hi, 1, FieldConfig(n_samples=16, near=near), seed=0)
        t = np.array(sample_along_rays(mi.Point3f(o.T), mi.Vector3f(d.T), ens.params())["t"]).reshape(2, 16)
        start = max(near * np.linalg.norm(hi - lo) * 1.1, 0.0)
        assert t[0, 0] - 0.5 * (t[0, 1] - t[0, 0]) == pytest.approx(start, abs=1e-5)  # inside: from near on
        assert t[1, 0] - 0.5 * (t[1, 1] - t[1, 0]) == pytest.approx(0.9, abs=1e-5)  # outside: from the box on
    for bad in (1.0, -0.1):
        with pytest.raises(UserError, match="near"):
            FieldConfig(near=bad)


def test_rooms_get_the_room_options_objects_do_not(shared_data, sphere_xml):
    cbox = tiny_source(shared_data / "mitsuba" / "cbox" / "cbox.xml", n_candidates=6, n_heldout=2)
    assert cameras_inside(cbox.candidates, cbox.bbox_min, cbox.bbox_max)
    assert cbox.field_options() == ROOM_OPTIONS
    ball = tiny_source(sphere_xml, n_candidates=6, n_heldout=2)
    assert ball.field_options() == {} and not cameras_inside(ball.candidates, ball.bbox_min, ball.bbox_max)
    # The evaluation field gets smooth levels up to what its images resolve, the planner's
    # ensemble its two coarse ones.
    for planner, options in ((True, ROOM_PLANNER_OPTIONS), (False, {**ROOM_OPTIONS, "n_levels": 2})):
        config = source_field_config(cbox, RunConfig(scene="x", resolution=16), planner)
        assert all(getattr(config, k) == v for k, v in options.items())
    assert ROOM_OPTIONS["smoothness_weight"] > 0 and "smoothness_weight" not in ROOM_PLANNER_OPTIONS
    assert ball.field_options(planner=True) == {}
    # With the distance loss the planner's ensemble takes the room's options but the smoothness.
    config = source_field_config(cbox, RunConfig(scene="x", resolution=16, distance_weight=10.0), True)
    assert config.smoothness_weight == 0 and config.view_degree == ROOM_DISTANCE_OPTIONS["view_degree"]
    # Trained on the distance maps too, a room gets the options that suit those.
    config = source_field_config(cbox, RunConfig(scene="x", resolution=16, distance_weight=10.0), False)
    assert config.near == ROOM_DISTANCE_OPTIONS.get("near", 0.0)
    assert config.n_levels == ROOM_DISTANCE_OPTIONS.get("n_levels", 2)  # else the preset's at 16 pixels
    # At 128 pixels the preset's evaluation field is view-dependent with three levels: a room's options replace it.
    cbox128 = tiny_source(shared_data / "mitsuba" / "cbox" / "cbox.xml", n_candidates=6, n_heldout=2, resolution=128)
    for weight, options in ((0.0, ROOM_OPTIONS), (10.0, ROOM_DISTANCE_OPTIONS)):
        preset = FieldConfig.preset("default", width=128)
        assert any(getattr(preset, k) != v for k, v in options.items())
        config = source_field_config(cbox128, RunConfig(scene="x", resolution=128, distance_weight=weight), False)
        assert all(getattr(config, k) == v for k, v in options.items())
    # The run's own field options come first.
    mine = {"n_levels": 3, "near": 0.0}
    config = source_field_config(cbox, RunConfig(scene="x", resolution=16, field=mine))
    assert (config.n_levels, config.near) == (3, 0.0)


def test_the_room_grid_is_dense_where_smoothness_needs_it():
    """Every level of a room's evaluation field is stored dense, so its total variation covers them all."""
    layout = GridLayout.from_config(FieldConfig.preset("default", width=128, **ROOM_OPTIONS))
    assert all(layout.dense) and layout.resolutions == (16, 32, 64)
    # Levels up to the finest that the preset gives the images, two at least, three at most.
    cams = [type("Camera", (), {"position": np.zeros(3)})()]
    levels = [room_options(cams, -np.ones(3), np.ones(3), finest=f)["n_levels"] for f in (16, 32, 64, 128)]
    assert levels == [2, 2, 3, 3]
