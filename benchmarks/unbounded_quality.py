"""Field quality on a capture whose background lies far beyond the object's box.

Renders a textured ball (radius 0.5, emitting a checkerboard) in front of a
textured environment map with Mitsuba, from ``--views`` cameras on rings 2
units away (``--res`` pixels, 200 by default), and writes them as a
transforms.json capture whose ``aabb`` is the ball's box: the images'
backgrounds are neither white nor transparent. Trains the `default` preset's
evaluation field on ``--train-views`` evenly spaced frames for ``--steps``
steps, in the forms ``--fields`` names: ``chosen``, with the options the
capture asks for (``DatasetSource.field_options``: a directional
background); ``box``, the box and one background colour alone;
``contracted``, the scene contraction
(``DatasetSource.suggested_contraction``). Scores the test frames: PSNR over
the whole image and over the ball's pixels (dilated as ``psnr_fg`` is), from
the ball's exact silhouette.

Usage::

    PYTHONPATH=. python benchmarks/unbounded_quality.py [--res 200] [--train-views 20] [--steps 1500]
        [--fields chosen,box,contracted] [--out benchmarks/results/unbounded_quality.json]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mitsuba_active  # noqa: E402,F401
import imageio.v3 as iio  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

from mitsuba_active.cameras import camera_rays  # noqa: E402
from mitsuba_active.datasets import DatasetSource  # noqa: E402
from mitsuba_active.field import Ensemble, FieldConfig  # noqa: E402
from mitsuba_active.imageio_utils import linear_to_srgb  # noqa: E402
from mitsuba_active.metrics import foreground_psnr, psnr  # noqa: E402
from mitsuba_active.rigs import rings  # noqa: E402
from mitsuba_active.training import predict_view, train_on  # noqa: E402
from mitsuba_active.transforms import mitsuba_to_opengl  # noqa: E402

RADIUS = 0.5


def scene(env_size=(128, 256)):
    """The ball in front of its environment map, ``env_size`` (height, width) texels."""
    h, w = env_size
    yy, xx = np.mgrid[0:h, 0:w] / np.array([float(h), float(w)])[:, None, None]
    env = np.stack([0.5 + 0.4 * np.sin(8 * np.pi * xx), 0.5 + 0.4 * np.cos(4 * np.pi * yy),
                    0.3 + 0.3 * (((xx * 8).astype(int) + (yy * 4).astype(int)) % 2)], axis=-1)
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(env.astype(np.float32))},
        "ball": {"type": "sphere", "radius": RADIUS,
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
                 "emitter": {"type": "area", "radiance": {
                     "type": "checkerboard", "color0": {"type": "rgb", "value": [0.9, 0.2, 0.1]},
                     "color1": {"type": "rgb", "value": [0.1, 0.3, 0.9]},
                     "to_uv": mi.ScalarTransform4f().scale([6, 6, 1])}}},
    })


def write_capture(root: Path, n: int, size: int, fov: float = 50.0, elevations=(-15.0, 10.0, 35.0),
                  spp: int = 32, test_every: int = 5, env_size=(128, 256)) -> Path:
    """``n`` frames of ``size`` pixels on rings 2 units away at ``elevations``, every ``test_every``-th a
    test frame; returns the transforms.json."""
    sc = scene(env_size)
    (root / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    cams = rings(n, [0.0, 0.0, 0.0], 2.0, fov=fov, width=size, height=size, elevations=elevations)
    for k, cam in enumerate(cams):
        sensor = mi.load_dict({"type": "perspective", "fov": fov, "fov_axis": "x",
                               "to_world": mi.ScalarTransform4f(cam.to_world.tolist()),
                               "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}},
                               "sampler": {"type": "independent", "sample_count": spp}})
        img = np.clip(np.array(mi.render(sc, sensor=sensor, seed=k)), 0.0, 1.0)
        iio.imwrite(root / "images" / f"f_{k:03d}.png", (linear_to_srgb(img) * 255 + 0.5).astype(np.uint8))
        frames.append({"file_path": f"images/f_{k:03d}.png", "split": "test" if k % test_every == test_every - 1 else "train",
                       "transform_matrix": mitsuba_to_opengl(cam.to_world).tolist()})
    meta = {"camera_angle_x": math.radians(fov), "aabb": [[-0.6] * 3, [0.6] * 3], "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root / "transforms.json"


def ball_mask(camera) -> np.ndarray:
    """(H, W) bool: the pixel-centre ray meets the ball."""
    o, d = camera_rays(camera)
    b = np.einsum("ij,ij->i", o, d)
    c = np.einsum("ij,ij->i", o, o) - RADIUS ** 2
    return ((b * b - c > 0) & (-b + np.sqrt(np.maximum(b * b - c, 0)) > 0)).reshape(camera.height, camera.width)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=200)
    ap.add_argument("--views", type=int, default=120, help="frames rendered (every 5th a test frame)")
    ap.add_argument("--train-views", type=int, default=20)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                    help="a FieldConfig option over the preset's, for both fields")
    ap.add_argument("--fields", default="chosen,box,contracted", help="comma-separated forms of the field: "
                    "chosen (the capture's options), box (one background colour), contracted")
    ap.add_argument("--out", default="benchmarks/results/unbounded_quality.json")
    args = ap.parse_args(argv)
    names = [n.strip() for n in args.fields.split(",") if n.strip()]
    if not names or set(names) - {"chosen", "box", "contracted"}:
        ap.error(f"--fields: comma-separated among chosen, box, contracted, got {args.fields!r}")
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        src = DatasetSource.from_path(write_capture(Path(tmp), args.views, args.res))
        forms = {"chosen": src.field_options(), "box": {}, "contracted": {"contraction": src.suggested_contraction()}}
        train = [src.candidate_view(int(i)) for i in
                 np.linspace(0, len(src.candidates), args.train_views, endpoint=False)]
        test = [src.heldout_view(i) for i in range(len(src.heldout))]
        fields = [(name, forms[name]) for name in names]
        for name, extra in fields:
            config = FieldConfig.from_options(args.set, **FieldConfig.preset("default", width=args.res,
                                                                              **extra).to_dict())
            ens = Ensemble(src.bbox_min, src.bbox_max, 1, config, seed=args.seed)
            t0 = time.perf_counter()
            train_on(ens, train, args.steps)
            seconds = time.perf_counter() - t0
            full, fg = [], []
            for v in test:
                pred = np.clip(predict_view(ens, v.camera)["rgb"], 0, 1)
                full.append(psnr(pred, v.rgb))
                fg.append(foreground_psnr(pred, v.rgb, ball_mask(v.camera)))
            results[name] = {"options": {**extra, "set": args.set}, "psnr": float(np.mean(full)), "psnr_fg": float(np.mean(fg)),
                             "train_seconds": round(seconds, 1)}
            print(f"{name:10s} PSNR {np.mean(full):6.2f} dB  foreground {np.mean(fg):6.2f} dB  ({seconds:.0f} s)",
                  flush=True)
    out = {"res": args.res, "views": args.views, "train_views": args.train_views, "test_views": len(test),
           "steps": args.steps, "seed": args.seed, "results": results, "machine": platform.machine(),
           "variant": mi.variant()}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
