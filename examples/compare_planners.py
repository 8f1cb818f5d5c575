"""Compare planners on one scene and plot held-out PSNR against views captured.

    python examples/compare_planners.py                       # rfe vs even on the bundled scene
    python examples/compare_planners.py SCENE.xml --planners rfe coverage
    python examples/compare_planners.py --planners examples/custom_planner.py:NoveltyWeightedVariance rfe
    python examples/compare_planners.py --tiny --out /tmp/cmp  # seconds, as in CI
"""

import argparse
from pathlib import Path

import mitsuba_active  # noqa: F401  (selects the Mitsuba variant)
from mitsuba_active.errors import UserError
from mitsuba_active.planners import make_planner, planner_folder, planner_label
from mitsuba_active.report import plot_metrics
from mitsuba_active.run import Run, RunConfig
from mitsuba_active.scenes import BUNDLED_SCENE


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", nargs="?", default=str(BUNDLED_SCENE))
    ap.add_argument("--planners", nargs="+", default=["rfe", "even"],
                    help="registered names, or FILE.py:CLASS for a planner of your own")
    ap.add_argument("--out", default="runs/compare")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tiny", action="store_true", help="tiny settings (seconds)")
    args = ap.parse_args()
    out = Path(args.out)
    # The command line's defaults (as `mitsuba-active plan`), or tiny settings.
    tiny = dict(budget=4, resolution=16, candidates=12, heldout=3, spp=4, eval_views=[2, 4],
                initial_steps=20, steps_per_view=10, eval_steps=30, rays_per_candidate=32,
                field=dict(batch_rays=256, n_samples=16))
    base = dict(scene=args.scene, seed=args.seed, **(tiny if args.tiny else {}))
    labels = [planner_label(name) for name in args.planners]  # a planner file's name without its folder
    if len(set(labels)) < len(labels):
        ap.error(f"give each planner once, and planner files different names: {' '.join(labels)}")
    try:
        for name in args.planners:  # before anything runs
            make_planner(name)
    except UserError as exc:
        ap.error(str(exc))
    configs = [RunConfig(planner=name, **base) for name in args.planners]
    # One source for every planner: the same candidates, held-out views and cached ground truth.
    source = configs[0].open_source()
    series = {}
    for cfg, label in zip(configs, labels):
        record = Run(source, cfg, out / planner_folder(cfg.planner), progress=not args.tiny).execute()
        series[label] = record["metrics"]
        print(label, " ".join(f"{m['views']}v:{m['psnr']:.2f}dB" for m in record["metrics"]))
    plots = plot_metrics(series, out, title=f"{Path(args.scene).stem}: {' vs '.join(series)}")
    print("plots:", ", ".join(str(p) for p in plots))


if __name__ == "__main__":
    main()
