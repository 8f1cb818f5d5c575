"""Drive the planning loop yourself, on a scene built in Python.

The scene is a Mitsuba scene dict (no XML file): two spheres and a cube
under an environment light. The loop is the one ``mitsuba-active plan`` runs,
written out with the library's pieces and a simpler training schedule (a
fixed number of steps per captured view): the gymnasium environment captures
views, an ensemble trains on them (each round continues from the last), the
planner scores the candidates with it, and a fresh field trained on all
captured views is scored on the held-out views.

    python examples/planning_loop.py                        # a couple of minutes
    python examples/planning_loop.py --planner even         # a baseline
    python examples/planning_loop.py --tiny                 # seconds, as in CI
"""

import argparse

import numpy as np

import mitsuba_active  # noqa: F401  (selects the Mitsuba variant)
import mitsuba as mi
from mitsuba_active.env import ActiveViewEnv, SceneSource
from mitsuba_active.field import Ensemble, FieldConfig
from mitsuba_active.metrics import psnr
from mitsuba_active.planners import PlanningState, make_planner, planner_rng
from mitsuba_active.training import PLANNER_INIT_SCALE, predict_view, sparse_candidate_rays, train_on


def scene_dict() -> dict:
    """Two diffuse spheres and a cube, lit by a grey environment (scene units: about 1)."""
    def diffuse(r, g, b):
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [r, g, b]}}

    return {
        "type": "scene",
        "red": {"type": "sphere", "center": [0.35, 0.0, 0.0], "radius": 0.3, "bsdf": diffuse(0.8, 0.2, 0.1)},
        "blue": {"type": "sphere", "center": [-0.35, 0.1, 0.2], "radius": 0.22, "bsdf": diffuse(0.1, 0.3, 0.8)},
        "cube": {"type": "cube", "to_world": mi.ScalarTransform4f().translate([0.0, -0.1, -0.4]).scale(0.2),
                 "bsdf": diffuse(0.9, 0.8, 0.3)},
        "light": {"type": "constant", "radiance": {"type": "rgb", "value": [0.9, 0.9, 0.9]}},
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--planner", default="rfe", help="a registered planner or FILE.py:CLASS [rfe]")
    ap.add_argument("--budget", type=int, default=10, help="views captured in total, at least 2 [10]")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tiny", action="store_true", help="tiny settings (seconds)")
    args = ap.parse_args()
    if args.budget < 2:
        ap.error("--budget must be at least 2: the loop starts from 2 random views")
    tiny = args.tiny

    source = SceneSource.from_mitsuba(scene_dict(), name="spheres", n_candidates=12 if tiny else 60,
                                      n_heldout=3 if tiny else 10, resolution=16 if tiny else 64,
                                      spp=4 if tiny else 64)
    budget = min(args.budget, 4) if tiny else args.budget
    # The field settings of `plan` (its default preset); the planner's ensemble starts with a wide
    # spread of features, so that its members disagree where no view has looked yet.
    field = dict(batch_rays=256, n_samples=16) if tiny else {}
    steps_per_view, eval_steps = (10, 30) if tiny else (60, 1500)

    env = ActiveViewEnv(source, budget=budget, allow_repeats=True)  # the random planner repeats views
    obs, info = env.reset(seed=args.seed, options={"initial_views": 2})
    planner = make_planner(args.planner)
    # The planner's own random stream: not the one that drew the initial views.
    state = PlanningState(source.candidates, info["captured"], rng=planner_rng(args.seed))
    if planner.needs_ensemble:
        # The field the planner scores with: an ensemble (or, for `variational`, one stochastic field).
        state.ensemble = planner.make_field(source.bbox_min, source.bbox_max, planner.ensemble_size(2),
                                            FieldConfig.preset("default", planner=True, **field,
                                                               init_scale=PLANNER_INIT_SCALE), args.seed)
        # A fixed sparse set of rays per candidate: the planner scores candidates over these.
        state.candidate_rays = sparse_candidate_rays(source.candidates, 32 if tiny else 256, args.seed + 1)
        train_on(state.ensemble, env.views, steps_per_view * len(env.views))
    while not env.terminated:
        picks, scores = planner.checked_select(state, 1)
        obs, reward, terminated, truncated, info = env.step(picks[0])
        state.captured = info["captured"]
        if state.ensemble is not None:
            train_on(state.ensemble, env.views, steps_per_view)  # continues from the last round
        best = "" if scores is None else f" (score {scores[picks[0]]:.3g}, best of {len(scores)})"
        print(f"{len(env.views):2d} views: captured candidate {picks[0]}{best}")

    # Evaluation: a fresh field on every captured view, scored on the held-out views.
    config = FieldConfig.preset("default", width=source.candidates[0].width, **field)
    fresh = Ensemble(source.bbox_min, source.bbox_max, n_members=1, config=config, seed=args.seed + 1)
    train_on(fresh, env.views, eval_steps)
    heldout = [source.heldout_view(i) for i in range(len(source.heldout))]
    scores = [psnr(predict_view(fresh, view.camera)["rgb"], view.rgb) for view in heldout]
    print(f"{args.planner}: captured {env.captured}; held-out PSNR {np.mean(scores):.2f} dB "
          f"over {len(heldout)} views")


if __name__ == "__main__":
    main()
