"""The authored looks: ``plain`` (as scenes were authored so far) and ``contrast``."""

import numpy as np
import pytest
from click.testing import CliRunner

from mitsuba_active.cli import main
from mitsuba_active.errors import UserError
from mitsuba_active.scene import SceneOptions, scene_from_mesh


@pytest.fixture(scope="module")
def ball(tmp_path_factory):
    import trimesh

    d = tmp_path_factory.mktemp("look")
    trimesh.creation.icosphere(subdivisions=3).export(d / "ball.ply")
    return d / "ball.ply"


def test_the_contrast_look_lights_from_the_side_and_takes_a_mid_tone(ball, tmp_path):
    plain = scene_from_mesh(ball, tmp_path / "plain" / "ball.xml", up="y").read_text()
    contrast = scene_from_mesh(ball, tmp_path / "contrast" / "ball.xml", up="y", look="contrast").read_text()
    # The plain look is the one scenes were authored with: their content hashes stay.
    assert ('<vector name="direction" x="-0.4" y="-1" z="-0.3"/><rgb name="irradiance" value="2.5"/>' in plain
            and '<rgb name="reflectance" value="0.45 0.3 0.2"/>' in plain)
    assert ('<vector name="direction" x="-0.6" y="-0.5" z="-0.45"/><rgb name="irradiance" value="4"/>' in contrast
            and '<rgb name="reflectance" value="0.25 0.25 0.25"/>' in contrast)
    assert contrast.count('type="directional"') == 1 and '<rgb name="radiance" value="1"/>' in contrast
    # A colour given is the object's, in either look.
    given = scene_from_mesh(ball, tmp_path / "given" / "ball.xml", up="y", look="contrast", color=(0.8, 0.1, 0.1))
    assert '<rgb name="reflectance" value="0.8 0.1 0.1"/>' in given.read_text()


def test_the_contrast_look_sets_the_object_apart_from_the_background(ball, tmp_path):
    from tests.conftest import tiny_source

    gaps = {}
    for look in ("plain", "contrast"):
        xml = scene_from_mesh(ball, tmp_path / look / "ball.xml", up="y", look=look)
        source = tiny_source(xml, n_candidates=4, n_heldout=2, resolution=16, spp=4)
        views = [source.heldout_view(i) for i in range(2)]
        gaps[look] = np.mean([v.rgb[~v.mask].mean() - v.rgb[v.mask].mean() for v in views])
    assert gaps["contrast"] > gaps["plain"] + 0.03, gaps


@pytest.mark.parametrize("options, message", [({"look": "moody"}, "the look must be one of plain, contrast"),
                                              ({"look": "contrast", "sun": False}, "lit by its sun")])
def test_bad_looks_are_one_line(options, message):
    with pytest.raises(UserError, match=message):
        SceneOptions(**options)


def test_a_suite_dresses_a_mesh_in_a_look_and_refuses_it_for_an_xml_scene(tmp_path):
    from mitsuba_active.bench import load_suite

    (tmp_path / "x.obj").write_text("")
    (tmp_path / "s.xml").write_text("<scene version='3.0.0'/>")
    (tmp_path / "s.toml").write_text("[[scenes]]\nmesh = 'x.obj'\nlook = 'contrast'\n")
    assert load_suite(tmp_path / "s.toml").scenes[0].scene_options == {"look": "contrast"}
    (tmp_path / "s.toml").write_text("[[scenes]]\nxml = 's.xml'\nlook = 'contrast'\n")
    with pytest.raises(UserError, match="look dress a mesh"):
        load_suite(tmp_path / "s.toml")


def test_scene_command_takes_the_look(ball, tmp_path):
    out = tmp_path / "c" / "ball.xml"
    result = CliRunner().invoke(main, ["scene", str(ball), "-o", str(out), "--up", "y", "--look", "contrast"])
    assert result.exit_code == 0, result.output
    assert 'x="-0.6" y="-0.5" z="-0.45"' in out.read_text()
    refused = tmp_path / "r" / "ball.xml"
    result = CliRunner().invoke(main, ["scene", str(ball), "-o", str(refused), "--look", "contrast", "--no-sun"])
    assert result.exit_code == 2 and not refused.exists()
