"""Held-out fit quality of the radiance field against training wall time.

Two kinds of data:

* a mesh (``--mesh``, default ``spot.obj`` at 64x64): 50 training views and
  20 held-out views from the sphere rig of
  :func:`mitsuba_active.rigs.scene_rigs` (held-out views in the
  candidates' gaps), ground truth from :class:`mitsuba_active.groundtruth.GroundTruth`;
* a ``transforms.json`` dataset (``--dataset``, e.g. nerf-synthetic Mic at
  ``--downscale 4``, 200x200): ``--train-views`` of its training frames,
  evenly spaced (0: all), scored on its test frames. Its images' alpha says
  which rays are empty.

Trains one ensemble (``--members``, default 1) of a preset (``--preset``,
the library's ``FieldConfig`` defaults when not given) and evaluates every
``--eval-every`` seconds of *training* time (evaluation time is excluded):

* PSNR (dB) of the rendered sRGB against the held-out images (member mean),
* mean relative distance error ``|d - d_gt| / d_gt`` over held-out pixels
  whose ground-truth ray hits the mesh (meshes only).

Usage::

    PYTHONPATH=. python benchmarks/fit_quality.py [--seconds 60]
        [--set OPTION=VALUE ...] [--out benchmarks/results/fit_quality.json]
    PYTHONPATH=. python benchmarks/fit_quality.py --dataset ../shared/data/datasets/nerf_synthetic_mic \
        --downscale 4 --train-views 20 --preset default --seconds 180 --out benchmarks/results/fit_quality_mic_20.json

``--steps N`` trains N steps instead of a time budget: PSNR at equal steps
compares settings on a machine busy with other work.

``--eval-steps N`` evaluates every N steps instead (one run of 4,000 steps
with ``--eval-steps 500`` gives the scores at 1,500 and 4,000 steps).

``--set`` changes any other :class:`FieldConfig` option, e.g. empty-space
skipping: ``--set empty_weight=1 --set occupancy_resolution=64``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mitsuba_active  # noqa: E402,F401
import numpy as np  # noqa: E402

from mitsuba_active.datasets import DatasetSource  # noqa: E402
from mitsuba_active.errors import UserError  # noqa: E402
from mitsuba_active.field import Ensemble, FieldConfig  # noqa: E402
from mitsuba_active.field.config import FIELD_PRESETS  # noqa: E402
from mitsuba_active.groundtruth import GroundTruth  # noqa: E402
from mitsuba_active.rigs import scene_rigs  # noqa: E402
from mitsuba_active.scene import load_scene, scene_from_mesh  # noqa: E402
from mitsuba_active.training import train_on, view_rays  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MESH = str(ROOT.parent / "shared/data/meshes/spot.obj")


def evaluate(ens, test):
    rgb, dist, hit = test["rgb"], test["distance"], test["hit"]
    st = ens.predict(test["origins"], test["directions"])
    mse = float(np.mean((np.clip(st["rgb_mean"], 0, 1) - rgb) ** 2))
    out = dict(psnr=-10 * np.log10(mse), dist_rel_err=None, dist_rel_err_median=None)
    if hit.any():
        rel = np.abs(st["distance_mean"][hit] - dist[hit]) / dist[hit]
        out.update(dist_rel_err=float(rel.mean()), dist_rel_err_median=float(np.median(rel)))
    return out


def mesh_views(args):
    """Training views and held-out rays of the mesh's sphere rig, the box, the ground truth's seconds, the image
    width."""
    with tempfile.TemporaryDirectory() as tmp:
        xml = scene_from_mesh(args.mesh, Path(tmp) / "scene.xml")
        scene = load_scene(xml)
        train_cams, test_cams = scene_rigs(scene, "sphere", n_candidates=args.train_views,
                                           n_heldout=args.test_views, width=args.res)
        gt = GroundTruth(scene, spp=args.spp)
        t0 = time.perf_counter()
        train = [gt.render(c) for c in train_cams]
        test = view_rays([gt.render(c) for c in test_cams])
        return train, test, (scene.bbox_min, scene.bbox_max), time.perf_counter() - t0, args.res


def dataset_views(args):
    """Training views and held-out rays of the dataset, its box, the seconds taken to read them, the image width."""
    t0 = time.perf_counter()
    src = DatasetSource.from_path(args.dataset, downscale=args.downscale, n_heldout=args.test_views or None,
                                  n_candidates=args.train_views or None)
    train = [src.candidate_view(i) for i in range(len(src.candidates))]
    test = view_rays([src.heldout_view(i) for i in range(len(src.heldout))])
    return train, test, (src.bbox_min, src.bbox_max), time.perf_counter() - t0, src.candidates[0].width


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default=MESH)
    ap.add_argument("--dataset", default=None, help="a transforms.json dataset instead of the mesh")
    ap.add_argument("--downscale", type=int, default=4, help="the dataset's image downscale factor")
    ap.add_argument("--preset", choices=list(FIELD_PRESETS), default=None,
                    help="a run preset's options for the images' width, under --set's [FieldConfig's defaults]")
    ap.add_argument("--seconds", type=float, default=60.0, help="training wall-time budget")
    ap.add_argument("--steps", type=int, default=0,
                    help="train this many steps instead (0: --seconds), for comparisons on a busy machine")
    ap.add_argument("--eval-every", type=float, default=10.0)
    ap.add_argument("--eval-steps", type=int, default=0,
                    help="evaluate every this many steps instead of --eval-every seconds (a multiple of 10)")
    ap.add_argument("--members", type=int, default=1)
    ap.add_argument("--train-views", type=int, default=50, help="(a dataset's: evenly spaced, 0 for all)")
    ap.add_argument("--test-views", type=int, default=20, help="(a dataset's: evenly spaced, 0 for all)")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--distance-weight", type=float, default=None,
                    help="FieldConfig.distance_weight [0.5 for a mesh; 0 for a dataset, the library default]")
    ap.add_argument("--lr", type=float, default=None, help="FieldConfig.lr [the preset's]")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                    help="any other FieldConfig option, e.g. --set occupancy_resolution=64 (repeatable)")
    ap.add_argument("--out", default="benchmarks/results/fit_quality.json")
    args = ap.parse_args(argv)
    try:
        train, test, (bbox_min, bbox_max), gt_s, width = dataset_views(args) if args.dataset else mesh_views(args)
        base = FIELD_PRESETS[args.preset].config_options(width) if args.preset else {}
        base["distance_weight"] = args.distance_weight if args.distance_weight is not None else \
            (0.0 if args.dataset else 0.5)
        if args.lr is not None:
            base["lr"] = args.lr
        cfg = FieldConfig.from_options(args.set, **base)
    except UserError as exc:
        ap.error(str(exc))

    ens = Ensemble(bbox_min, bbox_max, n_members=args.members, config=cfg, seed=args.seed)
    train_on(ens, train, 0)  # the views' rays, as runs set them
    curve = []
    trained, steps, next_eval = 0.0, 0, args.eval_every
    chunk = 10
    while (steps < args.steps) if args.steps else (trained < args.seconds):
        t0 = time.perf_counter()
        losses = ens.train(chunk)
        trained += time.perf_counter() - t0
        steps += chunk
        due = (steps % args.eval_steps == 0) if args.eval_steps else trained >= next_eval
        if due or (steps >= args.steps if args.steps else trained >= args.seconds):
            m = evaluate(ens, test)
            occ = ens.occupancy()
            m.update(seconds=trained, steps=steps, train_mse=float(losses[-1]),
                     occupied=None if occ is None else float(occ.mean()))
            curve.append(m)
            dist = "" if m["dist_rel_err"] is None else \
                f"  dist err {100 * m['dist_rel_err']:.2f}% (median {100 * m['dist_rel_err_median']:.2f}%)"
            print(f"{trained:6.1f} s  {steps:5d} steps  PSNR {m['psnr']:.2f} dB{dist}"
                  + ("" if occ is None else f"  occupied {100 * occ.mean():.0f}%"), flush=True)
            if trained >= next_eval:
                next_eval += args.eval_every
    final = curve[-1]
    best = max(curve, key=lambda m: m["psnr"])
    result = dict(mesh=None if args.dataset else args.mesh, dataset=args.dataset, resolution=width,
                  downscale=args.downscale if args.dataset else None, train_views=args.train_views,
                  test_views=args.test_views, preset=args.preset, members=args.members, seed=args.seed,
                  config=cfg.to_dict(), groundtruth_seconds=gt_s, final=final, best=best, curve=curve)
    if not args.dataset:
        result.update(target=dict(psnr_db=28.0, dist_rel_err=0.03, seconds=60.0),
                      met=bool(final["psnr"] >= 28.0 and final["dist_rel_err"] <= 0.03))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
