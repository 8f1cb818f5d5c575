"""Shared fixtures: tiny scenes built from ../shared/data and from trimesh primitives."""

from pathlib import Path

import numpy as np
import pytest

import mitsuba_active  # noqa: F401  (sets the Mitsuba variant)

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    assert SHARED.is_dir(), f"the shared test data is expected at {SHARED}"
    return SHARED


@pytest.fixture(scope="session")
def spot_xml(tmp_path_factory, shared_data) -> Path:
    from mitsuba_active.scene import scene_from_mesh

    return scene_from_mesh(shared_data / "meshes" / "spot.obj", tmp_path_factory.mktemp("spot") / "spot.xml")


@pytest.fixture(scope="session")
def sphere_xml(tmp_path_factory) -> Path:
    """A unit-box-normalised icosphere: radius 0.5 at the origin, so distances are analytic, under
    the uniform light alone, so that its views differ only by what they see of it."""
    import trimesh

    from mitsuba_active.scene import scene_from_mesh

    d = tmp_path_factory.mktemp("sphere")
    trimesh.creation.icosphere(subdivisions=5, radius=1.0).export(d / "ball.ply")
    return scene_from_mesh(d / "ball.ply", d / "ball.xml", up="y", sun=False)


@pytest.fixture()
def cache_dir(tmp_path) -> Path:
    return tmp_path / "cache"


def tiny_source(xml, n_candidates=12, n_heldout=4, resolution=16, spp=4, cache_dir=False, rig="auto"):
    from mitsuba_active.env import SceneSource

    return SceneSource.from_xml(xml, rig=rig, n_candidates=n_candidates, n_heldout=n_heldout,
                                resolution=resolution, spp=spp, cache_dir=cache_dir)


@pytest.fixture()
def rng():
    return np.random.default_rng(0)


def two_sensor_xml(tmp_path, second_film="48x24"):
    """A sphere seen by two sensors of the author's: fields of view 30 (vertical) and 50 degrees."""
    w, h = second_film.split("x")
    xml = tmp_path / "two_sensors.xml"
    xml.write_text(f"""<scene version="3.0.0">
  <shape type="sphere"><float name="radius" value="0.5"/></shape>
  <emitter type="constant"/>
  <sensor type="perspective">
    <float name="fov" value="30"/><string name="fov_axis" value="y"/>
    <float name="near_clip" value="0.5"/><float name="far_clip" value="100"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="24"/></film>
  </sensor>
  <sensor type="perspective">
    <float name="fov" value="50"/>
    <transform name="to_world"><lookat origin="4, 0, 0" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="{w}"/><integer name="height" value="{h}"/></film>
  </sensor>
</scene>""")
    return xml
