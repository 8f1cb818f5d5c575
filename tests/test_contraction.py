"""The scene contraction: contracted sampling, captures with far backgrounds, save/load and the plugin's path."""

import json
import math

import imageio.v3 as iio
import mitsuba as mi
import numpy as np
import pytest

from mitsuba_active.cameras import camera_rays
from mitsuba_active.datasets import FAR_CONTRACTION, DatasetSource, plain_backdrop
from mitsuba_active.field.config import CAPTURE_SKY_RESOLUTION
from mitsuba_active.errors import UserError
from mitsuba_active.field import Ensemble, FieldConfig
from mitsuba_active.field.render_dr import render_rays_dr
from mitsuba_active.field.samples import field_position, sample_along_rays
from mitsuba_active.field.variational import VariationalField
from mitsuba_active.metrics import foreground_psnr, psnr
from mitsuba_active.training import predict_view, train_on

from benchmarks.unbounded_quality import ball_mask, write_capture

BOX = ([-0.6] * 3, [0.6] * 3)


def test_contraction_option_is_checked():
    for bad in (-1.0, 0.5, 1.0, 1e9):
        with pytest.raises(UserError, match="contraction"):
            FieldConfig(contraction=bad)
    assert FieldConfig(contraction=16).contraction == 16


def test_contracted_samples_cover_the_box_then_the_far_range():
    """Half a ray's samples in the box, evenly; the rest out to the far shell, sorted, metric and contiguous."""
    F, S = 16.0, 16
    ens = Ensemble([-1] * 3, [1] * 3, 1, FieldConfig(contraction=F, n_samples=S, bbox_padding=0.0))
    o = mi.Point3f(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 5.0], [0.3, -0.2, 0.1]]).T)
    d = mi.Vector3f(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.6, 0.0, 0.8]]).T)  # the 2nd misses the box
    s = sample_along_rays(o, d, ens.params())
    t, delta = np.array(s["t"]).reshape(3, S), np.array(s["delta"]).reshape(3, S)
    u = np.array(s["u"]).T.reshape(3, S, 3)
    assert np.all(np.diff(t, axis=1) > 0) and np.all(delta > 0)
    assert np.allclose(t[0, : S // 2], (np.arange(S // 2) + 0.5) / (S // 2))  # the box, from the camera to z = 1
    assert np.allclose(delta[0, : S // 2], 1.0 / (S // 2))
    # Bins abut: the far samples' bins run from the box's exit to the shell F out.
    edges = np.cumsum(delta[0, S // 2:]) + 1.0
    assert edges[-1] == pytest.approx(F, rel=1e-4) and np.all(t[0, S // 2:] < edges)
    # Each far bin covers an equal step of contracted radius 2 - 1/r.
    c = 2.0 - 1.0 / np.concatenate([[1.0], edges])
    assert np.allclose(np.diff(c), (2 - 1 / F - 1) / (S // 2), atol=1e-5)
    # A ray that misses the box: every sample beyond its point nearest the centre (5 away).
    assert t[1, 0] > 0 and np.sqrt(25 + t[1, -1] ** 2) == pytest.approx(np.sqrt(25 + (F ** 2 - 25)), rel=0.05)
    assert u.min() >= 0 and u.max() <= 1
    # The box is the middle half of the grid, undistorted; the far shell nears its faces.
    assert np.allclose(u[0, : S // 2, 2], 0.5 + 0.25 * t[0, : S // 2], atol=1e-6)
    assert u[0, -1, 2] > 0.95
    p = mi.Point3f(np.array([[0.5, 0.0, 0.0], [3.0, 1.0, 0.0], [-100.0, 0.0, 0.0]]).T)
    assert np.allclose(np.array(field_position(ens.params(), p)).T,
                       [[0.625, 0.5, 0.5], [0.5 + (2 - 1 / 3) / 4, 0.5 + (2 - 1 / 3) / 12, 0.5], [0.0025, 0.5, 0.5]],
                       atol=1e-6)


def test_contracted_field_saves_loads_and_renders_through_the_plugin_path(tmp_path, rng):
    cfg = FieldConfig(contraction=8.0, n_samples=16, batch_rays=256, occupancy_resolution=8, occupancy_warmup=2,
                      occupancy_interval=2)
    ens = Ensemble(*BOX, 2, cfg, seed=1)
    o = rng.normal(size=(300, 3)) * 2
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ens.set_rays(o, d, rng.uniform(size=(300, 3)), None, np.zeros(300, bool))
    assert np.all(np.isfinite(ens.train(6)))
    out = ens.render(o[:20], d[:20])
    # Distances are metric: along the ray, within the far shell's reach.
    assert np.all(out["distance"] >= 0) and np.all(out["distance"] < 8 * 0.66 * math.sqrt(3) + 4 * 2)
    path = ens.save(tmp_path / "f.npz") or tmp_path / "f.npz"
    back = Ensemble.load(path)
    assert back.config.contraction == 8.0
    again = back.render(o[:20], d[:20])
    assert np.allclose(again["rgb"], out["rgb"], atol=1e-6)
    rgb, dist, _ = render_rays_dr(back, mi.Point3f(o[:20].T.astype(np.float32)),
                                  mi.Vector3f(d[:20].T.astype(np.float32)), 1)
    assert np.allclose(np.array(rgb).T, out["rgb"][1], atol=1e-5)
    assert np.allclose(np.array(dist), out["distance"][1], rtol=1e-4, atol=1e-4)


def test_directional_background_learns_saves_loads_and_renders_through_the_plugin_path(tmp_path, rng):
    """Rays that miss the box see a colour that depends on their direction: the sky map fits it
    where one background colour cannot, and it survives save and load and the plugin's path."""
    n = 2000
    o = rng.normal(size=(n, 3))
    o = 3.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rgb = 0.5 + 0.4 * d
    errors = {}
    for rows in (0, 8):
        ens = Ensemble(*BOX, 2, FieldConfig(background_resolution=rows, n_samples=16, batch_rays=256), seed=1)
        ens.set_rays(o, d, rgb, None, np.zeros(n, bool))
        ens.train(200)
        out = ens.render(o[:200], d[:200])
        errors[rows] = float(np.abs(out["rgb"] - rgb[:200]).mean())
    assert errors[8] < 0.05 < errors[0], errors
    assert ens.sky_numpy().shape == (ens.sky_size,) and np.any(ens.sky_numpy() != 0)
    back = Ensemble.load(ens.save(tmp_path / "f.npz") or tmp_path / "f.npz")
    assert back.config.background_resolution == 8
    assert np.allclose(back.render(o[:200], d[:200])["rgb"], out["rgb"], atol=1e-6)
    rgb_dr, _, _ = render_rays_dr(back, mi.Point3f(o[:20].T.astype(np.float32)),
                                  mi.Vector3f(d[:20].T.astype(np.float32)), 1)
    assert np.allclose(np.array(rgb_dr).T, out["rgb"][1, :20], atol=1e-5)
    with pytest.raises(UserError, match="background_resolution"):
        FieldConfig(background_resolution=-1)


def test_variational_field_trains_contracted(rng):
    vf = VariationalField(*BOX, config=FieldConfig(contraction=4.0, n_samples=8, batch_rays=128), seed=0)
    o = rng.normal(size=(100, 3))
    d = rng.normal(size=(100, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    vf.set_rays(o, d, rng.uniform(size=(100, 3)), None, np.zeros(100, bool))
    assert np.all(np.isfinite(vf.train(3)))
    assert np.all(np.isfinite(vf.predict(o[:5], d[:5])["rgb_mean"]))


# -- a capture with a far background -------------------------------------------------

def far_capture(root, n=32, size=24, fov=50.0):
    """A textured ball (radius 0.5, emitting its checkerboard) in front of a textured
    environment, seen by ``n`` cameras on two rings 2 away, written as a transforms.json
    (every 4th held out)."""
    return write_capture(root, n, size, fov, elevations=(-10.0, 15.0), spp=16, test_every=4, env_size=(32, 64))


def test_far_background_capture_fits_better_contracted(tmp_path):
    src = DatasetSource.from_path(far_capture(tmp_path))
    assert src.suggested_contraction() == FAR_CONTRACTION
    assert src.field_options() == {"background_resolution": CAPTURE_SKY_RESOLUTION}
    views = [src.candidate_view(i) for i in range(len(src.candidates))]
    base = dict(n_levels=2, n_samples=32, batch_rays=1024, lr=0.02)
    scores = {}
    for contraction in (0.0, FAR_CONTRACTION):
        ens = Ensemble(src.bbox_min, src.bbox_max, 1, FieldConfig(contraction=contraction, **base), seed=0)
        train_on(ens, views, 300)
        scores[contraction] = np.mean([psnr(np.clip(ens.predict(*camera_rays(v.camera))["rgb_mean"], 0, 1),
                                            v.rgb.reshape(-1, 3)) for v in
                                       (src.heldout_view(i) for i in range(len(src.heldout)))])
    assert scores[FAR_CONTRACTION] > scores[0.0] + 3.0, scores


def test_far_background_capture_fits_better_with_a_directional_background(tmp_path):
    """From a third of the views, the sky map keeps the environment out of the volume: the ball's
    pixels in held-out views score better than with one background colour."""
    src = DatasetSource.from_path(far_capture(tmp_path))
    views = [src.candidate_view(i) for i in range(0, len(src.candidates), 3)]
    base = dict(n_levels=2, n_samples=32, batch_rays=1024, lr=0.02)
    scores = {}
    for rows in (0, CAPTURE_SKY_RESOLUTION):
        ens = Ensemble(src.bbox_min, src.bbox_max, 1, FieldConfig(background_resolution=rows, **base), seed=0)
        train_on(ens, views, 300)
        scores[rows] = np.mean([foreground_psnr(np.clip(predict_view(ens, v.camera)["rgb"], 0, 1), v.rgb,
                                                ball_mask(v.camera))
                                for v in (src.heldout_view(i) for i in range(len(src.heldout)))])
    assert scores[CAPTURE_SKY_RESOLUTION] > scores[0] + 2.0, scores


def test_capture_field_options(tmp_path):
    """aabb_scale over 1 contracts that far; a transparent or plain backdrop does not contract."""
    def write(folder, img, extra):
        folder.mkdir()
        iio.imwrite(folder / "a.png", img)
        frames = [{"file_path": "a.png", "split": split, "transform_matrix": np.eye(4).tolist()}
                  for split in ("train", "test")]
        (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames, **extra}))
        return DatasetSource.from_path(folder)

    rng = np.random.default_rng(0)
    textured = rng.integers(0, 255, (8, 8, 3), dtype=np.uint8)
    white = np.full((8, 8, 3), 255, np.uint8)
    white[3:5, 3:5] = 40
    rgba = np.concatenate([textured, np.full((8, 8, 1), 128, np.uint8)], axis=-1)
    box = {"aabb": [[-1, -1, -1], [1, 1, 1]]}
    assert write(tmp_path / "a", textured, {"aabb_scale": 16, "scale": 0.5})
    assert write(tmp_path / "b", textured, {"aabb_scale": 16}).suggested_contraction() == 16.0
    far = write(tmp_path / "c", textured, box)
    assert far.suggested_contraction() == FAR_CONTRACTION
    assert far.field_options() == {"background_resolution": CAPTURE_SKY_RESOLUTION}
    for folder, img in (("d", white), ("e", rgba)):
        plain = write(tmp_path / folder, img, box)
        assert plain.suggested_contraction() == 0.0 and plain.field_options() == {}
    assert plain_backdrop(np.zeros((4, 4, 3))) and not plain_backdrop(textured / 255.0)
