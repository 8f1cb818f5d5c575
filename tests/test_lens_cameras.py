"""Cameras that carry their lens: rays through captured pixels, pixels without a ray, datasets trained along them."""

import json

import cv2
import imageio.v3 as iio
import numpy as np
import pytest

from mitsuba_active.cameras import Camera, camera_rays, camera_valid, look_at
from mitsuba_active.datasets import depth_to_distance_factor, mitsuba_to_opengl
from mitsuba_active.errors import UserError
from mitsuba_active.groundtruth import View
from mitsuba_active.lens import FISHEYE, RADTAN, Lens, capture_through, distort
from mitsuba_active.training import score_views, sparse_candidate_rays, view_rays

from .conftest import tiny_source
from .test_bad_input import run_cli

RADTAN_COEFFS = {"k1": -0.6, "k2": 0.3, "p1": 0.01, "p2": -0.008}
FISHEYE_COEFFS = {"k1": -0.4, "k2": 0.1, "k3": -0.02, "k4": 0.004}
LENSES = [(RADTAN, RADTAN_COEFFS), (FISHEYE, FISHEYE_COEFFS)]


def lens_of(model, coeffs, f, size, cx=None, cy=None, fy=None):
    w, h = size
    return Lens(model, f, fy or f, w / 2 if cx is None else cx, h / 2 if cy is None else cy,
                tuple(float(coeffs.get(k, 0.0)) for k in ("k1", "k2", "k3", "k4", "p1", "p2")), (w, h))


def pixels_of(camera):
    """Where each of the camera's rays lands in its image, through its lens: (H*W, 2) pixels."""
    local = camera_rays(camera)[1].astype(np.float64) @ camera.to_world[:3, :3]
    x, y = -local[:, 0] / local[:, 2], -local[:, 1] / local[:, 2]  # OpenCV's frame: x right, y down
    xd, yd = distort(camera.lens, x, y)
    k = camera.intrinsics()
    return np.stack([k[0, 0] * xd + k[0, 2], k[1, 1] * yd + k[1, 2]], axis=1)


@pytest.mark.parametrize("model,coeffs", LENSES)
def test_a_lens_cameras_rays_land_on_their_pixel_centres(model, coeffs):
    lens = lens_of(model, coeffs, 40.0, (40, 30), cx=21.3, cy=14.2, fy=41.0)
    cam = Camera(look_at([1, 2, 3], [0, 0, 0]), 60.0, 40, 30, lens=lens)
    u, v = np.meshgrid(np.arange(40) + 0.5, np.arange(30) + 0.5)
    centres = np.stack([u.ravel(), v.ravel()], axis=1)
    assert camera_valid(cam).all()
    assert np.abs(pixels_of(cam) - centres).max() < 1e-3
    # Not the pinhole's rays: the lens bends them by pixels at the border.
    pinhole = Camera(cam.to_world, 60.0, 40, 30)
    bend = np.degrees(np.arccos(np.clip(np.sum(camera_rays(cam)[1] * camera_rays(pinhole)[1], axis=1), -1, 1)))
    assert bend.max() > 1.0
    # OpenCV's own inverse agrees (its radial-tangential model has no k4, nor has this lens).
    k = cam.intrinsics()
    kc = np.array([[k[0, 0], 0, k[0, 2] - 0.5], [0, k[1, 1], k[1, 2] - 0.5], [0, 0, 1]])
    pts = (centres - 0.5).reshape(-1, 1, 2)
    if model == FISHEYE:
        und = cv2.fisheye.undistortPoints(pts, kc, np.array([coeffs[c] for c in ("k1", "k2", "k3", "k4")]))
    else:
        und = cv2.undistortPoints(pts, kc, np.array([coeffs.get(c, 0.0) for c in ("k1", "k2", "p1", "p2", "k3")]),
                                  criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    local = camera_rays(cam)[1].astype(np.float64) @ cam.to_world[:3, :3]
    assert np.allclose(-local[:, :2] / local[:, 2:], und.reshape(-1, 2), atol=1e-4)
    # The lens goes with the camera: saved and read back, scaled with its images; no pinhole sensor.
    back = Camera.from_dict(json.loads(json.dumps(cam.to_dict())))
    assert back.lens == lens and np.array_equal(camera_rays(back)[1], camera_rays(cam)[1])
    assert "lens" not in pinhole.to_dict()
    half = cam.with_resolution(20, 15)
    assert half.lens.fx == pytest.approx(20.0) and half.lens.cx == pytest.approx(21.3 / 2)
    # A lens without distortion, square pixels and a centred principal point is the pinhole.
    plain = Camera(cam.to_world, 60.0, 40, 30, lens=lens_of(model, {}, pinhole.intrinsics()[0, 0], (40, 30)))
    if model == RADTAN:
        assert np.allclose(camera_rays(plain)[1], camera_rays(pinhole)[1], atol=1e-6)
        assert np.allclose(depth_to_distance_factor(plain), depth_to_distance_factor(pinhole), atol=1e-5)
    with pytest.raises(UserError, match="cannot be rendered by Mitsuba's pinhole sensor"):
        cam.sensor()
    with pytest.raises(UserError, match="lens is for 40x30 images"):
        Camera(cam.to_world, 60.0, 20, 30, lens=lens)
    with pytest.raises(UserError, match="a camera's lens"):
        Camera.from_dict({**cam.to_dict(), "lens": {"model": "KANNALA"}})


def test_pixels_past_the_fold_have_no_ray_and_are_left_out():
    """A strong barrel lens over a wide image folds back at its corners: those pixels have no ray,
    and neither training, the planners' rays nor the scores use them."""
    lens = lens_of(RADTAN, {"k1": -0.6}, 22.0, (24, 24))
    cam = Camera(look_at([0, 0, -3], [0, 0, 0]), 57.2, 24, 24, lens=lens)
    valid = camera_valid(cam)
    assert 0 < (~valid).sum() < valid.sum()
    u, v = np.meshgrid(np.arange(24) + 0.5, np.arange(24) + 0.5)
    centres = np.stack([u.ravel(), v.ravel()], axis=1)
    assert np.abs(pixels_of(cam) - centres)[valid].max() < 1e-3
    r = np.hypot(u.ravel() - 12, v.ravel() - 12)
    assert r[~valid].min() > r[valid].min()  # the corners, not the centre
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0, 1, (24, 24, 3)).astype(np.float32)
    view = View(rgb, np.zeros((24, 24), np.float32), np.zeros((24, 24), bool), cam, np.zeros((24, 24), bool))
    rays = view_rays([view])
    assert len(rays["rgb"]) == valid.sum() and np.array_equal(rays["rgb"], rgb.reshape(-1, 3)[valid])
    _, d = sparse_candidate_rays([cam], 2000, seed=0)
    allowed = {tuple(x) for x in camera_rays(cam)[1][valid]}
    assert all(tuple(x) in allowed for x in d[0])

    class Grey:  # a field that sees grey everywhere
        def predict(self, o, d):
            n = len(o)
            return {"rgb_mean": np.full((n, 3), 0.5, np.float32), "rgb_var": np.zeros((n, 3), np.float32),
                    "distance_mean": np.zeros(n, np.float32), "distance_var": np.zeros(n, np.float32),
                    "opacity": np.zeros(n, np.float32)}

    other = rgb.copy()
    other.reshape(-1, 3)[~valid] = 0.5  # what the pixels without a ray show does not count
    a, _ = score_views(Grey(), [view])
    b, _ = score_views(Grey(), [View(other, view.distance, view.mask, cam, view.known_empty)])
    assert a["psnr"] == pytest.approx(b["psnr"]) and a["psnr_fg"] == pytest.approx(b["psnr_fg"])


@pytest.fixture(scope="module")
def capture(spot_xml, tmp_path_factory):
    """Spot rendered at 32x32 and captured through a radial-tangential lens, as a transforms.json folder."""
    src = tiny_source(spot_xml, n_candidates=6, n_heldout=2, resolution=32, spp=16)
    views = [src.candidate_view(i) for i in range(6)] + [src.heldout_view(i) for i in range(2)]
    f = float(views[0].camera.intrinsics()[0, 0])
    root = tmp_path_factory.mktemp("capture")
    (root / "images").mkdir()
    frames = []
    for n, v in enumerate(views):
        iio.imwrite(root / f"images/{n:03d}.png",
                    np.round(np.clip(capture_through(v.rgb, f, RADTAN, RADTAN_COEFFS), 0, 1) * 255).astype(np.uint8))
        frames.append({"file_path": f"images/{n:03d}.png", "split": "test" if n >= 6 else "train",
                       "transform_matrix": mitsuba_to_opengl(v.camera.to_world).tolist()})
    meta = {"camera_model": RADTAN, **RADTAN_COEFFS, "fl_x": f, "fl_y": f, "cx": 16, "cy": 16, "w": 32, "h": 32,
            "aabb": [src.bbox_min.tolist(), src.bbox_max.tolist()], "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def test_a_distorted_dataset_plans_along_its_rays_and_an_older_record_is_refused(capture, tmp_path):
    root = capture
    args = ("plan", root, "--out", tmp_path / "run", "--budget", "3", "--initial-views", "2", "--eval-steps", "20",
            "--steps-per-view", "5", "--planner", "rfe", "--ensemble", "2", "--rays-per-candidate", "64", "--quiet")
    code, text = run_cli(*args)
    assert code == 0, text
    rec = json.loads((tmp_path / "run" / "run.json").read_text())
    assert all(c["lens"]["model"] == RADTAN for c in rec["candidates"] + rec["heldout"])
    assert np.isfinite(rec["metrics"][-1]["psnr"])
    # A record of the same dataset from when its images were undistorted to pinholes: its cameras are not these.
    old = {**rec, "finished": False, "candidates": [{k: v for k, v in c.items() if k != "lens"}
                                                    for c in rec["candidates"]]}
    (tmp_path / "run" / "run.json").write_text(json.dumps(old))
    code, text = run_cli(*args)
    lines = [ln for ln in text.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and "cameras are not the view source's" in lines[0], text
