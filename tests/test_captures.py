"""Real captures: lens distortion, per-frame intrinsics, image files, the view cache, COLMAP projects."""

import json
import math
import subprocess
import sys

import cv2
import imageio.v3 as iio
import numpy as np
import pytest

from mitsuba_active.cameras import MITSUBA_TO_OPENCV, camera_rays
from mitsuba_active.colmap import BOUNDS_PERCENTILES
from mitsuba_active.datasets import DatasetSource, area_downscale, mitsuba_to_opengl, open_source
from mitsuba_active.errors import UserError
from mitsuba_active.images import read_linear_rgb, read_rgb
from mitsuba_active.imageio_utils import linear_to_srgb, srgb_to_linear
from mitsuba_active.lens import capture_through

from .conftest import tiny_source
from .test_datasets import write_dataset

SIZE = 96
RADTAN = {"k1": -0.6, "k2": 0.3, "p1": 0.01, "p2": -0.008}
FISHEYE = {"k1": -0.4, "k2": 0.1, "k3": -0.02, "k4": 0.004}


@pytest.fixture(scope="module")
def renders(spot_xml):
    """Clean renders of spot: (views, focal length in pixels)."""
    src = tiny_source(spot_xml, n_candidates=6, n_heldout=2, resolution=SIZE, spp=64)
    views = [src.candidate_view(i) for i in range(6)] + [src.heldout_view(i) for i in range(2)]
    return views, float(views[0].camera.intrinsics()[0, 0])




def psnr(a, b):
    return -10 * math.log10(float(np.mean((a - b) ** 2)))


def write_capture(root, views, f, model, coeffs, per_frame):
    """A transforms.json of the renders distorted by ``coeffs`` (given at the top level or per frame)."""
    (root / "images").mkdir(parents=True)
    frames = []
    for n, v in enumerate(views):
        name = f"images/{n:03d}.png"
        image = np.clip(capture_through(v.rgb, f, model, coeffs), 0, 1)
        iio.imwrite(root / name, np.round(image * 255).astype(np.uint8))
        frame = {"file_path": name, "transform_matrix": mitsuba_to_opengl(v.camera.to_world).tolist(),
                 "split": "test" if n >= 6 else "train"}
        frames.append({**frame, **(coeffs if per_frame else {}), "camera_model": model} if per_frame else frame)
    meta = {"fl_x": f, "fl_y": f, "cx": SIZE / 2, "cy": SIZE / 2, "w": SIZE, "h": SIZE, "frames": frames}
    if not per_frame:
        meta.update(coeffs, camera_model=model)
    (root / "transforms.json").write_text(json.dumps(meta))


@pytest.mark.parametrize("model,coeffs,per_frame", [("OPENCV", RADTAN, False), ("OPENCV", RADTAN, True),
                                                    ("OPENCV_FISHEYE", FISHEYE, False),
                                                    ("OPENCV_FISHEYE", FISHEYE, True)])
def test_a_distorted_capture_is_seen_along_its_lenss_rays(tmp_path, renders, model, coeffs, per_frame):
    """The images stay as captured, whole; each camera carries the lens, whose rays followed into
    the clean render find the colours the captured pixels show."""
    views, f = renders
    write_capture(tmp_path, views, f, model, coeffs, per_frame)
    src = DatasetSource.from_path(tmp_path)
    frames = src.candidate_frames + src.heldout_frames
    assert all(fr.lens is not None and fr.lens.model == model and fr.camera.lens.model == model for fr in frames)
    gains = []
    for fr, clean in zip(frames, views):
        assert fr.crop == (0, 0, SIZE, SIZE) and np.allclose(fr.camera.to_world, clean.camera.to_world)
        got = src._view(fr).rgb
        assert np.allclose(got, iio.imread(fr.image) / 255.0, atol=1e-6)
        local = camera_rays(fr.camera)[1].astype(np.float64) @ fr.camera.to_world[:3, :3]
        x, y = -local[:, 0] / local[:, 2], -local[:, 1] / local[:, 2]  # OpenCV's frame
        grid = [(SIZE / 2 + f * t - 0.5).reshape(SIZE, SIZE).astype(np.float32) for t in (x, y)]
        seen = cv2.remap(clean.rgb, *grid, cv2.INTER_LINEAR)
        hit = clean.mask  # the object: the background is alike everywhere
        good, naive = psnr(seen[hit], got[hit]), psnr(clean.rgb[hit], got[hit])
        assert good > 26.0 and good > naive + 1.0, (good, naive)
        gains.append(good - naive)
    assert np.mean(gains) > 3.0, gains


def test_per_frame_size_focal_and_principal_point(tmp_path):
    """Frames of their own sizes and lenses share the smallest centred window; each keeps its focal length."""
    extra = {0: {"w": 12, "h": 10, "fl_x": 8.0, "fl_y": 8.0, "cx": 6.0, "cy": 5.0},
             1: {"fl_x": 12.0, "fl_y": 12.0}, 2: {"cx": 9.0, "cy": 8.0}}
    write_dataset(tmp_path, n=4, size=(16, 16), frame_extra=extra)
    iio.imwrite(tmp_path / "images" / "f_000.png", np.zeros((10, 12, 3), np.uint8))
    src = DatasetSource.from_path(tmp_path)
    frames = {fr.image.name: fr for fr in src.candidate_frames + src.heldout_frames}
    assert {(f.camera.width, f.camera.height) for f in frames.values()} == {(12, 10)}
    assert frames["f_000.png"].crop == (0, 0, 12, 10)
    assert frames["f_002.png"].crop == (3, 3, 12, 10)  # centred on (9, 8)
    for name, fl in (("f_000.png", 8.0), ("f_001.png", 12.0), ("f_003.png", 10.0)):
        assert frames[name].camera.fov == pytest.approx(math.degrees(2 * math.atan(6 / fl)))
    assert src.candidate_view(0).rgb.shape == (10, 12, 3)


def test_non_square_pixels_keep_their_pixels_and_bend_the_rays(tmp_path):
    """fl_y unlike fl_x: the image stays as captured; its rows' rays climb by 1 / fl_y per pixel."""
    img = np.zeros((32, 32, 3), np.uint8)
    img[:, :, 1] = (np.arange(32) * 8)[:, None]  # green encodes the row
    write_dataset(tmp_path, n=3, size=(32, 32), rgba=img, extra={"fl_x": 20.0, "fl_y": 10.0, "cy": 15.0})
    src = DatasetSource.from_path(tmp_path, downscale=2)
    cam = src.heldout[0]
    assert src.heldout_frames[0].crop == (0, 0, 32, 32) and (cam.width, cam.height) == (16, 16)
    assert (cam.lens.fx, cam.lens.fy, cam.lens.cx, cam.lens.cy) == (10.0, 5.0, 8.0, 7.5)
    v = src.heldout_view(0).rgb
    lin = srgb_to_linear(np.arange(32) * 8 / 255.0).reshape(16, 2).mean(axis=1)  # 2x2 blocks, linear light
    assert np.allclose(v[:, 8, 1], linear_to_srgb(lin), atol=2e-3)
    local = camera_rays(cam)[1].astype(np.float64).reshape(16, 16, 3)[:, 8] @ cam.to_world[:3, :3]
    rows = (np.arange(16) + 0.5) * 2  # each block's centre, in the image's pixels
    assert np.allclose(-local[:, 1] / local[:, 2], (rows - 15.0) / 10.0, atol=1e-5)


def test_aabb_scale_gives_instant_ngps_box_and_a_contraction(tmp_path):
    write_dataset(tmp_path, n=4, extra={"aabb_scale": 1})
    src = DatasetSource.from_path(tmp_path)
    assert np.allclose(src.bbox_min, -0.5 / 0.33) and np.allclose(src.bbox_max, 0.5 / 0.33)
    write_dataset(tmp_path / "b", n=4, extra={"aabb_scale": 16, "scale": 0.5, "offset": [0.5, 0.5, 0.5]})
    src = DatasetSource.from_path(tmp_path / "b")
    assert np.allclose(src.bbox_max, 1.0) and src.suggested_contraction() == 16.0
    assert src.field_options() == {"background_resolution": 16}
    write_dataset(tmp_path / "c", n=4, extra={"aabb_scale": 16, "aabb": [[-1, -1, -1], [2, 2, 2]]})
    assert np.allclose(DatasetSource.from_path(tmp_path / "c").bbox_max, 2.0)  # the aabb wins


# -- image files --------------------------------------------------------------------

def test_jpeg_16_bit_png_and_exif_orientation(tmp_path):
    from PIL import Image, ImageOps

    rng = np.random.default_rng(1)
    write_dataset(tmp_path, n=3, form="blender", size=(6, 4))
    deep = (rng.random((4, 6, 3)) * 65535).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "images" / "f_000.png"), deep[..., ::-1])
    rgb = DatasetSource.from_path(tmp_path / "transforms_train.json").candidate_view(0).rgb
    assert np.allclose(rgb, deep / 65535, atol=1e-6)  # all 16 bits, not Pillow's 8
    # A phone's JPEG: stored sideways (4 wide, 6 high) with EXIF orientation 6.
    stored = (rng.random((6, 4, 3)) * 255).astype(np.uint8)
    exif = Image.Exif()
    exif[0x0112] = 6
    (tmp_path / "images" / "f_000.png").unlink()
    Image.fromarray(stored).save(tmp_path / "images" / "f_000.jpg", exif=exif, quality=100)
    upright = np.asarray(ImageOps.exif_transpose(Image.open(tmp_path / "images" / "f_000.jpg"))) / 255.0
    assert upright.shape == (4, 6, 3)
    rgb = DatasetSource.from_path(tmp_path / "transforms_train.json").candidate_view(0).rgb
    assert np.allclose(rgb, upright, atol=1e-6)


@pytest.mark.parametrize("orientation", [2, 3, 4, 5, 7, 8])
def test_every_exif_orientation_turns_upright_as_pillow_does(tmp_path, orientation):
    from PIL import Image, ImageOps

    from mitsuba_active.images import read_rgb

    stored = (np.random.default_rng(orientation).random((6, 4, 3)) * 255).astype(np.uint8)
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(stored).save(tmp_path / "a.png", exif=exif)
    upright = np.asarray(ImageOps.exif_transpose(Image.open(tmp_path / "a.png"))) / 255.0
    rgb, _ = read_rgb(tmp_path / "a.png", True)
    assert np.allclose(rgb, upright, atol=1e-6)


def test_large_images_are_loaded_once_into_the_cache(tmp_path, monkeypatch):
    import mitsuba_active.datasets as datasets

    img = (np.random.default_rng(2).random((800, 800, 3)) * 255).astype(np.uint8)
    write_dataset(tmp_path / "d", n=3, size=(800, 800), rgba=img, extra={"k1": 0.01})
    first = DatasetSource.from_path(tmp_path / "d", downscale=8, cache_dir=tmp_path / "cache").heldout_view(0)
    assert len(list((tmp_path / "cache" / "views").glob("*.npz"))) == 1

    def refuse(*args):
        raise AssertionError("read again")

    monkeypatch.setattr(datasets, "load_view", refuse)
    again = DatasetSource.from_path(tmp_path / "d", downscale=8, cache_dir=tmp_path / "cache").heldout_view(0)
    assert np.array_equal(again.rgb, first.rgb) and np.array_equal(again.empty, first.empty)
    with pytest.raises(AssertionError, match="read again"):  # another factor is another entry
        DatasetSource.from_path(tmp_path / "d", downscale=4, cache_dir=tmp_path / "cache").heldout_view(0)


# -- COLMAP -------------------------------------------------------------------------

def write_colmap(root, views, f, model="PINHOLE", params=None, points=None):
    """A COLMAP text model of the renders' cameras, and their images."""
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (root / "images").mkdir()
    params = params or [f, f, SIZE / 2, SIZE / 2]
    (sparse / "cameras.txt").write_text(f"1 {model} {SIZE} {SIZE} {' '.join(map(str, params))}\n")
    lines = []
    for n, v in enumerate(views):
        c2w = v.camera.to_world @ MITSUBA_TO_OPENCV  # OpenCV axes
        w2c = np.linalg.inv(c2w)
        q = _quaternion(w2c[:3, :3])
        numbers = " ".join(f"{float(x):.17g}" for x in [*q, *w2c[:3, 3]])
        lines += [f"{n + 1} {numbers} 1 v{n:02d}.png", ""]
        iio.imwrite(root / "images" / f"v{n:02d}.png", np.round(v.rgb * 255).astype(np.uint8))
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    pts = "".join(f"{k + 1} {p[0]:.17g} {p[1]:.17g} {p[2]:.17g} 128 128 128 0.5\n" for k, p in enumerate(points))
    (sparse / "points3D.txt").write_text(pts)


def _quaternion(r):
    """(w, x, y, z) of a rotation matrix (COLMAP's order)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(r).as_quat()
    return [w, x, y, z]


def test_a_colmap_text_model_loads_with_the_renders_poses(tmp_path, renders):
    views, f = renders
    rng = np.random.default_rng(3)
    points = np.concatenate([rng.uniform(-0.4, 0.4, (400, 3)), [[50.0, 0, 0], [0, -60.0, 0]]])  # two outliers
    write_colmap(tmp_path / "proj", views, f, points=points)
    src = open_source(tmp_path / "proj", n_candidates=None, n_heldout=2, downscale=1, cache_dir=False)
    assert len(src.candidates) == 6 and len(src.heldout) == 2
    by_name = {fr.image.name: fr for fr in src.candidate_frames + src.heldout_frames}
    for n, v in enumerate(views):
        cam = by_name[f"v{n:02d}.png"].camera
        assert np.allclose(cam.position, v.camera.position, atol=1e-6)
        assert np.allclose(cam.forward, v.camera.forward, atol=1e-6)
        assert np.allclose(cam.to_world[:3, :3], v.camera.to_world[:3, :3], atol=1e-6)
        assert cam.fov == pytest.approx(v.camera.fov, abs=1e-6)
    lo, hi = np.percentile(points, BOUNDS_PERCENTILES, axis=0)
    assert np.allclose(src.bbox_min, lo) and np.allclose(src.bbox_max, hi) and np.all(hi < 1.0)
    assert src.candidate_files[0].startswith("images/v")
    held = [by_name[n].image.name for n in by_name if by_name[n] in src.heldout_frames]
    assert held == ["v02.png", "v06.png"]  # spread evenly over the names
    assert np.allclose(src.heldout_view(0).rgb, np.round(views[2].rgb * 255) / 255, atol=1e-5)


def test_a_colmap_opencv_camera_carries_its_lens(tmp_path, renders):
    views, f = renders
    write_colmap(tmp_path / "proj", views, f, model="OPENCV",
                 params=[f, f, SIZE / 2, SIZE / 2, RADTAN["k1"], RADTAN["k2"], RADTAN["p1"], RADTAN["p2"]],
                 points=np.zeros((0, 3)))
    for n, v in enumerate(views):
        iio.imwrite(tmp_path / "proj" / "images" / f"v{n:02d}.png",
                    np.round(np.clip(capture_through(v.rgb, f, "OPENCV", RADTAN), 0, 1) * 255).astype(np.uint8))
    src = open_source(tmp_path / "proj", n_candidates=None, n_heldout=2, downscale=1, cache_dir=False)
    fr = src.heldout_frames[0]
    lens = fr.camera.lens
    assert fr.crop == (0, 0, SIZE, SIZE) and (lens.fx, lens.fy, lens.cx, lens.cy) == (f, f, SIZE / 2, SIZE / 2)
    assert lens.coeffs == (RADTAN["k1"], RADTAN["k2"], 0.0, 0.0, RADTAN["p1"], RADTAN["p2"])
    assert np.allclose(src.heldout_view(0).rgb, iio.imread(fr.image) / 255.0, atol=1e-6)


def test_a_colmap_binary_model_reads_as_its_text_model(tmp_path, renders):
    import pycolmap

    views, f = renders
    write_colmap(tmp_path / "text", views, f, model="SIMPLE_RADIAL", params=[f, SIZE / 2, SIZE / 2, -0.2],
                 points=np.random.default_rng(0).uniform(-0.4, 0.4, (50, 3)))
    binary = tmp_path / "binary"
    (binary / "sparse" / "0").mkdir(parents=True)
    pycolmap.Reconstruction(str(tmp_path / "text" / "sparse" / "0")).write_binary(str(binary / "sparse" / "0"))
    written = {p.name for p in (binary / "sparse" / "0").iterdir()}
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= written and not any(".txt" in n for n in written)
    (binary / "images").symlink_to(tmp_path / "text" / "images")
    text, binary = (open_source(tmp_path / d, n_candidates=None, n_heldout=2, downscale=1, cache_dir=False)
                    for d in ("text", "binary"))
    assert text.candidate_files == binary.candidate_files and text.heldout_files == binary.heldout_files
    for a, b in zip(text.candidate_frames + text.heldout_frames, binary.candidate_frames + binary.heldout_frames):
        assert np.allclose(a.camera.to_world, b.camera.to_world, atol=1e-9) and a.camera.fov == b.camera.fov
        assert a.lens == b.lens and a.lens.coeffs[0] == -0.2 and a.crop == b.crop
    assert np.allclose(text.bbox_min, binary.bbox_min) and np.allclose(text.bbox_max, binary.bbox_max)
    assert np.array_equal(text.heldout_view(1).rgb, binary.heldout_view(1).rgb)


@pytest.mark.parametrize("model,params,expected", [
    ("SIMPLE_PINHOLE", [70.0, 48.0, 47.0],
     {"camera_model": "PINHOLE", "fl_x": 70.0, "fl_y": 70.0, "cx": 48.0, "cy": 47.0}),
    ("SIMPLE_RADIAL", [70.0, 48.0, 47.0, -0.3],
     {"camera_model": "OPENCV", "fl_x": 70.0, "fl_y": 70.0, "cx": 48.0, "cy": 47.0, "k1": -0.3}),
    ("RADIAL", [70.0, 48.0, 47.0, -0.3, 0.1],
     {"camera_model": "OPENCV", "fl_x": 70.0, "fl_y": 70.0, "cx": 48.0, "cy": 47.0, "k1": -0.3, "k2": 0.1}),
    ("OPENCV_FISHEYE", [70.0, 70.0, 48.0, 47.0, -0.4, 0.1, -0.02, 0.004],
     {"camera_model": "OPENCV_FISHEYE", "fl_x": 70.0, "fl_y": 70.0, "cx": 48.0, "cy": 47.0, "k1": -0.4,
      "k2": 0.1, "k3": -0.02, "k4": 0.004}),
])
def test_colmap_camera_models_give_their_intrinsics_and_lens(tmp_path, renders, model, params, expected):
    from mitsuba_active.colmap import camera_keys

    keys = camera_keys(model, params, SIZE, SIZE, "here")
    assert {k: v for k, v in keys.items() if v is not None} == {**expected, "w": SIZE, "h": SIZE}
    # One project per model: its frames carry that lens (a pinhole's none) and focal length.
    views, f = renders
    write_colmap(tmp_path / "proj", views, f, model=model, params=params, points=np.zeros((0, 3)))
    src = open_source(tmp_path / "proj", n_candidates=None, n_heldout=2, downscale=1, cache_dir=False)
    fr = src.heldout_frames[0]
    coeffs = tuple(expected.get(k, 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
    if model == "SIMPLE_PINHOLE":
        assert fr.lens is None
    else:
        lens_model = "OPENCV_FISHEYE" if model == "OPENCV_FISHEYE" else "OPENCV"
        assert (fr.lens.model, fr.lens.coeffs, fr.lens.fx, fr.lens.cx, fr.lens.cy) == (lens_model, coeffs, 70.0,
                                                                                       48.0, 47.0)
    x0, y0, w, h = fr.crop
    assert fr.camera.fov == pytest.approx(math.degrees(2 * math.atan(w / 2 / 70.0)))
    if model == "SIMPLE_PINHOLE":
        assert (x0 + w / 2, y0 + h / 2) == (48.0, 47.0)  # the window is centred on the principal point
    else:  # the camera carries its principal point: the image stays whole
        assert fr.crop == (0, 0, SIZE, SIZE) and (fr.camera.lens.cx, fr.camera.lens.cy) == (48.0, 47.0)


def test_the_export_of_a_distorted_capture_keeps_its_lens(tmp_path, renders, monkeypatch):
    """The export's images are the views the run used, as captured, with their cameras' lens at the
    exported resolution; each frame keeps the source image and its lens; the export reads back with
    the run's split and the same cameras."""
    from mitsuba_active.export import export_transforms
    from mitsuba_active.run import Run, RunConfig

    monkeypatch.setenv("MITSUBA_ACTIVE_CACHE", str(tmp_path / "cache"))
    views, f = renders
    write_capture(tmp_path / "cap", views, f, "OPENCV", RADTAN, per_frame=False)
    cfg = RunConfig(scene=str(tmp_path / "cap"), planner="even", budget=2, initial_views=1, resolution=24,
                    candidates=6, heldout=2, eval_views=[2], eval_steps=5, initial_steps=5, steps_per_view=5)
    src = cfg.open_source()
    rec = Run(src, cfg, tmp_path / "run", progress=False, log=lambda m: None).execute()
    path = export_transforms(tmp_path / "run", tmp_path / "ds")
    meta = json.loads(path.read_text())
    lens = src.candidates[0].lens
    assert {k: meta[k] for k in RADTAN} == RADTAN and meta["w"] == src.candidates[0].width
    assert (meta["camera_model"], meta["fl_x"], meta["cx"]) == ("OPENCV", lens.fx, lens.cx) and lens.fx == f / 4
    frames = src.candidate_frames
    for frame, fr in zip(meta["frames"], [frames[i] for i in rec["captured"]] + src.heldout_frames):
        lens = frame["source_camera"]
        assert {k: lens[k] for k in RADTAN} == RADTAN and lens["camera_model"] == "OPENCV"
        assert (lens["fl_x"], lens["cx"], lens["w"], lens["h"]) == (f, SIZE / 2, SIZE, SIZE)
        assert tmp_path / "cap" / frame["source_file_path"] == fr.image
        assert "mask_path" not in frame  # the capture's images have no alpha
    back = open_source(tmp_path / "ds", resolution=24, cache_dir=False)
    assert np.allclose([c.to_world for c in back.heldout], [c.to_world for c in src.heldout])
    assert back.heldout[0].fov == pytest.approx(src.heldout[0].fov, abs=1e-6)
    assert back.heldout[0].lens == src.heldout[0].lens
    assert np.abs(back.heldout_view(0).rgb - src.heldout_view(0).rgb).max() <= 1 / 255


def _unsupported_model(root, views, f):
    write_colmap(root, views, f, model="FOV", params=[f, f, SIZE / 2, SIZE / 2, 0.1], points=np.zeros((0, 3)))


def _missing_points(root, views, f):
    write_colmap(root, views, f, points=np.zeros((0, 3)))
    (root / "sparse" / "0" / "points3D.txt").unlink()


def _unknown_camera_model(root, views, f):
    write_dataset(root, n=3, extra={"camera_model": "KANNALA"})


def _fisheye_with_tangential_terms(root, views, f):
    write_dataset(root, n=3, extra={"camera_model": "OPENCV_FISHEYE", "p1": 0.1})


def _wordy_coefficient(root, views, f):
    write_dataset(root, n=3, extra={"k2": "small"})


@pytest.mark.parametrize("make,message", [
    (_unsupported_model, "COLMAP camera model FOV is not supported"),
    (_missing_points, "has no points3D.bin or points3D.txt"),
    (_unknown_camera_model, "camera_model 'KANNALA' is not supported"),
    (_fisheye_with_tangential_terms, "has no tangential terms"),
    (_wordy_coefficient, "k2 must be a number, got 'small'"),
])
def test_bad_captures_are_one_line_and_exit_2(tmp_path, renders, make, message):
    make(tmp_path / "p", *renders)
    with pytest.raises(UserError, match=message) as err:
        open_source(tmp_path / "p", cache_dir=False)
    assert "\n" not in str(err.value)
    run = subprocess.run([sys.executable, "-m", "mitsuba_active", "plan", str(tmp_path / "p"), "--out",
                          str(tmp_path / "out")], capture_output=True, text=True, timeout=300)
    assert run.returncode == 2 and message.split(" is ")[0].split(" must")[0] in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


def test_linear_colour_through_the_table_matches_the_transfer_function(tmp_path, rng):
    """8-bit, 16-bit and grey images go through a table of their levels; the values are those of
    read_rgb then srgb_to_linear. RGBA images (composited first) and EXR keep that path."""
    images = {"a.jpg": (rng.random((6, 8, 3)) * 255).astype(np.uint8),
              "b.png": (rng.random((6, 8, 3)) * 65535).astype(np.uint16),
              "c.png": (rng.random((6, 8)) * 255).astype(np.uint8),
              "d.png": (rng.random((6, 8, 4)) * 255).astype(np.uint8)}
    for name, pixels in images.items():
        path = tmp_path / name
        if pixels.dtype == np.uint16:
            cv2.imwrite(str(path), pixels[..., ::-1])
        else:
            iio.imwrite(path, pixels)
        for white in (True, False):
            lin, alpha = read_linear_rgb(path, white)
            rgb, alpha2 = read_rgb(path, white)
            assert lin.shape == (6, 8, 3) and lin.dtype == np.float32
            assert np.array_equal(lin, srgb_to_linear(rgb)), name
            assert (alpha is None) == (alpha2 is None) == (name != "d.png")


def test_area_downscale_is_the_block_mean(rng):
    for shape in ((48, 40, 3), (48, 40), (48, 40, 4), (48, 40, 5)):
        img = rng.random(shape).astype(np.float32)
        ref = img.astype(np.float64).reshape(6, 8, 5, 8, *shape[2:]).mean(axis=(1, 3))
        out = area_downscale(img, 8)
        assert out.shape == ref.shape and out.dtype == np.float32 and np.allclose(out, ref, atol=1e-6)
        assert area_downscale(img, 1) is img
