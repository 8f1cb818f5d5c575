"""Training throughput of the radiance-field ensemble (ray-samples per second).

A ray-sample is one of the ``n_samples`` stratified samples of one training
ray of one member; every sample is evaluated (no empty-space skipping), so
``samples/s = K * batch_rays * n_samples / step_time``. A step is a full
training step: batch sampling, forward, backward and the Adam update, timed
with the loss read back (which synchronises the device).

Usage::

    PYTHONPATH=. python benchmarks/train_throughput.py [--steps 20] [--repeats 3]
        [--memory-steps 2000] [--out benchmarks/results/train_throughput.json]

``--memory-steps N`` additionally trains K=1 for N steps and records the
resident set size (RSS) every 100 steps; the drift is (last - first)/first
after a 100-step warm-up.

On the CPU the step is also timed with the compositing of the GPU path
(blocked prefix sums and reductions over per-sample arrays) in place of the
CPU's ray marching, the two kinds of steps taking turns likewise
(``blocked_compositing_step_ms``).

Diagnostics explain how the step time grows with K:

- ``phases``: forward (batch, lookups, compositing, loss), backward and Adam
  timed separately, with a synchronisation after each (so they add up to
  a little more than a normal step);
- ``lookups``: one kernel of ``batch_rays * n_samples * 8 * n_levels``
  trilinear-corner lookups into a table of the configured size, reading each
  member's 4 floats (K*4 adjacent floats per lookup), without any other work;
- ``grid_only``: a training step without the volume rendering: the grid
  lookups of a real batch's samples, a loss that is a fixed weighted sum of the
  looked-up features, its backward pass (the gradient scatter) and Adam. Every
  renderer pays at least this, so its K=4 / K=1 ratio bounds what fusing the
  members' compositing can achieve.

``--set OPTION=VALUE`` (repeatable) changes FieldConfig options, e.g. the
4-level grid of earlier versions: ``--set n_levels=4``. The default grid is
also that of the ``fast`` preset, of every planner's ensemble and of the
``default`` preset's evaluation field up to 64-pixel images, whose other
settings (a lower learning rate, the empty-ray loss) change the cost little.
``--preset default --width 200`` times the ``default`` preset's field for
200-pixel images (its 12-level grid, 256 samples a ray, view-dependent colour
and distortion loss), without its empty-space skipping, which these
synthetic rays would not exercise alike.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mitsuba_active  # noqa: E402,F401  (variant + LLVM first)
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

from mitsuba_active.errors import UserError  # noqa: E402
from mitsuba_active.field import Ensemble, FieldConfig  # noqa: E402
from mitsuba_active.field.render import lookup_samples  # noqa: E402
from mitsuba_active.field.samples import sample_along_rays  # noqa: E402
from mitsuba_active.field.config import FIELD_PRESETS  # noqa: E402


def synthetic_rays(n_views=20, width=64, height=64, radius=3.0, sphere=0.6, seed=0):
    """Rays of cameras on a sphere looking at a textured analytic sphere."""
    rng = np.random.default_rng(seed)
    O, D = [], []
    for i in range(n_views):
        v = rng.normal(size=3)
        cam = radius * v / np.linalg.norm(v)
        f = -cam / np.linalg.norm(cam)
        r = np.cross(f, [0.0, 1.0, 0.0])
        r /= np.linalg.norm(r)
        u = np.cross(r, f)
        t = np.tan(np.radians(20.0))
        ys, xs = np.meshgrid((np.arange(height) + 0.5) / height * 2 - 1,
                             (np.arange(width) + 0.5) / width * 2 - 1, indexing="ij")
        d = f + xs.reshape(-1, 1) * t * r - ys.reshape(-1, 1) * t * u
        D.append(d / np.linalg.norm(d, axis=1, keepdims=True))
        O.append(np.repeat(cam[None], width * height, 0))
    o = np.concatenate(O).astype(np.float32)
    d = np.concatenate(D).astype(np.float32)
    b = np.sum(o * d, 1)
    disc = b * b - (np.sum(o * o, 1) - sphere ** 2)
    hit = disc > 0
    dist = np.where(hit, -b - np.sqrt(np.maximum(disc, 0.0)), 0.0)
    p = o + dist[:, None] * d
    rgb = np.where(hit[:, None], 0.5 + 0.4 * np.sin(5 * p + np.arange(3)), 1.0)
    return o, d, rgb.astype(np.float32), dist.astype(np.float32), hit


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def ensembles(ks, rays, cfg, warmup):
    """One ensemble per K on the synthetic rays, each trained ``warmup`` steps
    (which compiles and caches every kernel of a full step)."""
    ens = {}
    for k in ks:
        ens[k] = Ensemble([-0.7] * 3, [0.7] * 3, n_members=k, config=cfg, seed=0)
        ens[k].set_rays(*rays)
        ens[k].train(warmup)
    return ens


@contextlib.contextmanager
def compositing(marched: bool):
    """Composite with the CPU's ray marching (the default there) or, if not
    ``marched``, with the blocked reductions of the GPU path."""
    from mitsuba_active.field import render

    default = render._marching
    if not marched:
        render._marching = lambda s, return_weights: False
    try:
        yield
    finally:
        render._marching = default


def time_steps(ks, rays, cfg, steps, repeats, warmup, kinds=(True,)):
    """Per-step wall times for each K and compositing (``kinds``: marched
    or not, see :func:`compositing`), keyed ``(k, marched)``. Each ensemble
    trains ``steps`` steps in a row, as training does (so its data stay in the
    caches), and the ensembles take turns ``repeats`` times (K=1, K=4, K=1,
    ...) so that load from other processes hits all alike."""
    ens = {}
    for marched in kinds:
        with compositing(marched):
            for k, e in ensembles(ks, rays, cfg, warmup).items():
                ens[k, marched] = e
    times = {key: [] for key in ens}
    for _ in range(repeats):
        for (k, marched), e in ens.items():
            with compositing(marched):
                for _ in range(steps):
                    t0 = time.perf_counter()
                    e.train(1)
                    times[k, marched].append(time.perf_counter() - t0)
    return times


def phase_times(ks, rays, cfg, steps, warmup):
    """Median ms of the forward, backward and Adam phases of a step, per K."""
    ens = ensembles(ks, rays, cfg, warmup)
    times = {k: {"forward": [], "backward": [], "adam": []} for k in ks}
    for _ in range(steps):
        for k, e in ens.items():
            t0 = time.perf_counter()
            _, loss = e.training_loss()
            dr.eval(loss)
            dr.sync_thread()
            t1 = time.perf_counter()
            dr.backward(loss)
            dr.eval(dr.grad(e.params().grid))
            dr.sync_thread()
            t2 = time.perf_counter()
            e.optimizer_step()
            dr.eval(e.params().grid)
            dr.sync_thread()
            t3 = time.perf_counter()
            for name, dt in (("forward", t1 - t0), ("backward", t2 - t1), ("adam", t3 - t2)):
                times[k][name].append(dt)
    return {str(k): {name: 1e3 * statistics.median(v) for name, v in t.items()}
            for k, t in times.items()}


def grid_only_times(ks, rays, cfg, steps, warmup):
    """Median ms of a step that only looks up, back-propagates and updates the
    grid, per K (the K's steps interleaved, as in :func:`time_steps`)."""
    ens = ensembles(ks, rays, cfg, 0)  # warmed up below, on the grid-only kernels
    times = {k: [] for k in ks}
    for j in range(warmup + steps):
        for k, e in ens.items():
            t0 = time.perf_counter()
            idx, jitter = e._batch()
            o = dr.gather(mi.Point3f, e._rays["o"], idx)
            d = dr.gather(mi.Vector3f, e._rays["d"], idx)
            raws = lookup_samples(e.params(), sample_along_rays(o, d, e.params(), jitter))
            loss = dr.sum(sum(r[0] * 0.4 + r[1] * 0.3 + r[2] * 0.2 + r[3] * 0.1 for r in raws))
            dr.backward(loss)
            e.optimizer_step()
            dr.eval(e.params().grid)
            dr.sync_thread()
            times[k].append(time.perf_counter() - t0)
    return {str(k): 1e3 * statistics.median(t[warmup:]) for k, t in times.items()}


def lookup_times(ks, cfg, repeats=7):
    """Median ms of a kernel doing only the grid lookups of one training step.

    Each of the ``batch_rays * n_samples`` lanes makes ``8 * n_levels``
    lookups at pseudo-random table entries and reads K*4 adjacent floats
    (every member's density and colour) per lookup, as the member-interleaved
    table does.
    """
    from mitsuba_active.field.grid import GridLayout

    n_lanes = cfg.batch_rays * cfg.n_samples
    entries = GridLayout.from_config(cfg).n_entries
    XF = type(mi.ArrayXf())
    out = {}
    for k in ks:
        table = mi.Float(np.random.default_rng(0).normal(size=entries * k * 4).astype(np.float32))
        lane = dr.arange(mi.UInt32, n_lanes)
        times = []
        for _ in range(repeats):
            acc = [mi.Float(0.0)] * (4 * k)
            for c in range(8 * cfg.n_levels):
                idx = (lane * ((c * 2654435761 + 1) & 0xFFFFFFF)) % entries
                v = dr.gather(XF, table, idx, True, shape=(4 * k, n_lanes))
                acc = [a + v[i] for i, a in enumerate(acc)]
            t0 = time.perf_counter()
            dr.eval(acc)
            dr.sync_thread()
            times.append(time.perf_counter() - t0)
        out[str(k)] = 1e3 * statistics.median(times[2:])
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20, help="timed steps per repeat")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--members", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--memory-steps", type=int, default=0,
                    help="also track RSS over this many K=1 steps (e.g. 2000)")
    ap.add_argument("--preset", choices=list(FIELD_PRESETS), default=None,
                    help="a run preset's evaluation field for --width pixels, skipping off [FieldConfig's defaults]")
    ap.add_argument("--width", type=int, default=200, help="the images' width the preset's grid follows")
    ap.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                    help="a FieldConfig option, e.g. --set n_levels=4 (repeatable)")
    ap.add_argument("--out", default="benchmarks/results/train_throughput.json")
    args = ap.parse_args(argv)

    base = {}
    if args.preset:  # these synthetic rays would not exercise its empty-space skipping alike
        base = {**FIELD_PRESETS[args.preset].config_options(args.width), "occupancy_resolution": 0}
    try:
        cfg = FieldConfig.from_options(args.set, **base)  # 4096 rays x 64 samples by default
    except UserError as exc:
        ap.error(str(exc))
    if cfg.occupancy_resolution > 0:
        ap.error("the sample counts assume every sample is evaluated: leave occupancy_resolution at 0")
    rays = synthetic_rays()
    result = dict(preset=args.preset, width=args.width if args.preset else None,
                  batch_rays=cfg.batch_rays, n_samples=cfg.n_samples,
                  config=cfg.to_dict(), machine=platform.processor() or platform.machine(),
                  cpu_count=os.cpu_count(), variant=__import__("mitsuba").variant(),
                  sample_counting="K * batch_rays * n_samples per step: every stratified "
                                  "sample of every ray and member is evaluated "
                                  "(no empty-space skipping)",
                  members={})
    # The CPU marches rays to composite them; the GPU path's blocked reductions are timed beside it.
    cpu = dr.backend_v(mi.Float) == dr.JitBackend.LLVM
    all_times = time_steps(args.members, rays, cfg, args.steps, args.repeats, args.warmup,
                           kinds=(True, False) if cpu else (True,))
    for k in args.members:
        times = all_times[k, True]
        med = statistics.median(times)
        sps = k * cfg.batch_rays * cfg.n_samples / med
        result["members"][str(k)] = dict(step_ms_median=med * 1e3,
                                         step_ms_min=min(times) * 1e3,
                                         ray_samples_per_s=sps,
                                         ray_samples_per_s_best=k * cfg.batch_rays * cfg.n_samples / min(times),
                                         timed_steps=len(times))
        print(f"K={k}: step {med * 1e3:.1f} ms (median of {len(times)}, min {min(times) * 1e3:.1f}), "
              f"{sps / 1e6:.2f} M ray-samples/s")
    if "1" in result["members"] and "4" in result["members"]:
        ratio = result["members"]["4"]["step_ms_median"] / result["members"]["1"]["step_ms_median"]
        result["k4_over_k1_step_time"] = ratio
        print(f"K=4 / K=1 step time: {ratio:.2f}")
    if cpu:
        blocked = {str(k): 1e3 * statistics.median(all_times[k, False]) for k in args.members}
        result["blocked_compositing_step_ms"] = blocked
        print("with the blocked reductions instead: " + ", ".join(f"K={k} {ms:.1f} ms" for k, ms in blocked.items())
              + (f" (K=4 / K=1 {blocked['4'] / blocked['1']:.2f})" if "1" in blocked and "4" in blocked else ""))

    phases = phase_times(args.members, rays, cfg, args.steps, args.warmup)
    lookups = lookup_times(args.members, cfg)
    grid_only = grid_only_times(args.members, rays, cfg, args.steps, args.warmup)
    result["phases_ms"] = phases
    result["lookups_ms"] = lookups
    result["grid_only_step_ms"] = grid_only
    for k in args.members:
        p = phases[str(k)]
        print(f"K={k}: forward {p['forward']:.1f} ms, backward {p['backward']:.1f} ms, "
              f"Adam {p['adam']:.1f} ms; lookups alone {lookups[str(k)]:.1f} ms; "
              f"grid-only step {grid_only[str(k)]:.1f} ms")
    if "1" in grid_only and "4" in grid_only:
        result["grid_only_k4_over_k1"] = grid_only["4"] / grid_only["1"]
        print(f"grid-only step K=4 / K=1: {result['grid_only_k4_over_k1']:.2f}")

    if args.memory_steps > 0:
        ens = ensembles([1], rays, cfg, 100)[1]
        trace = [(0, rss_mib())]
        done = 0
        while done < args.memory_steps:
            n = min(100, args.memory_steps - done)
            ens.train(n)
            done += n
            trace.append((done, rss_mib()))
        first, last = trace[0][1], trace[-1][1]
        drift = (last - first) / first
        result["memory"] = dict(steps=args.memory_steps, rss_mib_first=first,
                                rss_mib_last=last, rss_mib_max=max(r for _, r in trace),
                                drift=drift, trace=trace)
        print(f"RSS over {args.memory_steps} steps: {first:.1f} -> {last:.1f} MiB "
              f"(drift {100 * drift:+.1f}%, max {result['memory']['rss_mib_max']:.1f})")

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
