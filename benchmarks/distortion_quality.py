"""Field quality from a distorted capture against the same capture without distortion.

Renders a mesh's views (``--mesh``, default ``spot.obj``, ``--res`` 128x128)
from the sphere rig, distorts them with a known lens (OpenCV's own model:
radial-tangential ``k1=-0.6 k2=0.3 p1=0.01 p2=-0.008`` and equidistant
fisheye ``k1=-0.4 k2=0.1 k3=-0.02 k4=0.004``, the test suite's), and writes
each set as a transforms.json dataset (8-bit PNG), with an undistorted set
as the reference. Each dataset is read back as a run reads it (undistorted
and cropped to the pixels that see the capture) and trains the same field
(``--preset``, ``--steps``, ``--seed``); every field is scored on the same
clean held-out renders (PSNR, dB, and SSIM). Also reported per lens: the
window a frame keeps (fraction of the image's width) and the PSNR of the
undistorted training images against the clean renders in that window.

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
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mitsuba_active  # noqa: E402,F401
import imageio.v3 as iio  # noqa: E402
import numpy as np  # noqa: E402

from mitsuba_active.datasets import DatasetSource, mitsuba_to_opengl  # noqa: E402
from mitsuba_active.env import SceneSource  # noqa: E402
from mitsuba_active.field import Ensemble, FieldConfig  # noqa: E402
from mitsuba_active.field.config import FIELD_PRESETS  # noqa: E402
from mitsuba_active.lens import capture_through  # noqa: E402
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


def lens_rays(camera, f: float, model: str, coeffs: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays through the pixel centres of the distorted image of ``camera`` (the other route to a
    distorted capture: the field's rays follow the lens, the images stay as captured). Returns
    origins, unit directions (H*W, 3) float32 and an (H*W,) bool mask of the pixels whose ray
    OpenCV's iterative undistortion finds (it maps back onto the same pixel)."""
    import cv2

    w, h = camera.width, camera.height
    k = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pts = np.stack([u, v], -1).reshape(-1, 1, 2).astype(np.float64)
    if model == "OPENCV_FISHEYE":
        d = np.array([coeffs.get(c, 0.0) for c in ("k1", "k2", "k3", "k4")])
        und = cv2.fisheye.undistortPoints(pts, k, d)
        back = cv2.fisheye.distortPoints(und, k, d)
    else:
        d = np.array([coeffs.get(c, 0.0) for c in ("k1", "k2", "p1", "p2", "k3")])
        und = cv2.undistortPoints(pts, k, d, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
        back = cv2.projectPoints(np.concatenate([und, np.ones_like(und[..., :1])], -1), np.zeros(3), np.zeros(3),
                                 k, d)[0]
    x, y = und.reshape(-1, 2).T
    valid = np.linalg.norm((back - pts).reshape(-1, 2), axis=1) < 1e-2
    # Mitsuba's camera frame: x left, y up, z forward; OpenCV's: x right, y down.
    local = np.stack([-x, -y, np.ones_like(x)], -1)
    dirs = local @ camera.to_world[:3, :3].T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = np.broadcast_to(camera.position, dirs.shape)
    return origins.astype(np.float32), dirs.astype(np.float32), valid


def train_through_lens(field_, root: Path, train, f: float, model: str, coeffs: dict, background, steps: int):
    """Train ``field_`` on the distorted images of ``root`` as captured, along the lens's rays;
    returns the seconds the rays took to make."""
    t0 = time.perf_counter()
    parts = [lens_rays(v.camera, f, model, coeffs) for v in train]
    rays_s = time.perf_counter() - t0
    rgb = [np.asarray(iio.imread(root / f"images/{n:03d}.png"), np.float32)[..., :3].reshape(-1, 3) / 255
           for n in range(len(train))]
    keep = np.concatenate([m for _, _, m in parts])
    o, d = (np.concatenate([p[i] for p in parts])[keep] for i in (0, 1))
    colour = np.concatenate(rgb)[keep]  # sRGB, as the dataset route reads the PNGs
    n = len(o)
    field_.set_rays(o, d, colour, np.zeros(n, np.float32), np.zeros(n, bool), True, np.zeros(n, bool), background)
    field_.train(steps)
    return rays_s


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
            t0 = time.perf_counter()
            src = DatasetSource.from_path(tmp / name, downscale=1, cache_dir=False)
            views = [src.candidate_view(i) for i in range(len(src.candidates))]
            undistort_s = time.perf_counter() - t0
            x0, y0, w, h = src.candidate_frames[0].crop
            image = [psnr(v.rgb, clean.rgb[y0:y0 + h, x0:x0 + w]) for v, clean in zip(views, train)]
            field_ = Ensemble(*bbox, n_members=1, config=config, seed=args.seed)
            t0 = time.perf_counter()
            train_on(field_, views, args.steps)
            train_s = time.perf_counter() - t0
            scores, _ = score_views(field_, test)
            results[name] = {"camera_model": model, "coeffs": coeffs, "window": [w, h],
                             "window_fraction": w / args.res, "image_psnr": float(np.mean(image)),
                             "psnr": scores["psnr"], "ssim": scores["ssim"], "train_seconds": round(train_s, 1),
                             "undistort_seconds": round(undistort_s, 2)}
            print(f"{name:8s} window {w}x{h}  undistorted images {np.mean(image):6.2f} dB  "
                  f"field PSNR {scores['psnr']:6.2f} dB  SSIM {scores['ssim']:.4f}  ({train_s:.0f} s)", flush=True)
            if coeffs:  # the other route: the rays follow the lens, the images stay as captured
                field_ = Ensemble(*bbox, n_members=1, config=config, seed=args.seed)
                f = float(train[0].camera.intrinsics()[0, 0])
                rays_s = train_through_lens(field_, tmp / name, train, f, model, coeffs, views[0].background,
                                            args.steps)
                scores, _ = score_views(field_, test)
                results[name].update(rays_psnr=scores["psnr"], rays_ssim=scores["ssim"], rays_seconds=round(rays_s, 2))
                print(f"{'':8s} through the lens's rays: field PSNR {scores['psnr']:6.2f} dB  SSIM "
                      f"{scores['ssim']:.4f}  (rays made in {rays_s:.2f} s; images undistorted in "
                      f"{undistort_s:.2f} s)", flush=True)
    gaps = {name: results["none"]["psnr"] - r["psnr"] for name, r in results.items() if name != "none"}
    for name, gap in gaps.items():
        print(f"gap {name}: {gap:+.2f} dB (undistorted capture minus distorted; through the lens's rays "
              f"{results['none']['psnr'] - results[name]['rays_psnr']:+.2f} dB)")
    out = {"mesh": Path(args.mesh).name, "res": args.res, "spp": args.spp, "train_views": args.train_views,
           "test_views": args.test_views, "preset": args.preset, "steps": args.steps, "seed": args.seed,
           "render_seconds": round(render_s, 1), "results": results, "gap_db": gaps,
           "machine": platform.machine(), "variant": __import__("mitsuba").variant()}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
