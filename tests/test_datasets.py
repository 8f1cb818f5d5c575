"""Pre-captured datasets: layouts, pose and intrinsics conventions, images, errors."""

import dataclasses
import json
import math
import re
import warnings

import imageio.v3 as iio
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from mitsuba_active.cameras import camera_rays, look_at
from mitsuba_active.datasets import (DatasetSource, estimate_bounds, mitsuba_to_opengl, open_source,
                                     opengl_to_mitsuba)
from mitsuba_active.env import ActiveViewEnv, SceneSource
from mitsuba_active.errors import UserError
from mitsuba_active.rigs import fibonacci_sphere


@pytest.fixture(scope="module")
def mic_dir(shared_data):
    return shared_data / "datasets" / "nerf_synthetic_mic"


@pytest.fixture(scope="module")
def mic(mic_dir):
    return DatasetSource.from_path(mic_dir, downscale=32)


def blender_rays(matrix, fov_x, width, height):
    """Unit ray directions (H*W, 3) through pixel centres, by hand in the Blender convention."""
    f = 0.5 * width / math.tan(0.5 * fov_x)
    j, i = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    d_cam = np.stack([(j - 0.5 * width) / f, -(i - 0.5 * height) / f, -np.ones_like(j)], -1).reshape(-1, 3)
    d = d_cam @ np.asarray(matrix)[:3, :3].T
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def pose_gl(position, target):
    """A Blender camera-to-world matrix at ``position`` looking at ``target``."""
    return mitsuba_to_opengl(look_at(position, target))


def write_dataset(root, n=10, size=(8, 8), form="ngp", rgba=None, missing=(), extra=None, frame_extra=None):
    """A tiny dataset in ``root``: ``n`` cameras on a circle looking at the origin."""
    w, h = size
    (root / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for k in range(n):
        a = 2 * math.pi * k / n
        m = pose_gl([3 * math.cos(a), 0.5, 3 * math.sin(a)], [0, 0, 0])
        name = f"images/f_{k:03d}"
        if k not in missing:
            img = rgba if rgba is not None else np.full((h, w, 3), 10 * k, np.uint8)
            iio.imwrite(root / f"{name}.png", img)
        frame = {"file_path": name + ".png" if form == "ngp" else "./" + name, "transform_matrix": m.tolist()}
        frame.update((frame_extra or {}).get(k, {}))
        frames.append(frame)
    if form == "ngp":
        meta = {"fl_x": 10.0, "fl_y": 10.0, "cx": w / 2, "cy": h / 2, "w": w, "h": h, "frames": frames}
        meta.update(extra or {})
        (root / "transforms.json").write_text(json.dumps(meta))
        return root / "transforms.json"
    train, test = frames[: n - 2], frames[n - 2:]
    for split, fr in (("train", train), ("test", test)):
        meta = {"camera_angle_x": 0.8, "frames": fr}
        meta.update(extra or {})
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root / "transforms_train.json"


# -- poses and rays --------------------------------------------------------------

def test_pose_conversion_round_trips(rng):
    for _ in range(5):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        q *= np.sign(np.linalg.det(q))
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = q, rng.normal(size=3)
        mi_pose = opengl_to_mitsuba(m)
        assert np.allclose(mitsuba_to_opengl(mi_pose), m)
        assert np.allclose(mi_pose[:3, 2], -m[:3, 2])  # Mitsuba looks along +Z, Blender along -Z
        assert np.allclose(mi_pose[:3, 1], m[:3, 1])  # both have +Y up
        assert np.allclose(mi_pose[:3, 3], m[:3, 3])


def test_mirrored_or_scaled_rotation_is_refused():
    with pytest.raises(UserError, match="transform_matrix is not a rigid motion"):
        opengl_to_mitsuba(np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(UserError, match="transform_matrix is not a rigid motion"):
        opengl_to_mitsuba(np.diag([2.0, 2.0, 2.0, 1.0]))


def test_mic_frames_reproject_like_the_dataset_camera(mic, mic_dir):
    meta_test = json.loads((mic_dir / "transforms_test.json").read_text())
    meta_train = json.loads((mic_dir / "transforms_train.json").read_text())
    for cam, frame, meta in ((mic.heldout[0], meta_test["frames"][0], meta_test),
                             (mic.candidates[7], meta_train["frames"][7], meta_train)):
        assert (cam.width, cam.height) == (25, 25)
        assert cam.fov == pytest.approx(math.degrees(meta["camera_angle_x"]))
        o, d = camera_rays(cam)
        m = np.array(frame["transform_matrix"])
        assert np.allclose(o, m[:3, 3], atol=1e-5)
        assert np.allclose(d, blender_rays(m, meta["camera_angle_x"], 25, 25), atol=1e-5)


def test_mic_bounds_views_and_split(mic):
    assert len(mic.candidates) == 100 and len(mic.heldout) == 25 and mic.name == "nerf_synthetic_mic"
    assert np.all(mic.bbox_min > -1.8) and np.all(mic.bbox_min < -1.2)
    assert np.all(mic.bbox_max < 1.8) and np.all(mic.bbox_max > 1.2)
    v = mic.heldout_view(0)
    assert v.rgb.shape == (25, 25, 3) and v.rgb.dtype == np.float32
    assert 0.0 <= v.rgb.min() and v.rgb.max() <= 1.0
    assert v.rgb[0, 0] == pytest.approx([1, 1, 1], abs=1e-4)  # background composited on white
    assert v.rgb.min() < 0.5  # the microphone is there
    # The 8-bit depth maps of nerf-synthetic are not metric: distances are unknown.
    assert not v.mask.any() and not v.distance.any()
    again = mic.heldout_view(0)  # read once, handed out as arrays of the caller's own
    assert again is not v and np.array_equal(again.rgb, v.rgb)


def test_mic_downscale_is_an_area_average(mic_dir):
    src = DatasetSource.from_path(mic_dir / "transforms_train.json", downscale=16, n_heldout=3)
    assert len(src.heldout) == 3 and src.candidates[0].width == 50
    raw = iio.imread(mic_dir / "train" / "r_0.png").astype(np.float64) / 255
    rgb = raw[..., :3] * raw[..., 3:] + (1 - raw[..., 3:])
    from mitsuba_active.imageio_utils import linear_to_srgb, srgb_to_linear

    expect = linear_to_srgb(srgb_to_linear(rgb).reshape(50, 16, 50, 16, 3).mean(axis=(1, 3)))
    assert np.allclose(src.candidate_view(0).rgb, expect, atol=1e-5)


def test_env_over_a_dataset_passes_gymnasium_checker(mic):
    check_env(ActiveViewEnv(mic, budget=3), skip_render_check=True)


def test_render_only_looks_up_known_poses(mic):
    found, stored = mic.render(mic.heldout[2]), mic.heldout_view(2)
    assert found.camera is stored.camera and np.array_equal(found.rgb, stored.rgb)
    pose = mic.candidates[0].to_world.copy()
    pose[:3, 3] += 0.1
    env = ActiveViewEnv(mic, budget=2)
    env.reset(seed=0)
    with pytest.raises(UserError, match="cannot render new poses"):
        env.capture_pose(pose)


# -- images ------------------------------------------------------------------------

def test_rgba_is_composited_on_white_or_black(tmp_path):
    img = np.zeros((4, 4, 4), np.uint8)
    img[..., 0], img[..., 3] = 255, np.arange(16, dtype=np.uint8).reshape(4, 4) * 17
    path = write_dataset(tmp_path, n=3, size=(4, 4), form="blender", rgba=img)
    a = img[..., 3] / 255.0
    white = DatasetSource.from_path(path).candidate_view(0).rgb
    assert np.allclose(white[..., 0], 1.0, atol=1e-5)
    assert np.allclose(white[..., 1], 1.0 - a, atol=1e-5) and np.allclose(white[..., 2], 1.0 - a, atol=1e-5)
    black = DatasetSource.from_path(path, white_background=False).candidate_view(0).rgb
    assert np.allclose(black[..., 0], a, atol=1e-5) and np.allclose(black[..., 1], 0.0, atol=1e-6)


@pytest.mark.parametrize("channels", ["RGBA", "Y"])
def test_exr_images_with_alpha_or_grey(tmp_path, channels):
    """EXR colour is linear with premultiplied alpha (Blender's RGBA output): composited in linear light."""
    from mitsuba_active.imageio_utils import linear_to_srgb, write_exr

    write_dataset(tmp_path, n=3, form="blender", size=(4, 4))
    a = np.linspace(0, 1, 16, dtype=np.float32).reshape(4, 4)
    for k in range(3):
        (tmp_path / "images" / f"f_{k:03d}.png").unlink()
        data = ({"RGB": np.stack([0.5 * a, 0 * a, 0 * a], -1), "A": a} if channels == "RGBA"
                else {"Y": np.full((4, 4), 0.25, np.float32)})
        write_exr(tmp_path / "images" / f"f_{k:03d}.exr", data)
    for white in (True, False):
        rgb = DatasetSource.from_path(tmp_path / "transforms_train.json", white_background=white).candidate_view(0).rgb
        if channels == "Y":
            expected = np.broadcast_to(linear_to_srgb(np.float32(0.25)), (4, 4, 3))
        else:
            bg = (1.0 - a) if white else 0.0 * a
            expected = linear_to_srgb(np.stack([0.5 * a + bg, bg, bg], -1))
        assert np.allclose(rgb, expected, atol=1e-5)


def test_a_cmyk_jpeg_reads_as_its_rgb(tmp_path):
    from PIL import Image

    write_dataset(tmp_path, n=3, form="blender", size=(4, 4))
    cmyk = Image.new("CMYK", (4, 4), (40, 90, 10, 60))
    for k in range(3):
        (tmp_path / "images" / f"f_{k:03d}.png").unlink()
        cmyk.save(tmp_path / "images" / f"f_{k:03d}.jpg")
    rgb = DatasetSource.from_path(tmp_path / "transforms_train.json").candidate_view(0).rgb
    expected = np.asarray(Image.open(tmp_path / "images" / "f_000.jpg").convert("RGB"), np.float32) / 255
    assert np.allclose(rgb, expected, atol=1e-6) and expected.max() < 0.8  # not taken for RGBA on white


def test_a_damaged_npy_depth_map_is_one_line(tmp_path):
    np.save(tmp_path / "d.npy", np.array([{"a": 1}], dtype=object))
    write_dataset(tmp_path, n=3, frame_extra={0: {"depth_file_path": "d.npy"}})
    with pytest.raises(UserError, match="cannot read depth map .*d.npy"):
        DatasetSource.from_path(tmp_path).heldout_view(0)


def test_missing_frames_are_skipped_with_one_warning(tmp_path):
    path = write_dataset(tmp_path, n=10, form="blender", missing=(1, 4, 9))
    with pytest.warns(UserWarning, match="skipped 3 of 10 frames") as record:
        src = DatasetSource.from_path(path)
    assert len(record) == 1
    assert len(src.candidates) == 6 and len(src.heldout) == 1
    assert src.heldout_view(0).rgb[0, 0, 0] == pytest.approx(80 / 255, abs=1e-5)


# -- instant-ngp / nerfstudio form --------------------------------------------------

def test_instant_ngp_form_holds_out_every_8th_frame(tmp_path):
    write_dataset(tmp_path, n=17, size=(12, 8), extra={"camera_angle_x": 1.0})  # fl_x wins
    src = DatasetSource.from_path(tmp_path)
    assert len(src.heldout) == 3 and len(src.candidates) == 14
    cam = src.candidates[0]
    assert (cam.width, cam.height) == (12, 8)
    assert cam.fov == pytest.approx(math.degrees(2 * math.atan(6 / 10)))
    assert src.heldout_view(1).rgb[0, 0, 0] == pytest.approx(80 / 255, abs=1e-5)  # frame 8
    check_env(ActiveViewEnv(src, budget=2), skip_render_check=True)


def test_instant_ngp_off_centre_principal_point_is_cropped(tmp_path):
    w, h = 16, 12
    img = np.zeros((h, w, 3), np.uint8)
    img[..., 0] = np.arange(w)[None, :] * 10  # red encodes the column, green the row
    img[..., 1] = np.arange(h)[:, None] * 10
    write_dataset(tmp_path, n=3, size=(w, h), rgba=img, extra={"cx": 10.0, "cy": 5.0})
    src = DatasetSource.from_path(tmp_path / "transforms.json")
    cam = src.heldout[0]  # frame 0: every 8th frame is held out
    assert (cam.width, cam.height) == (12, 10)  # columns 4..15, rows 0..9
    v = src.heldout_view(0).rgb
    assert v[0, 0, 0] == pytest.approx(40 / 255, abs=1e-5) and v[-1, -1, 1] == pytest.approx(90 / 255, abs=1e-5)
    # The cropped camera's rays are the original camera's rays through the same pixels.
    meta = json.loads((tmp_path / "transforms.json").read_text())
    m = np.array(meta["frames"][0]["transform_matrix"])
    j, i = np.meshgrid(np.arange(4, 16) + 0.5, np.arange(0, 10) + 0.5)
    d = np.stack([(j - 10.0) / 10, -(i - 5.0) / 10, -np.ones_like(j)], -1).reshape(-1, 3) @ m[:3, :3].T
    assert np.allclose(camera_rays(cam)[1], d / np.linalg.norm(d, axis=1, keepdims=True), atol=1e-5)


def test_per_frame_principal_points_a_fraction_apart_share_one_window(tmp_path):
    write_dataset(tmp_path, n=9, size=(32, 32),
                  frame_extra={k: {"cx": 16.0 if k % 2 else 15.4, "cy": 16.0} for k in range(9)})
    src = DatasetSource.from_path(tmp_path)
    sizes = {(c.width, c.height) for c in src.candidates + src.heldout}
    assert sizes == {(31, 32)}, sizes  # the narrower window (centred on 15.5) for every frame
    ActiveViewEnv(src, budget=2)


def test_split_keys_and_nerfstudio_filenames(tmp_path):
    split = {k: {"split": "test"} for k in (2, 5)}
    write_dataset(tmp_path / "a", n=6, frame_extra=split)
    src = DatasetSource.from_path(tmp_path / "a")
    assert len(src.candidates) == 4 and len(src.heldout) == 2
    write_dataset(tmp_path / "b", n=6, extra={"train_filenames": ["images/f_000.png", "images/f_001.png"],
                                               "test_filenames": ["images/f_005.png"]})
    src = DatasetSource.from_path(tmp_path / "b")
    assert len(src.candidates) == 2 and len(src.heldout) == 1
    assert src.heldout_view(0).rgb[0, 0, 0] == pytest.approx(50 / 255, abs=1e-5)


def test_metric_depth_becomes_distance_along_rays(tmp_path):
    w = h = 8
    z = np.full((h, w), 2000, np.uint16)  # 2 m in millimetres
    z[:, :2] = 0  # unknown
    (tmp_path / "depth").mkdir()
    iio.imwrite(tmp_path / "depth" / "d.png", z)
    write_dataset(tmp_path, n=3, size=(w, h), frame_extra={0: {"depth_file_path": "depth/d.png"}},
                  extra={"depth_unit_scale_factor": 1e-3})
    src = DatasetSource.from_path(tmp_path)
    v = src.heldout_view(0)  # frame 0
    assert not v.mask[:, :2].any() and v.mask[:, 2:].all()
    _, d = camera_rays(src.heldout[0])
    cos = d @ src.heldout[0].forward
    assert np.allclose(v.distance[:, 2:], (2.0 / cos).reshape(h, w)[:, 2:], rtol=1e-5)
    assert not src.candidate_view(0).mask.any()  # no depth file: unknown


@pytest.mark.parametrize("key", ["depth_file_path", "distance_file_path"])
def test_an_8_bit_depth_map_names_the_key_to_remove(tmp_path, key):
    (tmp_path / "depth").mkdir()
    iio.imwrite(tmp_path / "depth" / "d.png", np.full((8, 8), 200, np.uint8))
    write_dataset(tmp_path, n=3, frame_extra={0: {key: "depth/d.png"}})
    with pytest.raises(UserError, match=f"8-bit and therefore not metric; remove the frame's {key}$"):
        DatasetSource.from_path(tmp_path).heldout_view(0)


def test_a_16_bit_colour_depth_png_is_named_as_such(tmp_path):
    """Pillow reads it as 8-bit: the message says what the file is, not what it was read as."""
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    rows = b"".join(b"\0" + np.full((8, 3), 1200, ">u2").tobytes() for _ in range(8))  # filter byte, RGB pixels
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 8, 8, 16, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))
    (tmp_path / "depth").mkdir()
    (tmp_path / "depth" / "d.png").write_bytes(png)
    write_dataset(tmp_path, n=3, frame_extra={0: {"depth_file_path": "depth/d.png"}})
    with pytest.raises(UserError, match="d.png is a 16-bit colour PNG, which is read as 8-bit; store depth as a "
                                        "16-bit grey PNG, an EXR or a .npy"):
        DatasetSource.from_path(tmp_path).heldout_view(0)


def test_aabb_key_sets_bounds(tmp_path):
    write_dataset(tmp_path, n=4, extra={"aabb": [[-1, -2, -3], [1, 2, 3]]})
    src = DatasetSource.from_path(tmp_path)
    assert np.allclose(src.bbox_min, [-1, -2, -3]) and np.allclose(src.bbox_max, [1, 2, 3])


def test_a_flat_aabb_is_a_box(tmp_path):
    """A planar scene's run records a flat box, and its export writes it as the aabb."""
    write_dataset(tmp_path, n=3, extra={"aabb": [[-1, 0, -1], [1, 0, 1]]})
    src = DatasetSource.from_path(tmp_path)
    assert np.allclose(src.bbox_min, [-1, 0, -1]) and np.allclose(src.bbox_max, [1, 0, 1])


def test_estimated_bounds_centre_on_the_object():
    cams = fibonacci_sphere(30, center=[1.0, -2.0, 0.5], radius=4.0, fov=40.0)
    lo, hi = estimate_bounds(cams)
    assert np.allclose(0.5 * (lo + hi), [1.0, -2.0, 0.5], atol=1e-6)
    assert np.allclose(0.5 * (hi - lo), 1.1 * 4.0 * math.sin(math.radians(20.0)), rtol=1e-6)


def test_transparent_pixels_are_known_empty_and_others_are_not(tmp_path):
    rgba = np.zeros((8, 8, 4), np.uint8)
    rgba[..., :3] = 200
    rgba[2:6, 2:6, 3] = 255  # the object
    rgba[0, 0, 3] = 1  # faint: not known to be empty
    write_dataset(tmp_path, n=6, rgba=rgba)
    view = DatasetSource.from_path(tmp_path).candidate_view(0)
    expect = rgba[..., 3] == 0
    assert np.array_equal(view.empty, expect)
    assert not view.mask.any()  # no depth maps: no distance is known
    # Downscaled by 2, a pixel is empty only where all four it averages are.
    half = DatasetSource.from_path(tmp_path, downscale=2).candidate_view(0)
    assert np.array_equal(half.empty, expect.reshape(4, 2, 4, 2).all(axis=(1, 3)))
    # The composite's colour is what the empty pixels show.
    assert view.background == (1.0, 1.0, 1.0) and np.allclose(view.rgb[expect], 1.0)
    black = DatasetSource.from_path(tmp_path, white_background=False).candidate_view(0)
    assert black.background == (0.0, 0.0, 0.0) and np.allclose(black.rgb[expect], 0.0)


def test_an_image_without_alpha_knows_no_empty_pixel(tmp_path):
    write_dataset(tmp_path, n=6)
    view = DatasetSource.from_path(tmp_path).candidate_view(0)
    assert view.empty.shape == (8, 8) and not view.empty.any() and view.background is None


def test_the_empty_ray_loss_clears_a_datasets_transparent_rays(tmp_path):
    """Trained on RGBA views, the empty-ray loss leaves less opacity on the transparent rays."""
    from mitsuba_active.run import RunConfig, make_ensemble, train_on

    rgba = np.zeros((16, 16, 4), np.uint8)
    rgba[..., :3] = 255
    rgba[5:11, 5:11] = (40, 90, 160, 255)
    write_dataset(tmp_path, n=8, size=(16, 16), rgba=rgba)
    src = DatasetSource.from_path(tmp_path)
    views = [src.candidate_view(i) for i in range(len(src.candidates))]
    empty = np.concatenate([v.empty.ravel() for v in views])
    opacity = []
    for weight in (0.0, 1.0):
        cfg = RunConfig(field_preset="fast", field={"empty_weight": weight, "lr": 0.1})
        ens = make_ensemble(src, cfg, 1, seed=0, planner=False)
        train_on(ens, views, 0)  # the background starts at the composite's white
        away = ens.render(np.float32([[0, 0, 50]]), np.float32([[0, 0, 1]]))["rgb"][0, 0]
        assert np.allclose(away, 0.98, atol=0.01), away
        train_on(ens, views, 150)
        o = np.concatenate([camera_rays(v.camera)[0] for v in views])
        d = np.concatenate([camera_rays(v.camera)[1] for v in views])
        opacity.append(ens.render(o, d)["opacity"][0][empty].mean())
    assert opacity[1] < 0.5 * opacity[0], opacity


def test_a_run_refuses_the_distance_loss_on_a_dataset_without_depth_maps(mic, mic_dir, tmp_path):
    """Its loss would be zero on every ray while run.json recorded the weight."""
    from mitsuba_active.run import Run, RunConfig

    cfg = RunConfig(scene=str(mic_dir), downscale=32, candidates=100, heldout=25, budget=3, distance_weight=1.0)
    with pytest.raises(UserError, match="needs distances, and nerf_synthetic_mic has no depth maps"):
        Run(mic, cfg, tmp_path / "refused", progress=False)
    assert not (tmp_path / "refused").exists()


def test_a_run_refuses_a_dataset_its_config_does_not_describe(mic, mic_dir, tmp_path):
    """run.json records the config as how the run was made: a dataset opened
    with other settings (image size, frames kept) or another dataset is refused,
    before anything is written; cfg.open_source() is accepted."""
    from mitsuba_active.run import Run, RunConfig

    cfg = RunConfig(scene=str(mic_dir), downscale=32, candidates=100, heldout=25, budget=3)
    Run(mic, cfg, tmp_path / "ok", progress=False)
    write_dataset(tmp_path / "other", n=6, size=(64, 64))
    for change, unlike in ((dict(downscale=16), "images of 50x50 pixels (the source's: 25x25)"),
                           (dict(candidates=10), "candidates=10: 10 frames (the source's: 100)"),
                           (dict(heldout=3), "heldout=3: 3 frames (the source's: 25)"),
                           (dict(scene=str(tmp_path / "other")), "the source's: the dataset 'nerf_synthetic_mic'")):
        with pytest.raises(UserError, match=re.escape(unlike)):
            Run(mic, dataclasses.replace(cfg, **change), tmp_path / "refused", progress=False)
    with pytest.raises(UserError, match="unknown field option nsamples"):
        Run(mic, dataclasses.replace(cfg, field={"nsamples": 3}), tmp_path / "refused", progress=False)
    assert not (tmp_path / "refused").exists()
    with pytest.raises(UserError, match="no scene given"):
        RunConfig().open_source()
    for options, message in ((dict(n_candidates=0), "at least one candidate view"),
                             (dict(n_heldout=2.5), "n_heldout must be a whole number"),
                             (dict(downscale=float("nan")), "downscale must be a positive integer, got nan"),
                             (dict(downscale=None, resolution=0), "resolution must be a positive whole number"),
                             (dict(downscale=None, resolution=-5), "resolution must be a positive whole number"),
                             (dict(white_background="false"), "white_background must be True or False, got 'false'")):
        with pytest.raises(UserError, match=message):
            DatasetSource.from_path(mic_dir, **{"downscale": 32, **options})
    with pytest.raises(UserError, match="resolution must be a positive whole number, got 0"):
        RunConfig(scene=str(mic_dir), resolution=0).open_source()


# -- errors -------------------------------------------------------------------------

def _bad_json(root):
    write_dataset(root, n=3)
    (root / "transforms.json").write_text("{ not json")


def _no_frames(root):
    write_dataset(root, n=3, extra={"frames": []})


def _no_focal(root):
    write_dataset(root, n=3, form="blender")
    for split in ("train", "test"):
        p = root / f"transforms_{split}.json"
        meta = json.loads(p.read_text())
        del meta["camera_angle_x"]
        p.write_text(json.dumps(meta))


def _all_missing(root):
    write_dataset(root, n=3, missing=(0, 1, 2))


def _bad_matrix(root):
    write_dataset(root, n=3, frame_extra={1: {"transform_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}})


def _panorama(root):
    write_dataset(root, n=3, extra={"camera_model": "EQUIRECTANGULAR"})


def _wordy_focal(root):
    write_dataset(root, n=3, extra={"camera_angle_x": "wide"})


def _flat_focal(root):
    write_dataset(root, n=3, form="blender", extra={"camera_angle_x": 0})


def _bad_aabb(root):
    write_dataset(root, n=3, extra={"aabb": [1, 2, 3]})


def _no_test_frames(root):
    write_dataset(root, n=4, frame_extra={k: {"split": "train"} for k in range(4)})


def _nerfstudio_train_only(root):
    write_dataset(root, n=4, extra={"train_filenames": ["images/f_000.png", "images/f_001.png"]})


def _wordy_width(root):
    write_dataset(root, n=3, extra={"w": "abc"})


def _wordy_depth_scale(root):
    write_dataset(root, n=3, extra={"depth_unit_scale_factor": "mm"},
                  frame_extra={1: {"depth_file_path": "images/f_000.png"}})


def _numbered_depth_path(root):
    write_dataset(root, n=3, frame_extra={1: {"depth_file_path": 5}})


def _numbered_train_names(root):
    write_dataset(root, n=3, extra={"train_filenames": 5, "test_filenames": ["images/f_000.png"]})


def _latin1_json(root):
    write_dataset(root, n=3)
    p = root / "transforms.json"
    p.write_bytes(p.read_bytes().replace(b'"frames"', '"caf\u00e9": 1, "frames"'.encode("latin-1")))


def _damaged_exr_image(root):
    write_dataset(root, n=3, form="blender")  # no w and h: the image's size is read from its header
    for k in range(3):
        (root / "images" / f"f_{k:03d}.png").unlink()
        (root / "images" / f"f_{k:03d}.exr").write_bytes(b"not an exr")


def _third_frame_without_path(root):
    write_dataset(root, n=5, frame_extra={3: {"file_path": None}})


def _deep_json(root):
    write_dataset(root, n=3)
    (root / "transforms.json").write_text('{"frames": ' + "[" * 100_000 + "]" * 100_000 + "}")


def _numbered_file_path(root):
    write_dataset(root, n=5, frame_extra={2: {"file_path": 5}})


@pytest.mark.parametrize("make,message", [
    (_bad_json, "not valid JSON"), (_deep_json, "nested too deeply to read"),
    (_numbered_file_path, "frame 2's file_path must be a file name, got 5"), (_no_frames, "no frames"), (_no_focal, "camera_angle_x or fl_x"),
    (_all_missing, "none of the dataset's image files"), (_bad_matrix, "must be 4x4"),
    (_panorama, "camera_model EQUIRECTANGULAR \\(a panorama\\) is not supported"), (_bad_aabb, "aabb"),
    (_wordy_focal, "camera_angle_x must be a number"), (_flat_focal, "camera_angle_x must be in \\(0, pi\\) radians, got 0"),
    (_no_test_frames, "no held-out frames"), (_nerfstudio_train_only, "no held-out frames"),
    (_wordy_width, "w must be a whole number of pixels, got 'abc'"),
    (_wordy_depth_scale, "depth_unit_scale_factor must be a positive number, got 'mm'"),
    (_numbered_depth_path, "depth_file_path must be a file name, got 5"),
    (_numbered_train_names, "'train_filenames' must be a list of file names, got 5"),
    (_latin1_json, "not valid JSON \\(not UTF-8 text\\)"), (_damaged_exr_image, r"cannot read image .*f_00\d.exr"),
    (_third_frame_without_path, "frame 3 has no 'file_path'"),  # its place among the file's frames
])
def test_malformed_datasets_fail_with_one_line(tmp_path, make, message):
    make(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(UserError, match=message) as err:
            DatasetSource.from_path(tmp_path)
    assert "\n" not in str(err.value)


# -- open_source ----------------------------------------------------------------------

def test_open_source_dispatches_on_the_path(tmp_path, mic_dir, sphere_xml):
    src = open_source(mic_dir, n_candidates=10, n_heldout=4, resolution=25)
    assert isinstance(src, DatasetSource)
    assert len(src.candidates) == 10 and len(src.heldout) == 4 and src.candidates[0].width == 25
    scene = open_source(sphere_xml, n_candidates=4, n_heldout=2, resolution=8, spp=1, cache_dir=False)
    assert isinstance(scene, SceneSource) and len(scene.candidates) == 4
    with pytest.raises(UserError, match="no such"):
        open_source(tmp_path / "nope.xml")
    (tmp_path / "scene.obj").write_text("")
    with pytest.raises(UserError, match="expected a Mitsuba scene"):
        open_source(tmp_path / "scene.obj")
    with pytest.raises(UserError, match="neither"):
        open_source(tmp_path)
    with pytest.raises(UserError, match="rig"):
        open_source(mic_dir, rig="sphere")


def test_lone_train_file_holds_out_every_8th_frame(tmp_path):
    path = write_dataset(tmp_path, n=12, form="blender")
    (tmp_path / "transforms_test.json").unlink()
    src = DatasetSource.from_path(path)
    assert len(src.candidates) == 8 and len(src.heldout) == 2  # 10 train frames: 0 and 8 held out


def test_image_size_that_contradicts_the_json_is_refused(tmp_path):
    write_dataset(tmp_path, n=3, size=(8, 8), extra={"w": 10, "h": 8, "cx": 5.0})
    src = DatasetSource.from_path(tmp_path)
    with pytest.raises(UserError, match="the dataset says 10x8"):
        src.candidate_view(0)


def test_distance_maps_of_our_own_export_are_read_as_distances(tmp_path):
    from mitsuba_active.imageio_utils import write_exr

    dist = np.full((8, 8), 2.5, np.float32)
    dist[0] = 0.0  # nothing hit
    write_exr(tmp_path / "distance" / "d.exr", {"RGB": np.zeros((8, 8, 3), np.float32), "Z": dist})
    write_dataset(tmp_path, n=3, frame_extra={0: {"distance_file_path": "distance/d.exr"}})
    v = DatasetSource.from_path(tmp_path).heldout_view(0)
    assert np.array_equal(v.distance, dist) and np.array_equal(v.mask, dist > 0)


def test_a_run_of_a_dataset_without_depth_exports_no_distances(tmp_path, mic_dir, monkeypatch):
    """mic has no depth maps: its views carry no Z channel of zeros (which
    would read as "nothing hit"), and the export names no distance files.
    The run folder belongs to the dataset, by whichever path it is named."""
    import os

    from mitsuba_active.export import export_transforms
    from mitsuba_active.imageio_utils import read_exr
    from mitsuba_active.run import Run, RunConfig

    src = open_source(mic_dir, n_candidates=6, n_heldout=2, resolution=25)
    assert not src.has_distance
    cfg = RunConfig(scene=str(mic_dir), planner="even", budget=3, initial_views=1, resolution=25, candidates=6,
                    heldout=2, eval_views=[3], eval_steps=5, initial_steps=5, steps_per_view=5)
    rec = Run(src, cfg, tmp_path / "run", progress=False, log=lambda m: None).execute()
    assert rec["distances"] is False
    assert set(read_exr(tmp_path / "run" / "views" / "view_000.exr")) == {"RGB"}
    meta = json.loads(export_transforms(tmp_path / "run", tmp_path / "export").read_text())
    assert len(meta["frames"]) == 3 + 2 and not any("distance_file_path" in f for f in meta["frames"])
    assert "distance_note" not in meta and not (tmp_path / "export" / "distance").exists()
    # The held-out frames are the dataset's test frames; every mask is the image's alpha.
    held = meta["frames"][3:]
    assert [f["source_file_path"] for f in held] == rec["heldout_files"]
    for frame, view in zip(meta["frames"], [src.candidate_view(i) for i in rec["captured"]]
                           + [src.heldout_view(i) for i in range(2)]):
        image = iio.imread(tmp_path / "export" / frame["file_path"]) / 255
        assert np.abs(image - view.rgb).max() <= 1 / 255
        assert np.array_equal(iio.imread(tmp_path / "export" / frame["mask_path"]) > 127, ~view.known_empty)
        assert "source_camera" not in frame  # mic's images are pinholes: nothing was undistorted
    # Which of the dataset's frames each view is: the file the dataset's JSON gives that pose.
    poses = {str(mic_dir / (f["file_path"] + ".png")): np.asarray(f["transform_matrix"])
             for f in json.loads((mic_dir / "transforms_train.json").read_text())["frames"]}
    assert len(rec["candidate_files"]) == 6 and len(rec["heldout_files"]) == 2
    for frame, index in zip(meta["frames"], rec["captured"]):
        assert frame["source_file_path"] == rec["candidate_files"][index]
        assert np.allclose(poses[str(mic_dir / frame["source_file_path"])], frame["transform_matrix"], atol=1e-5)
    monkeypatch.chdir(tmp_path)
    train_json = os.path.relpath(mic_dir / "transforms_train.json", tmp_path)
    again = Run(open_source(train_json, n_candidates=6, n_heldout=2, resolution=25),
                RunConfig(**{**cfg.__dict__, "scene": train_json}), tmp_path / "run", progress=False,
                log=lambda m: None).execute()
    assert again["finished"] and again["captured"] == rec["captured"]
    # A record from before datasets had a digest is matched by its path, as then.
    path = tmp_path / "run" / "run.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "content_hash": None}))
    old = Run(open_source(mic_dir, n_candidates=6, n_heldout=2, resolution=25), cfg, tmp_path / "run",
              progress=False, log=lambda m: None).execute()
    assert old["finished"] and old["captured"] == rec["captured"]


def test_a_views_arrays_are_the_callers_own(mic):
    """Editing a view in place (an augmentation) changes no later view of the same frame."""
    view = mic.candidate_view(0)
    original = view.rgb.copy()
    view.rgb[:] = 0
    view.distance[:] = 1
    view.mask[:] = True
    again = mic.candidate_view(0)
    np.testing.assert_array_equal(again.rgb, original)
    assert again.rgb.max() > 0 and not again.mask.all()
