"""Field quality from a distorted capture against the same capture without distortion.

Renders a mesh's views (``--mesh``, default ``spot.obj``, ``--res`` 128x128)
from the sphere rig, distorts them with a known lens (OpenCV's own model:
radial-tangential ``k1=-0.6 k2=0.3 p1=0.01 p2=-0.008`` and equidistant
fisheye ``k1=-0.4 k2=0.1 k3=-0.02 k4=0.004``, the test suite's), and writes
each set as a transforms.json dataset (8-bit PNG), with an undistorted set
as the reference. Each dataset is read back as a run reads it (the images
as captured, the cameras' rays following the lens; pixels without a ray
left out) and trains the same field (``--preset``, ``--steps``, ``--seed``);
every field is scored on the same clean held-out renders (PSNR, dB, and
SSIM). For comparison, each distorted set also trains through the route
datasets took before (``undistort_*``): images resampled to a pinhole of the
same focal length and cropped to the window that sees captured pixels;
reported with that window (fraction of the image's width) and the PSNR of
the undistorted training images against the clean renders in it.

Usage::

    PYTHONPATH=. python benchmarks/distortion_quality.py [--steps 1500] [--res 128]
        [--out benchmarks/results/distortion_quality.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from functools import lru_cache
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mitsuba_active  # noqa: E402,F401
import cv2  # noqa: E402
import imageio.v3 as iio  # noqa: E402
import numpy as np  # noqa: E402

from mitsuba_active.cameras import Camera, camera_rays, camera_valid  # noqa: E402
from mitsuba_active.datasets import DatasetSource, mitsuba_to_opengl  # noqa: E402
from mitsuba_active.env import SceneSource  # noqa: E402
from mitsuba_active.field import Ensemble, FieldConfig  # noqa: E402
from mitsuba_active.field.config import FIELD_PRESETS  # noqa: E402
from mitsuba_active.groundtruth import View  # noqa: E402
from mitsuba_active.imageio_utils import linear_to_srgb, srgb_to_linear  # noqa: E402
from mitsuba_active.lens import Lens, fold_radius, capture_through, distort  # noqa: E402
from mitsuba_active.training import score_views, train_on  # noqa: E402
from mitsuba_active.scene import scene_from_mesh  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MESH = str(ROOT.parent / "shared/data/meshes/spot.obj")
#: The lenses the views are distorted with: (camera_model, coefficients).
LENSES = {"none": ("OPENCV", {}),
          "radtan": ("OPENCV", {"k1": -0.6, "k2": 0.3, "p1": 0.01, "p2": -0.008}),
          "fisheye": ("OPENCV_FISHEYE", {"k1": -0.4, "k2": 0.1, "k3": -0.02, "k4": 0.004})}




def write_dataset(root: Path, train, test, bbox, model: str, coeffs: dict) -> None:
    """A transforms.json of the views distorted by the lens (the held-out frames only make the split)."""
    (root / "images").mkdir(parents=True)
    cam = train[0].camera
    f = float(cam.intrinsics()[0, 0])
    frames = []
    for n, v in enumerate(train + test):
        name = f"images/{n:03d}.png"
        image = np.clip(capture_through(v.rgb, f, model, coeffs), 0, 1)
        iio.imwrite(root / name, np.round(image * 255).astype(np.uint8))
        frames.append({"file_path": name, "transform_matrix": mitsuba_to_opengl(v.camera.to_world).tolist(),
                       "split": "train" if n < len(train) else "test"})
    meta = {"camera_model": model, "fl_x": f, "fl_y": f, "cx": cam.width / 2, "cy": cam.height / 2,
            "w": cam.width, "h": cam.height, **coeffs, "aabb": [list(map(float, b)) for b in bbox], "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))


# -- the undistortion route, as datasets took it before their cameras carried the lens ----------

@lru_cache(maxsize=4)
def undistort_maps(lens: Lens) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each pixel of the undistorted image lies in the captured one.

    The undistorted image is a pinhole with focal length ``fx`` in both axes,
    principal point ``(cx, cy)`` and the captured image's size. Returns
    ``(map_x, map_y, valid)``: (H, W) float32 pixel coordinates (pixel
    centres at +0.5 are OpenCV's integers) and an (H, W) bool mask of the
    pixels that see the captured image (inside it, before any fold).
    """
    w, h = lens.size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64) + 0.5, np.arange(h, dtype=np.float64) + 0.5)
    x, y = (u - lens.cx) / lens.fx, (v - lens.cy) / lens.fx
    xd, yd = distort(lens, x, y)
    # Captured pixel coordinates, with OpenCV's integer pixel centres.
    map_x, map_y = xd * lens.fx + lens.cx - 0.5, yd * lens.fy + lens.cy - 0.5
    inside = (map_x >= -0.5) & (map_x <= w - 0.5) & (map_y >= -0.5) & (map_y <= h - 0.5)
    valid = inside & (np.hypot(x, y) < fold_radius(lens, float(np.hypot(x, y).max()) * 1.01))
    return map_x.astype(np.float32), map_y.astype(np.float32), valid


def valid_scale(lens: Lens) -> float:
    """Largest ``s`` in (0, 1] such that the window of ``s`` times the image's half size
    on each side of ``(cx, cy)`` sees only captured pixels (0 when none does)."""
    w, h = lens.size
    _, _, valid = undistort_maps(lens)
    if valid.all():
        return 1.0
    rows, cols = np.nonzero(~valid)
    # A window of scale s holds a pixel when both its offsets lie within s half sizes.
    t = np.maximum(np.abs(cols + 0.5 - lens.cx) / (0.5 * w), np.abs(rows + 0.5 - lens.cy) / (0.5 * h))
    return float(min(t.min(), 1.0))


def remap(lens: Lens, img: np.ndarray, nearest: bool = False) -> np.ndarray:
    """The undistorted image of (H, W) or (H, W, C) float32 ``img`` (bilinear, or ``nearest``); pixels that
    see nothing captured repeat the edge (:func:`valid_scale` keeps them out of the views)."""
    map_x, map_y, _ = undistort_maps(lens)
    flags = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    out = cv2.remap(np.ascontiguousarray(img, dtype=np.float32), map_x, map_y, flags,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(img.shape)


def undistorted_views(src: DatasetSource) -> tuple[list, tuple]:
    """The candidate views of ``src`` as datasets read them before their cameras carried the lens:
    each image resampled (bilinear, linear light) to a pinhole of focal length ``fx`` and cropped to
    the centred window that sees captured pixels only. Returns the views and the window."""
    views = []
    for frame in src.candidate_frames:
        lens = frame.lens
        w, h = lens.size
        s = valid_scale(lens)  # the window as datasets.py cut it: centred, to half a pixel
        wc, hc = int(2 * (np.floor(s * w) / 2)), int(2 * (np.floor(s * h) / 2))
        x0, y0 = int(round(lens.cx - wc / 2)), int(round(lens.cy - hc / 2))
        rgb = np.asarray(iio.imread(frame.image), np.float32)[..., :3] / 255
        rgb = linear_to_srgb(remap(lens, srgb_to_linear(rgb))[y0:y0 + hc, x0:x0 + wc])
        cam = Camera(frame.camera.to_world, np.degrees(2 * np.arctan(0.5 * wc / lens.fx)), wc, hc)
        views.append(View(rgb.astype(np.float32), np.zeros((hc, wc), np.float32), np.zeros((hc, wc), bool), cam,
                          np.zeros((hc, wc), bool), None))
    return views, (x0, y0, wc, hc)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10 * np.log10(np.mean((a - b) ** 2)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default=MESH)
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--train-views", type=int, default=24)
    ap.add_argument("--test-views", type=int, default=8)
    ap.add_argument("--preset", choices=list(FIELD_PRESETS), default="default")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="benchmarks/results/distortion_quality.json")
    args = ap.parse_args(argv)

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        xml = scene_from_mesh(args.mesh, tmp / "scene.xml")
        scene = SceneSource.from_xml(xml, n_candidates=args.train_views, n_heldout=args.test_views,
                                     resolution=args.res, spp=args.spp, cache_dir=False)
        t0 = time.perf_counter()
        train = [scene.candidate_view(i) for i in range(len(scene.candidates))]
        test = [scene.heldout_view(i) for i in range(len(scene.heldout))]
        render_s = time.perf_counter() - t0
        bbox = (scene.bbox_min, scene.bbox_max)
        # One field configuration for every lens: the clean images' width sets it.
        config = FieldConfig(**FIELD_PRESETS[args.preset].config_options(args.res, False))
        results = {}
        for name, (model, coeffs) in LENSES.items():
            write_dataset(tmp / name, train, test, bbox, model, coeffs)
            src = DatasetSource.from_path(tmp / name, downscale=1, cache_dir=False)
            views = [src.candidate_view(i) for i in range(len(src.candidates))]
            t0 = time.perf_counter()
            for c in src.candidates:
                camera_rays(c)
            valid = np.concatenate([camera_valid(c) for c in src.candidates])
            rays_s = time.perf_counter() - t0
            field_ = Ensemble(*bbox, n_members=1, config=config, seed=args.seed)
            t0 = time.perf_counter()
            train_on(field_, views, args.steps)
            train_s = time.perf_counter() - t0
            scores, _ = score_views(field_, test)
            results[name] = {"camera_model": model, "coeffs": coeffs, "psnr": scores["psnr"], "ssim": scores["ssim"],
                             "invalid_fraction": float(1 - valid.mean()), "train_seconds": round(train_s, 1),
                             "rays_seconds": round(rays_s, 2)}
            print(f"{name:8s} dataset route (the lens's rays): field PSNR {scores['psnr']:6.2f} dB  SSIM "
                  f"{scores['ssim']:.4f}  pixels without a ray {1 - valid.mean():.2%}  ({train_s:.0f} s; rays "
                  f"made in {rays_s:.2f} s)", flush=True)
            if coeffs:  # the route datasets took before: images resampled to a pinhole and cropped
                t0 = time.perf_counter()
                flat, (x0, y0, w, h) = undistorted_views(src)
                undistort_s = time.perf_counter() - t0
                image = [psnr(v.rgb, clean.rgb[y0:y0 + h, x0:x0 + w]) for v, clean in zip(flat, train)]
                field_ = Ensemble(*bbox, n_members=1, config=config, seed=args.seed)
                train_on(field_, flat, args.steps)
                scores, _ = score_views(field_, test)
                results[name].update(undistort_psnr=scores["psnr"], undistort_ssim=scores["ssim"], window=[w, h],
                                     window_fraction=w / args.res, undistort_image_psnr=float(np.mean(image)),
                                     undistort_seconds=round(undistort_s, 2))
                print(f"{'':8s} undistorted (window {w}x{h}, images {np.mean(image):6.2f} dB): field PSNR "
                      f"{scores['psnr']:6.2f} dB  SSIM {scores['ssim']:.4f}  (undistorted in {undistort_s:.2f} s)",
                      flush=True)
    gaps = {name: results["none"]["psnr"] - r["psnr"] for name, r in results.items() if name != "none"}
    for name, gap in gaps.items():
        print(f"gap {name}: {gap:+.2f} dB (clean capture minus distorted, through the lens's rays; undistorted "
              f"{results['none']['psnr'] - results[name]['undistort_psnr']:+.2f} dB)")
    out = {"mesh": Path(args.mesh).name, "res": args.res, "spp": args.spp, "train_views": args.train_views,
           "test_views": args.test_views, "preset": args.preset, "steps": args.steps, "seed": args.seed,
           "render_seconds": round(render_s, 1), "results": results, "gap_db": gaps,
           "machine": platform.machine(), "variant": __import__("mitsuba").variant()}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
