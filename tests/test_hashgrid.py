"""Tests of the many-level grid: hash encoding, its gradient, the lazy Adam,
coarse-to-fine annealing and saving many levels.

NumPy references on tiny layouts (a dense level, then hashed ones), so the
file runs in seconds.
"""

import json

import numpy as np
import pytest

import mitsuba_active  # noqa: F401  (variant first)
import drjit as dr
import mitsuba as mi

from mitsuba_active.field import Ensemble, FieldConfig
from mitsuba_active.field import lazy_adam
from mitsuba_active.field.grid import GridLayout, accumulate, query
from mitsuba_active.field.lazy_adam import GridGradient, LazyAdam

from .test_field import BOX, views

#: Three levels (2, 4, 8 cells): the first dense (27 vertices), the others hashed into 32 entries.
HASHED = FieldConfig(n_levels=3, base_resolution=2, per_level_scale=2.0, log2_table_size=5, n_samples=16,
                     batch_rays=256, render_batch=256)
PRIMES = (1, 2654435761, 805459861)


def reference_query(table, layout, u):
    """Summed trilinear features, NumPy: table (E, K, 4), u (N, 3) -> (K, N, 4)."""
    u = np.clip(np.asarray(u, np.float64), 0.0, 1.0)
    out = np.zeros((table.shape[1], len(u), 4))
    for level, r in enumerate(layout.resolutions):
        x = u * r
        x0 = np.minimum(np.floor(x), r - 1).astype(np.int64)
        f = x - x0
        for corner in range(8):
            bits = np.array([(corner >> a) & 1 for a in range(3)])
            c = x0 + bits
            w = np.prod(np.where(bits, f, 1.0 - f), axis=1)
            if layout.dense[level]:
                idx = c[:, 0] + c[:, 1] * (r + 1) + c[:, 2] * (r + 1) ** 2
            else:
                h = [(c[:, a].astype(np.uint64) * np.uint64(PRIMES[a])) & np.uint64(0xFFFFFFFF) for a in range(3)]
                idx = ((h[0] ^ h[1] ^ h[2]) & np.uint64(layout.sizes[level] - 1)).astype(np.int64)
            out += w[None, :, None] * np.transpose(table[idx + layout.offsets[level]], (1, 0, 2))
    return out


def random_table(layout, K, seed=0):
    return np.random.default_rng(seed).normal(size=(layout.n_entries, K, 4)).astype(np.float32)


def test_layout_has_dense_then_hashed_levels():
    layout = GridLayout.from_config(HASHED)
    assert layout.dense == (True, False, False)
    assert layout.sizes == (27, 32, 32) and layout.offsets == (0, 27, 59)


@pytest.mark.parametrize("K", [1, 3])
def test_query_matches_numpy_reference(K):
    layout = GridLayout.from_config(HASHED)
    table = random_table(layout, K)
    u = np.random.default_rng(1).uniform(-0.05, 1.05, (200, 3))  # some outside: clamped to the border
    got = query(mi.Float(table.ravel()), layout, K, mi.Point3f(u.T.astype(np.float32)))
    ref = reference_query(table, layout, u)
    for k in range(K):
        np.testing.assert_allclose(np.array(got[k]).T, ref[k], rtol=1e-5, atol=1e-5)
    # One member per point reads that member's slice.
    member = np.arange(200) % K
    one = np.array(query(mi.Float(table.ravel()), layout, K, mi.Point3f(u.T.astype(np.float32)),
                         mi.UInt32(member))).T
    np.testing.assert_allclose(one, ref[member, np.arange(200)], rtol=1e-5, atol=1e-5)


def test_level_weights_scale_each_level():
    layout = GridLayout.from_config(HASHED)
    table = random_table(layout, 1)
    u = np.random.default_rng(2).uniform(0, 1, (50, 3))
    weights = (1.0, 0.25, 0.0)
    got = np.array(query(mi.Float(table.ravel()), layout, 1, mi.Point3f(u.T.astype(np.float32)), None, True,
                         tuple(dr.opaque(mi.Float, w) for w in weights))[0]).T
    ref = 0.0
    for level, w in enumerate(weights):
        only = np.zeros_like(table)
        lo, n = layout.offsets[level], layout.sizes[level]
        only[lo:lo + n] = table[lo:lo + n]
        ref = ref + w * reference_query(only, layout, u)[0]
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)


def test_table_gradient_matches_finite_differences_and_the_split_sink(monkeypatch):
    K = 2
    layout = GridLayout.from_config(HASHED)
    rng = np.random.default_rng(3)
    table = random_table(layout, K)
    u = mi.Point3f(rng.uniform(0, 1, (64, 3)).T.astype(np.float32))
    c = rng.normal(size=(K, 4, 64)).astype(np.float32)

    def loss(t):
        raws = query(t, layout, K, u)
        return dr.sum(sum(dr.sum(raws[k][ch] * mi.Float(c[k, ch])) for k in range(K) for ch in range(4)))

    t = mi.Float(table.ravel())
    dr.enable_grad(t)
    dr.backward(loss(t))
    grad = np.array(dr.grad(t))
    # The loss is linear in the table: central differences are exact up to rounding.
    eps = 0.5
    for i in np.random.default_rng(4).choice(table.size, 25, replace=False):
        plus, minus = table.ravel().copy(), table.ravel().copy()
        plus[i] += eps
        minus[i] -= eps
        fd = (float(loss(mi.Float(plus))[0]) - float(loss(mi.Float(minus))[0])) / (2 * eps)
        assert grad[i] == pytest.approx(fd, rel=1e-3, abs=1e-3)
    # The adjoint the marched renderer uses gives the same, into a plain array and into the two-part sink.
    values = [mi.Float(c[k, ch]) for k in range(K) for ch in range(4)]
    plain = dr.zeros(mi.Float, table.size)
    accumulate(plain, layout, K, u, values)
    np.testing.assert_allclose(np.array(plain), grad, rtol=1e-5, atol=1e-5)
    monkeypatch.setattr(lazy_adam, "EXPAND_ENTRIES", 30)  # the dense level small, the hashed ones large
    sink = GridGradient(layout, K)
    assert sink.split == 27
    accumulate(sink, layout, K, u, values)
    np.testing.assert_allclose(np.concatenate([np.array(sink.small), np.array(sink.large)]), grad,
                               rtol=1e-5, atol=1e-5)


def numpy_lazy_adam(p, m, v, g, t, lr, b1, b2, eps):
    """One lazy Adam step, NumPy float64: floats with g == 0 keep p, m and v."""
    m2 = b1 * m + (1 - b1) * g
    v2 = b2 * v + (1 - b2) * g * g
    p2 = p - lr * np.sqrt(1 - b2 ** t) / (1 - b1 ** t) * m2 / np.sqrt(v2 + eps ** 2)
    keep = g == 0
    return np.where(keep, p, p2), np.where(keep, m, m2), np.where(keep, v, v2)


@pytest.mark.parametrize("dense", [False, True])
def test_lazy_adam_matches_numpy_adam_and_leaves_untouched_entries(monkeypatch, dense):
    K = 2
    monkeypatch.setattr(lazy_adam, "EXPAND_ENTRIES", 30)
    layout = GridLayout.from_config(HASHED)
    rng = np.random.default_rng(5)
    p = rng.normal(size=layout.n_entries * K * 4)
    opt = LazyAdam(p.astype(np.float32), layout, K, lr=0.05, beta_1=0.9, beta_2=0.99, epsilon=1e-8)
    m, v = np.zeros_like(p), np.zeros_like(p)
    split = opt.gradient.split * K * 4
    for t in range(1, 4):
        g = np.where(rng.uniform(size=p.size) < 0.3, rng.normal(size=p.size), 0.0).astype(np.float32)
        g[:4] = 0.0  # an entry of the small part and one of the large that no step touches
        g[split:split + 4] = 0.0
        param = opt.param()
        if dense:  # a gradient of Dr.Jit's own: the dense update
            dr.backward(dr.sum(param * mi.Float(g)))
        else:  # the marched renderer's: into the sinks
            opt.gradient.small = mi.Float(g[:split])
            opt.gradient.large = mi.Float(g[split:])
            opt.gradient.touched = mi.Bool((g[split:].reshape(-1, K * 4) != 0).any(axis=1))
        opt.step()
        p, m, v = numpy_lazy_adam(p, m, v, g.astype(np.float64), t, 0.05, 0.9, 0.99, 1e-8)
        np.testing.assert_allclose(np.array(opt.table), p, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(np.array(opt.m), m, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(np.array(opt.v), v, rtol=1e-5, atol=1e-9)
        # The sinks are at zero again for the next step.
        assert not np.array(opt.gradient.small).any() and not np.array(opt.gradient.large).any()
        assert not np.array(opt.gradient.touched).any()
    start = np.random.default_rng(5).normal(size=p.size).astype(np.float32)
    table = np.array(opt.table)
    assert np.array_equal(table[:4], start[:4]) and np.array_equal(table[split:split + 4], start[split:split + 4])
    assert not np.array(opt.m)[:4].any()


def test_training_with_the_sinks_equals_dense_adam_steps(monkeypatch):
    """The marched renderer's sinks and Dr.Jit's gradient give the same steps."""
    monkeypatch.setattr(lazy_adam, "EXPAND_ENTRIES", 30)
    a = views([[0.0, 0.3, 2.2], [2.0, 0.5, -0.8]], width=12, height=12)
    results = []
    for sink in (True, False):
        ens = Ensemble(*BOX, n_members=2, config=HASHED, seed=0)
        ens.set_rays(*a)
        for _ in range(3):
            mse, loss = ens.training_loss()
            if not sink:  # a term of Dr.Jit's own (of zero gradient, but it forces the dense path)
                grid = ens.params().grid
                loss = loss + dr.sum(grid * mi.Float(np.zeros(dr.width(grid), np.float32)))
            dr.backward(loss)
            ens.optimizer_step()
        results.append(ens.grid_numpy())
    np.testing.assert_allclose(results[0], results[1], rtol=1e-4, atol=1e-5)


def annealed(steps=8, **kw):
    return FieldConfig(**{**HASHED.to_dict(), "anneal_steps": steps, **kw})


def test_annealing_weights_ramp_coarse_to_fine():
    ens = Ensemble(*BOX, n_members=1, config=annealed(8), seed=0)
    assert ens.level_weights().tolist() == [1.0, 0.0, 0.0]
    ens._step = 2
    np.testing.assert_allclose(ens.level_weights(), [1.0, 0.5, 0.0])
    ens._step = 6
    np.testing.assert_allclose(ens.level_weights(), [1.0, 1.0, 0.5])
    ens._step = 8
    assert ens.level_weights().tolist() == [1.0, 1.0, 1.0] and ens.params().level_weights is None
    assert Ensemble(*BOX, n_members=1, config=HASHED, seed=0).params().level_weights is None


def test_annealing_gives_fine_levels_no_gradient_at_first_and_renders_with_the_weights():
    a = views([[0.0, 0.3, 2.2]], width=12, height=12)
    o, d = a[0][:40], a[1][:40]
    on = Ensemble(*BOX, n_members=2, config=annealed(1000), seed=0)
    off = Ensemble(*BOX, n_members=2, config=HASHED, seed=0)
    layout = on.layout
    before = [e.grid_numpy().copy() for e in (on, off)]
    for e in (on, off):
        e.set_rays(*a)
        e.train(1)
    moved = [(e.grid_numpy() - b)[:, layout.offsets[1]:] for e, b in zip((on, off), before)]  # levels 1, 2
    assert not moved[0].any() and moved[1].any()
    # Rendering at step 0 reads the coarse level alone: as a field whose fine levels are 0.
    fresh = Ensemble(*BOX, n_members=2, config=annealed(1000), seed=0)
    plain = Ensemble(*BOX, n_members=2, config=HASHED, seed=0)
    grid = fresh.grid_numpy()
    grid[:, layout.offsets[1]:] = 0.0
    plain._make_optimizer(grid, plain._numpy("background").reshape(2, 3))
    np.testing.assert_allclose(fresh.render(o, d)["rgb"], plain.render(o, d)["rgb"], rtol=1e-5, atol=1e-6)
    assert not np.allclose(fresh.render(o, d)["rgb"], Ensemble(*BOX, n_members=2, config=HASHED,
                                                               seed=0).render(o, d)["rgb"], atol=1e-4)


def test_many_levels_save_and_load(tmp_path):
    cfg = FieldConfig(n_levels=12, base_resolution=4, per_level_scale=1.3, log2_table_size=9, n_samples=16,
                      batch_rays=256, render_batch=256, anneal_steps=4)
    assert sum(not d for d in GridLayout.from_config(cfg).dense) >= 6
    a = views([[0.0, 0.3, 2.2]], width=12, height=12)
    ens = Ensemble(*BOX, n_members=2, config=cfg, seed=1)
    ens.set_rays(*a)
    ens.train(3)
    path = ens.save(tmp_path / "many.npz")
    back = Ensemble.load(path)
    assert back.config == cfg and back._step == 3 and back._grid_opt.t == 3
    np.testing.assert_array_equal(back.grid_numpy(), ens.grid_numpy())
    np.testing.assert_array_equal(back.render(a[0][:30], a[1][:30])["rgb"], ens.render(a[0][:30], a[1][:30])["rgb"])
    # Both carry on alike (the moments came back too).
    back.set_rays(*a, reset_occupancy=False)
    np.testing.assert_allclose(back.train(2), ens.train(2), rtol=1e-5)
    # A file written before annealing existed (no anneal_steps in its config) still loads.
    with np.load(path) as z:
        old = dict(z)
    config = json.loads(str(old["config"]))
    del config["anneal_steps"]
    old["config"] = np.array(json.dumps(config))
    np.savez(tmp_path / "old.npz", **old)
    assert Ensemble.load(tmp_path / "old.npz").config.anneal_steps == 0


def test_skipping_waits_for_annealing():
    a = views([[0.0, 0.3, 2.2]], width=8, height=8)
    ens = Ensemble(*BOX, n_members=1, config=annealed(6, occupancy_resolution=8, occupancy_warmup=1,
                                                      occupancy_interval=1), seed=0)
    ens.set_rays(*a)
    ens.train(5)
    assert ens.occupancy() is None
    ens.train(1)
    assert ens.occupancy() is not None
