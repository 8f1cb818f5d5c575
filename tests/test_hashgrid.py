"""Tests of the grid's hash encoding: its lookups and their gradient against
NumPy references, and saving many hashed levels.

Tiny layouts (a dense level, then hashed ones), so the file runs in seconds.
"""

import numpy as np
import pytest

import mitsuba_active  # noqa: F401  (variant first)
import drjit as dr
import mitsuba as mi

from mitsuba_active.field import Ensemble, FieldConfig
from mitsuba_active.field.grid import GridLayout, accumulate, query

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


def test_table_gradient_matches_finite_differences_and_the_adjoint():
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
    # The adjoint the marched renderer scatters with gives the same.
    values = [mi.Float(c[k, ch]) for k in range(K) for ch in range(4)]
    plain = dr.zeros(mi.Float, table.size)
    accumulate(plain, layout, K, u, values)
    np.testing.assert_allclose(np.array(plain), grad, rtol=1e-5, atol=1e-5)


def test_many_levels_save_and_load(tmp_path):
    cfg = FieldConfig(n_levels=12, base_resolution=4, per_level_scale=1.3, log2_table_size=9, n_samples=16,
                      batch_rays=256, render_batch=256)
    assert sum(not d for d in GridLayout.from_config(cfg).dense) >= 6
    a = views([[0.0, 0.3, 2.2]], width=12, height=12)
    ens = Ensemble(*BOX, n_members=2, config=cfg, seed=1)
    ens.set_rays(*a)
    ens.train(3)
    path = ens.save(tmp_path / "many.npz")
    back = Ensemble.load(path)
    assert back.config == cfg
    np.testing.assert_array_equal(back.grid_numpy(), ens.grid_numpy())
    np.testing.assert_array_equal(back.render(a[0][:30], a[1][:30])["rgb"], ens.render(a[0][:30], a[1][:30])["rgb"])
    # Both carry on alike (the moments came back too).
    back.set_rays(*a, reset_occupancy=False)
    np.testing.assert_allclose(back.train(2), ens.train(2), rtol=1e-5)
