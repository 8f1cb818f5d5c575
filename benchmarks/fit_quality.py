"""Held-out fit quality of the radiance field against training wall time.

Scene: ``spot.obj`` (64x64 views): 50 training views and 20 held-out views
from the sphere rig of :func:`mitsuba_active.cameras.scene_rigs` (held-out
views in the candidates' gaps), ground truth from :class:`mitsuba_active.groundtruth.GroundTruth`.
Trains one ensemble (``--members``, default 1) and evaluates every
``--eval-every`` seconds of *training* time (evaluation time is excluded):

* PSNR (dB) of the rendered sRGB against the held-out images (member mean),
* mean relative distance error ``|d - d_gt| / d_gt`` over held-out pixels
  whose ground-truth ray hits the mesh.

Usage::

    PYTHONPATH=. python benchmarks/fit_quality.py [--seconds 60]
        [--set OPTION=VALUE ...] [--out benchmarks/results/fit_quality.json]

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

from mitsuba_active.cameras import camera_rays, scene_rigs  # noqa: E402
from mitsuba_active.errors import UserError  # noqa: E402
from mitsuba_active.field import Ensemble, FieldConfig  # noqa: E402
from mitsuba_active.groundtruth import GroundTruth  # noqa: E402
from mitsuba_active.scene import load_scene, scene_from_mesh  # noqa: E402

MESH = "/work/shared/data/meshes/spot.obj"


def stack_views(gt, cams):
    o, d, rgb, dist, hit = [], [], [], [], []
    for cam in cams:
        v = gt.render(cam)
        oo, dd = camera_rays(cam)
        o.append(oo)
        d.append(dd)
        rgb.append(v.rgb.reshape(-1, 3))
        dist.append(v.distance.reshape(-1))
        hit.append(v.mask.reshape(-1))
    return tuple(np.concatenate(x) for x in (o, d, rgb, dist, hit))


def evaluate(ens, test):
    o, d, rgb, dist, hit = test
    st = ens.predict(o, d)
    mse = float(np.mean((np.clip(st["rgb_mean"], 0, 1) - rgb) ** 2))
    rel = np.abs(st["distance_mean"][hit] - dist[hit]) / dist[hit]
    return dict(psnr=-10 * np.log10(mse), dist_rel_err=float(rel.mean()),
                dist_rel_err_median=float(np.median(rel)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default=MESH)
    ap.add_argument("--seconds", type=float, default=60.0, help="training wall-time budget")
    ap.add_argument("--eval-every", type=float, default=10.0)
    ap.add_argument("--members", type=int, default=1)
    ap.add_argument("--train-views", type=int, default=50)
    ap.add_argument("--test-views", type=int, default=20)
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--distance-weight", type=float, default=0.5,
                    help="FieldConfig.distance_weight (the library default is 0)")
    ap.add_argument("--lr", type=float, default=FieldConfig.lr)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                    help="any other FieldConfig option, e.g. --set occupancy_resolution=64 (repeatable)")
    ap.add_argument("--out", default="benchmarks/results/fit_quality.json")
    args = ap.parse_args(argv)
    try:
        cfg = FieldConfig.from_options(args.set, distance_weight=args.distance_weight, lr=args.lr)
    except UserError as exc:
        ap.error(str(exc))

    with tempfile.TemporaryDirectory() as tmp:
        xml = scene_from_mesh(args.mesh, Path(tmp) / "scene.xml")
        scene = load_scene(xml)
        train_cams, test_cams = scene_rigs(scene, "sphere", n_candidates=args.train_views,
                                           n_heldout=args.test_views, width=args.res)
        gt = GroundTruth(scene, spp=args.spp)
        t0 = time.perf_counter()
        train = stack_views(gt, train_cams)
        test = stack_views(gt, test_cams)
        gt_s = time.perf_counter() - t0
        bbox_min, bbox_max = scene.bbox_min, scene.bbox_max

    ens = Ensemble(bbox_min, bbox_max, n_members=args.members, config=cfg, seed=args.seed)
    ens.set_rays(*train)
    curve = []
    trained, steps, next_eval = 0.0, 0, args.eval_every
    chunk = 10
    while trained < args.seconds:
        t0 = time.perf_counter()
        losses = ens.train(chunk)
        trained += time.perf_counter() - t0
        steps += chunk
        if trained >= next_eval or trained >= args.seconds:
            m = evaluate(ens, test)
            occ = ens.occupancy()
            m.update(seconds=trained, steps=steps, train_mse=float(losses[-1]),
                     occupied=None if occ is None else float(occ.mean()))
            curve.append(m)
            print(f"{trained:6.1f} s  {steps:5d} steps  PSNR {m['psnr']:.2f} dB  "
                  f"dist err {100 * m['dist_rel_err']:.2f}% (median "
                  f"{100 * m['dist_rel_err_median']:.2f}%)"
                  + ("" if occ is None else f"  occupied {100 * occ.mean():.0f}%"), flush=True)
            next_eval += args.eval_every
    final = curve[-1]
    result = dict(mesh=args.mesh, resolution=args.res, train_views=args.train_views,
                  test_views=args.test_views, members=args.members, config=cfg.to_dict(),
                  groundtruth_seconds=gt_s, final=final, curve=curve,
                  target=dict(psnr_db=28.0, dist_rel_err=0.03, seconds=60.0),
                  met=bool(final["psnr"] >= 28.0 and final["dist_rel_err"] <= 0.03))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
