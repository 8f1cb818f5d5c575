"""A PyTorch peer of the radiance field: the same model and training step, timed against ours.

The peer is built from a :class:`FieldConfig` as an :class:`Ensemble` of one
member is: the same grid levels (dense coarse levels, the Instant-NGP spatial
hash ``(x*1) ^ (y*2654435761) ^ (z*805459861) mod T`` for the finer ones,
the same table sizes and offsets), trilinear features summed over levels,
``sigma = exp(min(s + density_bias, 15)) / diag``, ``rgb = sigmoid``, the
optional spherical-harmonic view residual, stratified samples in the padded
box, alpha compositing over a learnt background, the same losses (the
distortion loss included) and Adam
(Dr.Jit's form: ``m * rsqrt(v + eps^2)`` scaled by ``-lr sqrt(1 - b2^t) /
(1 - b1^t)``). It trains with ``torch.compile`` on the CPU with as many
threads as Dr.Jit uses.

The script first checks that both compute the same thing (the peer starts
from our table; the same rays, the same samples): forward colours without
jitter, and the first training step's loss, gradient and update with our
step's own batch and jitter. It then times training steps of both in turns
(blocks of steps, alternating, medians after a warm-up; compile time
apart) on the synthetic rays of ``benchmarks/train_throughput.py``.

Usage (torch is the ``peers`` extra, never imported by the package)::

    PYTHONPATH=. python benchmarks/peers/torch_field.py --preset fast
    PYTHONPATH=. python benchmarks/peers/torch_field.py --preset default --width 200

Empty-space skipping is off in both (``occupancy_resolution=0``): every
sample is evaluated, so ray-samples/s are ``batch_rays * n_samples`` per step.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

# Compile times are reported: each run compiles afresh, not from inductor's on-disk cache.
os.environ.setdefault("TORCHINDUCTOR_FORCE_DISABLE_CACHES", "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import mitsuba_active  # noqa: E402,F401  (variant + LLVM first)
import drjit as dr  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from mitsuba_active.errors import UserError  # noqa: E402
from mitsuba_active.field import Ensemble, FieldConfig  # noqa: E402
from mitsuba_active.field.grid import GridLayout  # noqa: E402
from mitsuba_active.field.view import n_coefficients, view_layout  # noqa: E402
from train_throughput import synthetic_rays  # noqa: E402

#: The spatial hash's primes (Instant-NGP's), as in mitsuba_active.field.grid.
PRIMES = (1, 2654435761, 805459861)
#: The synthetic rays' box (that of benchmarks/train_throughput.py).
BOX = ([-0.7] * 3, [0.7] * 3)


def grid_lookup(table, layout: GridLayout, u):
    """Summed trilinear features (M, C) of ``table`` (entries, C) at points
    ``u`` (M, 3) of the unit cube (clamped to it), levels as ``layout`` lays them out.

    All levels' corners are gathered as one (M, 8 * levels) index: its
    backward pass is then one scatter-add into one gradient table (one
    gather per corner would give each its own zeroed table to sum)."""
    x = u.clamp(0.0, 1.0)
    indices, weights = [], []
    for r, size, offset, dense in zip(layout.resolutions, layout.sizes, layout.offsets, layout.dense):
        p = x * float(r)
        p0 = torch.floor(p).clamp_max(float(r - 1))
        f = p - p0
        c0 = p0.to(torch.int64)
        for corner in range(8):
            bits = [(corner >> a) & 1 for a in range(3)]
            w = None
            c = []
            for a in range(3):
                wa = f[:, a] if bits[a] else 1.0 - f[:, a]
                w = wa if w is None else w * wa
                c.append(c0[:, a] + bits[a])
            if dense:
                idx = c[0] + c[1] * (r + 1) + c[2] * ((r + 1) * (r + 1))
            else:  # the low bits of 64-bit products are those of Dr.Jit's 32-bit ones
                idx = ((c[0] * PRIMES[0]) ^ (c[1] * PRIMES[1]) ^ (c[2] * PRIMES[2])) & (size - 1)
            indices.append(idx + offset)
            weights.append(w)
    return (table[torch.stack(indices, 1)] * torch.stack(weights, 1)[..., None]).sum(1)


def sh_basis(d, degree: int):
    """Real spherical harmonics of degrees 1 to ``degree`` of unit directions (M, 3): (M, n)."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    basis = [-0.48860251 * y, 0.48860251 * z, -0.48860251 * x]
    if degree >= 2:
        basis += [1.09254843 * x * y, -1.09254843 * y * z, 0.31539157 * (3.0 * z * z - 1.0),
                  -1.09254843 * x * z, 0.54627421 * (x * x - y * y)]
    return torch.stack(basis, 1)


class TorchField:
    """One radiance field of ``cfg`` on the box ``bbox_min``-``bbox_max`` (padded
    as an Ensemble pads it), with its parameters and Adam state as tensors.

    Args:
        grid: float32 (n_entries, 4) starting table, or None (uniform in
            ``±init_scale``); background: (3,) logits or None (zeros);
            view: (view entries, 3 * n_coefficients) or None (zeros).
    """

    def __init__(self, cfg: FieldConfig, bbox_min, bbox_max, grid=None, background=None, view=None, seed=0):
        self.cfg = cfg
        self.layout = GridLayout.from_config(cfg)
        lo, hi = np.asarray(bbox_min, np.float64), np.asarray(bbox_max, np.float64)
        pad = cfg.bbox_padding * (hi - lo)
        self.box_min, self.box_max = lo - pad, hi + pad
        self.diag = float(np.linalg.norm(self.box_max - self.box_min))
        self.box_min_t = torch.tensor(self.box_min.tolist(), dtype=torch.float32)
        self.box_scale_t = torch.tensor((1.0 / (self.box_max - self.box_min)).tolist(), dtype=torch.float32)
        self.box_max_t = torch.tensor(self.box_max.tolist(), dtype=torch.float32)
        rng = np.random.default_rng(seed)
        if grid is None:
            grid = rng.uniform(-cfg.init_scale, cfg.init_scale, (self.layout.n_entries, 4))
        self.params = {"grid": torch.tensor(np.asarray(grid, np.float32)),
                       "background": torch.tensor(np.zeros(3, np.float32) if background is None
                                                  else np.asarray(background, np.float32))}
        self.lrs = {"grid": cfg.lr, "background": cfg.lr_background}
        if cfg.view_degree > 0:
            n = view_layout(cfg.view_resolution).n_entries
            shape = (n, 3 * n_coefficients(cfg.view_degree))
            self.params["view"] = torch.tensor(np.zeros(shape, np.float32) if view is None
                                               else np.asarray(view, np.float32).reshape(shape))
            self.lrs["view"] = cfg.lr
        for p in self.params.values():
            p.requires_grad_(True)
        self.moments = {k: (torch.zeros_like(p), torch.zeros_like(p)) for k, p in self.params.items()}
        self.t = 0

    def samples(self, o, d, jitter=None):
        """Stratified samples of rays o, d (R, 3): distances t (R, S), bin
        lengths delta (R,), box-normalised points u (R*S, 3), ray_valid (R,)."""
        S = int(self.cfg.n_samples)
        box_min, box_max = self.box_min_t, self.box_max_t
        d_safe = torch.where(d.abs() < 1e-9, torch.copysign(torch.tensor(1e-9), d), d)
        inv = 1.0 / d_safe
        t0, t1 = (box_min - o) * inv, (box_max - o) * inv
        t_near = torch.minimum(t0, t1).amax(1).clamp_min(0.0)
        t_far = torch.maximum(t0, t1).amin(1)
        delta = (t_far - t_near).clamp_min(0.0) * (1.0 / S)
        k = torch.arange(S, dtype=torch.float32)
        frac = k + 0.5 if jitter is None else k + jitter
        t = t_near[:, None] + frac * delta[:, None]
        p = o[:, None, :] + d[:, None, :] * t[..., None]
        u = ((p - box_min) * self.box_scale_t).reshape(-1, 3)
        return t, delta, u, t_far > t_near

    def render(self, params, o, d, jitter=None, clip=False, distortion=False):
        """Colour (R, 3), distance (R,), opacity (R,) of rays o, d (R, 3); with
        ``distortion`` also each ray's distortion loss (R,), as ours computes it."""
        cfg = self.cfg
        t, delta, u, valid = self.samples(o, d, jitter)
        R, S = t.shape
        raw = grid_lookup(params["grid"], self.layout, u).reshape(R, S, 4)
        sigma = torch.exp(torch.clamp_max(raw[..., 0] + cfg.density_bias, 15.0)) * (1.0 / self.diag)
        sigma = torch.where(valid[:, None], sigma, 0.0)
        colour = torch.sigmoid(raw[..., 1:])
        tau = sigma * delta[:, None]
        trans = torch.exp(-(torch.cumsum(tau, 1) - tau))  # exclusive prefix sum
        w = trans * (1.0 - torch.exp(-tau))
        opacity = w.sum(1)
        distance = (w * t).sum(1) / opacity.clamp_min(1e-6)
        bg = torch.sigmoid(params["background"])
        rgb = (w[..., None] * colour).sum(1) + (1.0 - opacity)[:, None] * bg
        if cfg.view_degree > 0:  # at the expected hit; neither hit nor opacity learn from it
            hit = o + d * distance.detach()[:, None]
            hu = (hit - self.box_min_t) * self.box_scale_t
            coef = grid_lookup(params["view"], view_layout(cfg.view_resolution), hu)
            n = n_coefficients(cfg.view_degree)
            residual = (coef.reshape(-1, 3, n) * sh_basis(d, cfg.view_degree)[:, None, :]).sum(2)
            rgb = rgb + opacity.detach()[:, None] * residual
            if clip:
                rgb = rgb.clamp(0.0, 1.0)
        if distortion:  # sum_ij w_i w_j |t_i - t_j| / length + sum_i w_i^2 / (3 S), in the box's length
            before_w = torch.cumsum(w, 1) - w
            before_wt = torch.cumsum(w * t, 1) - w * t
            inv_length = torch.where(delta > 0, 1.0 / (delta * S), 0.0)
            share = w * (2.0 * inv_length[:, None] * (t * before_w - before_wt) + w * (1.0 / (3 * S)))
            return rgb, distance, opacity, share.sum(1)
        return rgb, distance, opacity

    def loss(self, params, rays, idx, jitter):
        """(photometric MSE, total loss) of the rays ``idx`` of ``rays`` (dict of
        tensors: o, d, rgb, distance, hit, empty) with sample ``jitter`` (N, S)."""
        cfg = self.cfg
        N = idx.shape[0]
        out = self.render(params, rays["o"][idx], rays["d"][idx], jitter, distortion=cfg.distortion_weight > 0)
        rgb, distance, opacity = out[:3]
        mse = ((rgb - rays["rgb"][idx]) ** 2).sum() * (1.0 / (N * 3))
        loss = mse
        if cfg.distortion_weight > 0:
            loss = loss + cfg.distortion_weight / N * out[3].sum()
        if cfg.empty_weight > 0:
            loss = loss + cfg.empty_weight / N * torch.where(rays["empty"][idx], opacity ** 2, 0.0).sum()
        if cfg.distance_weight > 0:
            diag2 = float(np.sum((self.box_max - self.box_min) ** 2))
            err = torch.where(rays["hit"][idx], distance - rays["distance"][idx], 0.0)
            loss = loss + cfg.distance_weight / (diag2 * N) * (err ** 2).sum()
        return mse, loss

    def adam(self, params, grads, moments, scales):
        """Dr.Jit's Adam update of every parameter, in place; ``scales``: each
        parameter's ``-lr sqrt(1 - b2^t) / (1 - b1^t)`` (0-d tensors: no recompiles)."""
        cfg = self.cfg
        with torch.no_grad():
            for key, p in params.items():
                m, v = moments[key]
                g = grads[key]
                m.lerp_(g, 1.0 - cfg.beta_1)
                v.lerp_(g * g, 1.0 - cfg.beta_2)
                p.add_(m * torch.rsqrt(v + cfg.epsilon ** 2) * scales[key])

    def adam_scales(self):
        """The bias-corrected step sizes of the next update (float64 as Dr.Jit computes them)."""
        t = self.t + 1
        c = -np.sqrt(1.0 - self.cfg.beta_2 ** t) / (1.0 - self.cfg.beta_1 ** t)
        return {k: torch.tensor(np.float32(lr * c)) for k, lr in self.lrs.items()}


class Trainer:
    """Compiled training steps of a :class:`TorchField` on fixed rays."""

    def __init__(self, field: TorchField, rays: dict, compile: bool = True):
        self.field, self.rays = field, rays
        cfg = field.cfg
        N, S, M = int(cfg.batch_rays), int(cfg.n_samples), rays["o"].shape[0]

        def draw():
            return torch.randint(0, M, (N,)), torch.rand(N, S)

        wrap = torch.compile if compile else (lambda f: f)
        self.draw = wrap(draw)
        self.loss = wrap(field.loss)
        self.adam = wrap(field.adam)

    def step(self, idx=None, jitter=None):
        """One training step (a batch drawn unless given); returns the
        photometric MSE read back, as Ensemble.train does."""
        f = self.field
        if idx is None:
            idx, jitter = self.draw()
        mse, loss = self.loss(f.params, self.rays, idx, jitter)
        loss.backward()
        grads = {k: p.grad for k, p in f.params.items()}
        self.adam(f.params, grads, f.moments, f.adam_scales())
        f.t += 1
        for p in f.params.values():
            p.grad = None
        return float(mse.detach())


def member_state(ens: Ensemble) -> dict:
    """Member 0 of ``ens`` as the peer's starting arrays: grid, background, view (or None)."""
    view = None
    if ens.config.view_degree > 0:
        view = ens.view_numpy().reshape(-1, ens.n_members, 3 * n_coefficients(ens.config.view_degree))[:, 0]
    return dict(grid=ens.grid_numpy()[0], background=ens._numpy("background")[:3], view=view)


def peer_of(ens: Ensemble) -> TorchField:
    """A TorchField with the state of member 0 of ``ens`` (table, background, view residual)."""
    return TorchField(ens.config, ens.bbox_min, ens.bbox_max, **member_state(ens))


def restart_from(field: TorchField, ens: Ensemble):
    """Give ``field`` member 0's state of ``ens`` in place, with fresh Adam moments
    (the same tensors: its compiled steps are reused, not compiled again)."""
    with torch.no_grad():
        for key, value in member_state(ens).items():
            if value is not None:
                field.params[key].copy_(torch.tensor(np.asarray(value, np.float32)).reshape(field.params[key].shape))
        for m, v in field.moments.values():
            m.zero_()
            v.zero_()
    field.t = 0


def torch_rays(o, d, rgb, dist, hit, empty=None) -> dict:
    return dict(o=torch.tensor(o), d=torch.tensor(d), rgb=torch.tensor(rgb), distance=torch.tensor(dist),
                hit=torch.tensor(hit), empty=torch.tensor(~hit if empty is None else empty))


def check_agreement(ens: Ensemble, trainer: Trainer, rays) -> dict:
    """Ours (``ens``, untrained, one member) and the peer started from it:
    forward colours at the bin midpoints, and the first training step (our
    batch and jitter), its loss, the table's gradient and the updated table;
    also the time the peer's first step takes to compile. Raises
    AssertionError where they differ."""
    cfg, field = ens.config, trainer.field
    o, d = rays[0][::7][:cfg.batch_rays], rays[1][::7][:cfg.batch_rays]
    ours = ens.render(o, d)
    with torch.no_grad():
        rgb, dist, opac = trainer.field.render(field.params, torch.tensor(o), torch.tensor(d),
                                               clip=True)
    colour_err = float(np.abs(ours["rgb"][0] - rgb.numpy()).max())
    opacity_err = float(np.abs(ours["opacity"][0] - opac.numpy()).max())

    idx, jitter = ens._batch()
    idx = torch.tensor(np.array(idx, np.int64))
    jitter = torch.tensor(np.array(jitter, np.float32).reshape(cfg.batch_rays, cfg.n_samples))
    t0 = time.perf_counter()  # our first step traces its kernels (compiled, or read from Dr.Jit's cache)
    mse, loss = ens.training_loss()
    dr.backward(loss)
    grad_ours = np.array(dr.grad(ens._opt["grid"]), np.float64).reshape(-1, 4)
    ens.optimizer_step()
    dr.eval(ens.params().grid)
    ours_first_s = time.perf_counter() - t0
    ours_loss = float(np.array(dr.detach(loss))[0])
    t0 = time.perf_counter()  # the peer's first step compiles its loss, the loss's backward pass and Adam
    p_mse, p_loss = trainer.loss(field.params, trainer.rays, idx, jitter)
    p_loss.backward()
    grad_peer = field.params["grid"].grad.double().numpy()
    trainer.adam(field.params, {k: p.grad for k, p in field.params.items()}, field.moments, field.adam_scales())
    compile_s = time.perf_counter() - t0
    for p in field.params.values():
        p.grad = None
    grad_err = float(np.linalg.norm(grad_ours - grad_peer) / np.linalg.norm(grad_ours))
    # Where the gradient is not tiny, Adam's first update is about -lr sign(g) in both.
    firm = np.abs(grad_ours) > 1e-3 * np.abs(grad_ours).max()
    step_err = float(np.abs(ens.grid_numpy()[0] - field.params["grid"].detach().numpy())[firm].max())
    out = dict(max_colour_error=colour_err, max_opacity_error=opacity_err, loss_ours=ours_loss,
               loss_peer=float(p_loss.detach()), mse_ours=float(np.array(dr.detach(mse))[0]),
               mse_peer=float(p_mse.detach()),
               grid_gradient_relative_error=grad_err, first_update_max_error=step_err, peer_compile_s=compile_s,
               ours_first_step_s=ours_first_s)
    assert colour_err < 1e-4 and opacity_err < 1e-4, out
    assert abs(out["loss_ours"] - out["loss_peer"]) < 1e-5 * max(1.0, abs(out["loss_ours"])), out
    assert grad_err < 1e-3 and step_err < 1e-5, out
    return out


def time_in_turns(cfg: FieldConfig, rays, trainer: Trainer, blocks: int, steps: int, warmup: int, seed=0) -> dict:
    """Step times (s) of ours and the peer, from the same start, in alternating blocks of ``steps``."""
    ens = Ensemble(*BOX, n_members=1, config=cfg, seed=seed)
    ens.set_rays(*rays)
    restart_from(trainer.field, ens)
    t0 = time.perf_counter()
    trainer.step()  # compiles the batch draw
    compile_s = time.perf_counter() - t0
    for _ in range(warmup):
        trainer.step()
        ens.train(1)
    times = {"ours": [], "peer": []}
    losses = {"ours": [], "peer": []}
    for _ in range(blocks):
        for name in ("ours", "peer"):
            for _ in range(steps):
                t0 = time.perf_counter()
                value = float(ens.train(1)[0]) if name == "ours" else trainer.step()
                times[name].append(time.perf_counter() - t0)
                losses[name].append(value)
    return dict(times=times, losses=losses, peer_draw_compile_s=compile_s)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="fast", help="field preset (fast, default)")
    ap.add_argument("--width", type=int, default=None, help="image width the preset's grid follows (default: 200)")
    ap.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                    help="a FieldConfig option over the preset's (repeatable)")
    ap.add_argument("--blocks", type=int, default=4, help="turns of each")
    ap.add_argument("--steps", type=int, default=10, help="timed steps per block")
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--out", default="benchmarks/results/peer_torch.json")
    args = ap.parse_args(argv)

    width = args.width if args.width is not None else (64 if args.preset == "fast" else 200)
    try:
        cfg = FieldConfig.preset(args.preset, width=width)
        cfg = FieldConfig.from_options(args.set, **{**cfg.to_dict(), "occupancy_resolution": 0})
    except UserError as exc:
        ap.error(str(exc))
    if cfg.occupancy_resolution > 0:
        ap.error("the peer evaluates every sample: leave occupancy_resolution at 0")
    if cfg.occlusion_weight > 0 or cfg.random_background or cfg.contraction or cfg.background_resolution \
            or cfg.anneal_steps or cfg.coherent_batches:
        ap.error("the peer has no occlusion penalty, random background, contraction, directional background, "
                 "annealing or coherent batches: leave them off")
    threads = dr.thread_count()
    torch.set_num_threads(threads)
    rays = synthetic_rays()
    print(f"{args.preset} at {width} px: {cfg.n_levels} levels, {cfg.n_samples} samples, "
          f"{cfg.batch_rays} rays; {threads} threads; torch {torch.__version__}")

    ens = Ensemble(*BOX, n_members=1, config=cfg, seed=0)
    ens.set_rays(*rays)
    trainer = Trainer(peer_of(ens), torch_rays(*rays))
    check = check_agreement(ens, trainer, rays)
    print("agreement: colours within {max_colour_error:.2g}, first loss {loss_ours:.6g} / {loss_peer:.6g}, "
          "gradient relative error {grid_gradient_relative_error:.2g}, first update within "
          "{first_update_max_error:.2g}".format(**check))

    run = time_in_turns(cfg, rays, trainer, args.blocks, args.steps, args.warmup)
    samples = cfg.batch_rays * cfg.n_samples
    result = dict(preset=args.preset, width=width, config=cfg.to_dict(), threads=threads,
                  torch=torch.__version__, drjit=dr.__version__, machine=platform.processor() or platform.machine(),
                  cpu_count=os.cpu_count(), load_average=os.getloadavg(), agreement=check,
                  peer_compile_s=check["peer_compile_s"] + run["peer_draw_compile_s"],
                  blocks=args.blocks, steps_per_block=args.steps, warmup=args.warmup)
    for name in ("ours", "peer"):
        t = run["times"][name]
        med = statistics.median(t)
        blocks = [statistics.median(t[i:i + args.steps]) * 1e3 for i in range(0, len(t), args.steps)]
        result[name] = dict(step_ms_median=med * 1e3, step_ms_min=min(t) * 1e3, block_medians_ms=blocks,
                            ray_samples_per_s=samples / med, last_mse=run["losses"][name][-1])
        print(f"{name}: step {med * 1e3:.1f} ms (median of {len(t)}; blocks "
              f"{', '.join(f'{b:.1f}' for b in blocks)} ms), {samples / med / 1e6:.2f} M ray-samples/s")
    result["peer_over_ours_step_time"] = result["peer"]["step_ms_median"] / result["ours"]["step_ms_median"]
    print(f"peer / ours step time: {result['peer_over_ours_step_time']:.2f}; peer compile "
          f"{result['peer_compile_s']:.1f} s, our first step {check['ours_first_step_s']:.1f} s")

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    merged = json.loads(out.read_text()) if out.exists() else {}
    merged[f"{args.preset}_{width}px"] = result
    out.write_text(json.dumps(merged, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
