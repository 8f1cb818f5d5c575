"""The ``radiance_field`` Mitsuba integrator against the library's own renderer."""

import numpy as np
import pytest

import mitsuba_active  # noqa: F401  (variant first)
import mitsuba as mi

from mitsuba_active.cameras import Camera, camera_rays, look_at
from mitsuba_active.field import Ensemble, FieldConfig
from mitsuba_active.imageio_utils import srgb_to_linear
from mitsuba_active.plugins import register
from mitsuba_active.plugins.radiance_field import AOV_NAMES, NAME
from mitsuba_active.rigs import fibonacci_sphere

W, H = 16, 12


def trained_field(path, cfg):
    """A 3-member ensemble of ``cfg`` trained for a few steps on rays of a ball, saved to ``path``."""
    ens = Ensemble([-0.7] * 3, [0.7] * 3, n_members=3, config=cfg, seed=1)
    o, d = map(np.concatenate, zip(*(camera_rays(c) for c in fibonacci_sphere(4, [0, 0, 0], 3.0, width=16))))
    hit = np.abs(np.cross(o, d)).sum(1) < 0.5  # roughly the rays that pass the centre
    rgb = np.where(hit[:, None], [0.8, 0.3, 0.1], 1.0)
    ens.set_rays(o, d, rgb, np.where(hit, 2.5, 0.0), hit)
    ens.train(5)
    ens.save(path)
    return path


@pytest.fixture(scope="module")
def field_path(tmp_path_factory):
    assert register()
    cfg = FieldConfig(n_levels=2, base_resolution=8, log2_table_size=12, n_samples=32,
                      batch_rays=512, render_batch=1024)
    return trained_field(tmp_path_factory.mktemp("plugin") / "field.npz", cfg)


def pixel_centre_sensor(cam: Camera, spp=1, near=0.5, pixel_format="rgb"):
    """A perspective sensor sampling pixel centres only (stratified, no jitter, box filter)."""
    return mi.load_dict({
        "type": "perspective", "fov": cam.fov, "fov_axis": "x", "near_clip": near,
        "to_world": mi.ScalarTransform4f(cam.to_world.tolist()),
        "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height,
                 "rfilter": {"type": "box"}, "pixel_format": pixel_format},
        "sampler": {"type": "stratified", "sample_count": spp, "jitter": False},
    })


def render(path, sensor, **params):
    scene = mi.load_dict({"type": "scene", "integrator": {"type": NAME, "filename": str(path), **params},
                          "sensor": sensor})
    return scene, np.array(mi.render(scene), dtype=np.float32)


@pytest.fixture(scope="module")
def camera():
    return Camera(look_at([0.4, 0.6, -2.8], [0.0, 0.1, 0.0]), 45.0, W, H)


def test_plugin_matches_the_library_renderer(field_path, camera):
    scene, img = render(field_path, pixel_centre_sensor(camera), linear=False)
    assert img.shape == (H, W, 3 + len(AOV_NAMES))
    assert scene.integrator().aov_names() == AOV_NAMES
    p = Ensemble.load(field_path).predict(*camera_rays(camera))
    flat = img.reshape(-1, img.shape[-1])
    assert np.allclose(flat[:, :3], p["rgb_mean"], atol=1e-5)
    assert np.allclose(flat[:, 3:6], p["rgb_var"], atol=1e-6)
    # Distances are from the optical centre although Mitsuba starts rays at the near plane (0.5).
    assert np.allclose(flat[:, 6], p["distance_mean"], atol=1e-4)
    assert np.allclose(flat[:, 7], p["distance_var"], atol=1e-5)
    assert np.allclose(flat[:, 8], p["opacity"], atol=1e-5)
    # The field is not trivial: members disagree and something is in view.
    assert p["rgb_var"].max() > 1e-6 and p["opacity"].max() > 0.05 and p["distance_mean"].max() > 1.0


@pytest.mark.parametrize("preset", ["fast", "default"])
def test_each_preset_renders_as_the_library_renders_it(preset, tmp_path, camera):
    """Both presets' evaluation fields (the default's for 400-pixel images: hashed levels and
    empty-space skipping, at a tiny table size) in the plugin."""
    assert register()
    cfg = FieldConfig.preset(preset, width=400, log2_table_size=12, n_samples=32, batch_rays=512,
                             render_batch=1024, occupancy_warmup=1, occupancy_interval=1)
    path = trained_field(tmp_path / "field.npz", cfg)
    assert (Ensemble.load(path).occupancy() is not None) == (preset == "default")
    _, img = render(path, pixel_centre_sensor(camera), linear=False)
    p = Ensemble.load(path).predict(*camera_rays(camera))
    flat = img.reshape(-1, img.shape[-1])
    # Mitsuba starts rays at the near plane: a sample within rounding of an
    # occupancy cell's face may fall on the other side, and a skipped cell's
    # faint density (below occupancy_threshold) then counts or not.
    diff = np.abs(flat[:, :3] - p["rgb_mean"]).max(axis=1)
    assert np.mean(diff < 1e-5) > 0.9 and diff.max() < 1e-2, diff.max()
    assert np.abs(flat[:, 8] - p["opacity"]).max() < 1e-2 and p["opacity"].max() > 0.05
    if preset == "fast":  # nothing skipped: every pixel as the library renders it
        assert diff.max() < 1e-5 and np.abs(flat[:, 6] - p["distance_mean"]).max() < 1e-4


def test_a_view_dependent_field_renders_as_the_library_renders_it(tmp_path, camera):
    assert register()
    cfg = FieldConfig(n_levels=2, base_resolution=8, log2_table_size=12, n_samples=32, batch_rays=512,
                      render_batch=1024, view_degree=2, view_resolution=4)
    path = trained_field(tmp_path / "field.npz", cfg)
    assert Ensemble.load(path).view_numpy().any()
    _, img = render(path, pixel_centre_sensor(camera), linear=False)
    p = Ensemble.load(path).predict(*camera_rays(camera))
    assert np.abs(img.reshape(-1, img.shape[-1])[:, :3] - p["rgb_mean"]).max() < 1e-5


def test_default_output_is_linear_rgb(field_path, camera):
    _, img = render(field_path, pixel_centre_sensor(camera))
    p = Ensemble.load(field_path).predict(*camera_rays(camera))
    assert np.allclose(img[..., :3].reshape(-1, 3), srgb_to_linear(p["rgb_mean"]), atol=1e-5)


def test_any_sensor_through_plain_mi_render(field_path, camera):
    # A sensor passed to mi.render (not the scene's), several random samples per pixel.
    scene, _ = render(field_path, pixel_centre_sensor(camera))
    img = np.array(mi.render(scene, sensor=camera.with_resolution(8, 6).sensor(spp=4), spp=4))
    assert img.shape == (6, 8, 9) and np.all(np.isfinite(img))
    assert img[..., :3].min() >= 0 and img[..., :3].max() <= 1 and img[..., 8].max() <= 1 + 1e-6


def test_an_rgba_films_alpha_is_one_and_opacity_is_the_coverage(field_path, camera):
    _, img = render(field_path, pixel_centre_sensor(camera, pixel_format="rgba"))
    assert img.shape == (H, W, 4 + len(AOV_NAMES))
    assert np.allclose(img[..., 3], 1.0)  # as documented: Mitsuba's alpha marks valid samples
    opacity = Ensemble.load(field_path).predict(*camera_rays(camera))["opacity"]
    assert np.allclose(img[..., -1].ravel(), opacity, atol=1e-5) and opacity.min() < 0.9


def test_missing_filename_is_refused():
    assert register()
    with pytest.raises(Exception, match="filename"):
        mi.load_dict({"type": NAME})


def test_linear_must_be_a_boolean(field_path):
    """A string such as "false" would otherwise read as true."""
    assert register()
    with pytest.raises(Exception, match="'linear' must be a boolean, got 'false'"):
        mi.load_dict({"type": NAME, "filename": str(field_path), "linear": "false"})
    assert mi.load_dict({"type": NAME, "filename": str(field_path), "linear": False}).linear is False


def test_a_relative_filename_is_found_beside_the_scene_xml(field_path, tmp_path, monkeypatch):
    import shutil

    folder = tmp_path / "scene"
    folder.mkdir()
    shutil.copy(field_path, folder / "my_field.npz")
    (folder / "scene.xml").write_text(f"""<scene version="3.0.0">
  <integrator type="{NAME}"><string name="filename" value="my_field.npz"/></integrator>
  <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="4"/>
    <integer name="height" value="3"/></film></sensor>
</scene>""")
    monkeypatch.chdir(tmp_path)  # not the scene's folder
    img = np.array(mi.render(mi.load_file("scene/scene.xml"), spp=1))
    assert img.shape == (3, 4, 9) and np.all(np.isfinite(img))


def test_other_variants_are_told_which_the_integrator_needs():
    import os
    import subprocess
    import sys

    code = ("import mitsuba_active, mitsuba as mi\nmi.set_variant('llvm_ad_spectral')\n"
            "try:\n    mi.load_dict({'type': 'radiance_field', 'filename': 'x.npz'})\n"
            "except Exception as exc:\n    print(str(exc).strip().splitlines()[-1])\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=dict(os.environ, MITSUBA_ACTIVE_VARIANT="llvm_ad_rgb"))
    assert "needs Mitsuba variant llvm_ad_rgb or cuda_ad_rgb, not llvm_ad_spectral" in proc.stdout, proc.stderr


def test_a_variational_field_renders_its_draws(field_path, camera, tmp_path):
    from mitsuba_active.field import VariationalField

    ens = Ensemble.load(field_path)
    field = VariationalField(ens.bbox_min, ens.bbox_max, config=ens.config, seed=2, draws=4)
    path = tmp_path / "variational.npz"
    field.save(path)
    _, img = render(path, pixel_centre_sensor(camera), linear=False)
    p = VariationalField.load(path).predict(*camera_rays(camera))
    flat = img.reshape(-1, img.shape[-1])
    # The spread of the draws, not of the table's two slots as if they were members.
    assert p["rgb_var"].mean() > 1e-4
    assert np.allclose(flat[:, :3], p["rgb_mean"], atol=1e-5)
    assert np.allclose(flat[:, 3:6], p["rgb_var"], atol=1e-6)


def test_a_contracted_field_renders_as_the_library_renders_it(tmp_path, camera):
    assert register()
    cfg = FieldConfig(n_levels=2, base_resolution=8, log2_table_size=12, n_samples=32, batch_rays=512,
                      render_batch=1024, contraction=8.0)
    path = trained_field(tmp_path / "field.npz", cfg)
    _, img = render(path, pixel_centre_sensor(camera), linear=False)
    p = Ensemble.load(path).predict(*camera_rays(camera))
    flat = img.reshape(-1, img.shape[-1])
    assert np.allclose(flat[:, :3], p["rgb_mean"], atol=1e-5)
    assert np.allclose(flat[:, 6], p["distance_mean"], rtol=1e-4, atol=1e-4)
    assert p["distance_mean"].max() > 4.0  # beyond the box, which the camera is 2.8 from the centre of
