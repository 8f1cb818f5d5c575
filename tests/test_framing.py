"""Rigs around an object stand as near as its geometry allows: every view holds the whole object."""

import math

import numpy as np
import pytest

from mitsuba_active.rigs import FRAMING_MARGIN, framing_radius, scene_rigs
from mitsuba_active.scene import load_scene


def _mesh_scene(tmp_path, mesh):
    """A Mitsuba scene of ``mesh`` (a trimesh) as it is, under a uniform light."""
    mesh.export(tmp_path / "object.ply")
    xml = tmp_path / "object.xml"
    xml.write_text('<scene version="3.0.0"><shape type="ply"><string name="filename" value="object.ply"/></shape>'
                   '<emitter type="constant"/></scene>')
    return load_scene(xml)


def _tilted_bar(tmp_path):
    """A 4 x 1 x 1 box turned 40 degrees about two axes: its bounding box's corners are empty."""
    import trimesh

    bar = trimesh.creation.box(extents=(4.0, 1.0, 1.0))
    bar.apply_transform(trimesh.transformations.euler_matrix(0.0, math.radians(40), math.radians(40)))
    bar.apply_translation((0.3, -0.2, 0.1))
    return bar, _mesh_scene(tmp_path, bar)


def _fill(camera, points) -> float:
    """How far out the points reach in ``camera``'s image: the largest of |x| / half-width and
    |y| / half-height over them (1: the image's edge), by hand from its pose and field of view.
    Every point must lie in front of it."""
    local = (points - camera.position) @ camera.to_world[:3, :3]  # Mitsuba: +X left, +Y up, +Z forward
    assert (local[:, 2] > 0).all()
    tan_x = math.tan(math.radians(camera.fov) / 2)
    tan_y = tan_x * camera.height / camera.width
    return float(max(np.abs(local[:, 0] / local[:, 2]).max() / tan_x, np.abs(local[:, 1] / local[:, 2]).max() / tan_y))


@pytest.mark.parametrize("rig, width, height", [("sphere", 16, 16), ("hemisphere", 16, 16), ("rings", 16, 16),
                                                ("sphere", 48, 16), ("sphere", 16, 40)])
def test_an_elongated_object_is_framed_by_its_geometry_and_every_view_holds_it(tmp_path, rig, width, height):
    bar, scene = _tilted_bar(tmp_path)
    # The sphere through its farthest corner, about the scene's centre: by hand, inside the box's sphere.
    assert framing_radius(scene) == pytest.approx(np.linalg.norm(bar.vertices - scene.center, axis=1).max())
    assert framing_radius(scene) < 0.8 * scene.radius
    candidates, heldout = scene_rigs(scene, rig, 30, 10, width, height)
    half_fov = math.atan(math.tan(math.radians(candidates[0].fov) / 2) * min(1.0, height / width))
    distances = [np.linalg.norm(c.position - scene.center) for c in candidates + heldout]
    assert max(distances) < 0.8 * FRAMING_MARGIN * scene.radius / math.sin(half_fov)  # nearer than before
    fills = [_fill(c, bar.vertices) for c in candidates + heldout]
    assert max(fills) < 1.0  # every corner inside every image
    assert max(fills) > 0.8  # and the nearest view is filled: no far stand-off


def test_a_box_along_the_axes_fills_its_bounding_sphere_and_shapes_without_vertices_keep_it(tmp_path):
    import trimesh

    bar = trimesh.creation.box(extents=(4.0, 1.0, 0.5))
    scene = _mesh_scene(tmp_path, bar)
    assert framing_radius(scene) == pytest.approx(scene.radius)  # its corners are its bounding box's
    candidates, heldout = scene_rigs(scene, "sphere", 40, 10, 16)
    assert max(_fill(c, bar.vertices) for c in candidates + heldout) < 1.0
    xml = tmp_path / "ball.xml"
    xml.write_text('<scene version="3.0.0"><shape type="sphere"/><emitter type="constant"/></scene>')
    ball = load_scene(xml)
    assert framing_radius(ball) == pytest.approx(ball.radius)  # an analytic shape: its bounding box's corners


def test_a_rounded_mesh_is_seen_nearer_and_fills_more_of_its_views(sphere_xml):
    from tests.conftest import tiny_source

    scene = load_scene(sphere_xml)
    assert framing_radius(scene) == pytest.approx(0.5, abs=1e-3)  # the icosphere's vertices, not its box's corners
    source = tiny_source(sphere_xml, n_candidates=6, n_heldout=2, resolution=16, spp=1)
    # Its silhouette is a disc of angular radius asin(sin(20 deg) / 1.05), a share pi tan^2 / (4 tan^2 20 deg)
    # of the square image: 0.70, where the bounding box's sphere (0.87 across) left it 0.22.
    sin_a = math.sin(math.radians(20)) / FRAMING_MARGIN
    expected = math.pi * sin_a ** 2 / (1 - sin_a ** 2) / (4 * math.tan(math.radians(20)) ** 2)
    covered = np.mean([source.heldout_view(i).mask.mean() for i in range(2)])
    assert expected == pytest.approx(0.70, abs=0.01) and covered == pytest.approx(expected, abs=0.06)
