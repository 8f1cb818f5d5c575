"""Tests of the grid's hash encoding: its lookups and their gradient against
NumPy references, saving many hashed levels, coarse-to-fine annealing and
the coherent training batches.

Tiny layouts (a dense level, then hashed ones), so the file runs in seconds.
"""

import dataclasses

import numpy as np
import pytest

import mitsuba_active  # noqa: F401  (variant first)
import drjit as dr
import mitsuba as mi

from mitsuba_active.field import Ensemble, FieldConfig
from mitsuba_active.field.grid import GridLayout, accumulate, half_table, query
from mitsuba_active.field.render import render_flat, render_members

from .test_field import BOX, camera_rays, views

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


def test_stratified_indices_give_every_ray_equal_odds_within_its_lane_stratum():
    """Lane i draws floor((i + u) M / N): over every distinct draw u of every lane
    each of the M rays comes up exactly N times, and lane i only within its stratum."""
    from mitsuba_active.field.batch import stratified_indices

    N, M = 8, 21
    counts = np.zeros(M, np.int64)
    for r in range(M):  # u = ceil(r 2^32 / M) makes mul_hi(u, M) = r exactly
        u = mi.UInt32(np.full(N, -(-(r << 32) // M), np.uint64).astype(np.uint32))
        idx = np.array(stratified_indices(N, dr.opaque(mi.UInt32, M), u))
        lane = np.arange(N)
        assert np.all(idx >= lane * M // N) and np.all(idx <= ((lane + 1) * M - 1) // N)
        assert np.all(np.diff(idx) >= 0)
        counts += np.bincount(idx, minlength=M)
    np.testing.assert_array_equal(counts, np.full(M, N))


def test_ray_order_groups_each_camera_and_keeps_neighbouring_directions_close():
    from mitsuba_active.field.batch import ray_order

    o, d = views([[0.0, 0.3, 2.2], [2.2, 0.3, 0.0], [0.0, 2.2, 0.3]], width=16, height=16)[:2]
    shuffle = np.random.default_rng(0).permutation(len(o))
    o, d = o[shuffle], d[shuffle]
    order = ray_order(o, d)
    assert order.dtype == np.uint32 and np.array_equal(np.sort(order), np.arange(len(o)))
    cams = np.unique(o[order], axis=0, return_inverse=True)[1].ravel()
    assert np.count_nonzero(np.diff(cams)) == 2  # each camera's rays in one run
    step = np.linalg.norm(np.diff(d[order], axis=0), axis=1)[np.diff(cams) == 0]
    shuffled = np.linalg.norm(np.diff(d, axis=0), axis=1)
    assert np.median(step) < 0.25 * np.median(shuffled)


def test_coherent_batches_train_and_rerun_alike():
    cfg = FieldConfig(n_levels=3, base_resolution=4, log2_table_size=9, n_samples=16, batch_rays=128,
                      render_batch=256, lr=0.1, coherent_batches=1)
    a = views([[0.0, 0.3, 2.2], [2.2, 0.3, 0.0]], width=12, height=12)
    runs = []
    for _ in range(2):
        ens = Ensemble(*BOX, n_members=2, config=cfg, seed=3)
        ens.set_rays(*a)
        runs.append(ens.train(30))
    np.testing.assert_allclose(runs[0], runs[1], rtol=1e-4)  # equal up to the threads' summation order
    assert runs[0][-5:].mean() < 0.5 * runs[0][:5].mean()
    # One step's rays come in the sorted order, one from each stratum.
    idx, _ = ens._batch()
    pos = np.argsort(np.array(ens._rays["order"]))[np.array(idx)]
    lane, M = np.arange(128), len(a[0])
    assert np.all(pos >= lane * M // 128) and np.all(pos <= ((lane + 1) * M - 1) // 128)


def test_annealing_masks_the_fine_levels_early_and_not_later():
    from mitsuba_active.field.grid import anneal_weights

    np.testing.assert_allclose(anneal_weights(3, 100, 0), [1, 0, 0])
    np.testing.assert_allclose(anneal_weights(3, 100, 75), [1, 1, 0.5])
    np.testing.assert_allclose(anneal_weights(3, 100, 100), [1, 1, 1])
    cfg = dataclasses.replace(HASHED, anneal_steps=20, lr=0.1)
    ens = Ensemble(*BOX, n_members=1, config=cfg, seed=0)
    ens.set_rays(*views([[0.0, 0.3, 2.2]], width=8, height=8))
    table = ens.grid_numpy()
    layout = ens.params().layout
    u = mi.Point3f(np.random.default_rng(1).uniform(size=(3, 50)).astype(np.float32))
    # At step 0 the fine levels' entries change nothing (and get no gradient).
    coarse_only = table.copy()
    coarse_only[:, ens.layout.offsets[1]:] = 0.0
    early = np.array(query(mi.Float(table.ravel()), layout, 1, u, 0))
    np.testing.assert_allclose(early, np.array(query(mi.Float(coarse_only.ravel()), ens.layout, 1, u, 0)),
                               atol=1e-6)
    grad = dr.zeros(mi.Float, table.size)
    accumulate(grad, layout, 1, u, [mi.Float(1.0)] * 4, 0)
    assert np.all(np.array(grad)[ens.layout.offsets[1] * 4:] == 0) and np.any(np.array(grad) != 0)
    ens.train(20)
    assert ens.params().layout.weights is None
    late = np.array(query(mi.Float(table.ravel()), ens.params().layout, 1, u, 0))
    assert np.abs(late - early).max() > 1e-3


def test_half_lookups_match_the_numpy_reference_to_float16_precision():
    """Lookups of a table's float16 copy sum the rounded features in float32:
    within float16's rounding of the reference, and not the float32 sums."""
    K = 3
    layout = GridLayout.from_config(HASHED)
    table = random_table(layout, K)
    u = np.random.default_rng(1).uniform(0.0, 1.0, (200, 3))
    half = half_table(mi.Float(table.ravel()))
    assert dr.type_v(half) == dr.VarType.Float16
    got = query(half, layout, K, mi.Point3f(u.T.astype(np.float32)))
    ref = reference_query(table, layout, u)
    rounded = reference_query(table.astype(np.float16).astype(np.float32), layout, u)
    for k in range(K):
        np.testing.assert_allclose(np.array(got[k]).T, rounded[k], rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(np.array(got[k]).T, ref[k], atol=5e-3)
    assert np.abs(np.array(got[0]).T - ref[0]).max() > 1e-6  # it did read the rounded copy
    member = np.arange(200) % K
    one = np.array(query(half, layout, K, mi.Point3f(u.T.astype(np.float32)), mi.UInt32(member))).T
    np.testing.assert_allclose(one, rounded[member, np.arange(200)], rtol=1e-5, atol=1e-5)


def test_an_ensemble_looks_up_the_float16_copy_of_its_current_table():
    """Each Adam step writes the lookups' float16 copy of the new table; a table
    put in its place (as finite differences do) is looked up as it is, and
    lookups that trace derivatives read the float32 table."""
    rays = views([[0.0, 0.3, 2.2], [2.2, 0.3, 0.0]], width=8, height=8)
    cfg = dataclasses.replace(HASHED, batch_rays=64)
    ens = Ensemble(*BOX, n_members=2, config=cfg, seed=0)
    ens.set_rays(*rays)
    for _ in range(2):
        ens.train(1)
        params = ens.params()
        assert params.lookup_table() is params.grid  # the step's own lookups differentiate it
        with dr.suspend_grad():
            table = params.lookup_table()
            assert dr.type_v(table) == dr.VarType.Float16
            np.testing.assert_array_equal(np.array(table, np.float32),
                                          np.array(params.grid, np.float32).astype(np.float16).astype(np.float32))
            params.grid = mi.Float(np.array(params.grid))
            assert params.lookup_table() is params.grid
    # Rendered with float32 lookups instead, the colours differ by float16's rounding of the features.
    o, d = mi.Point3f(rays[0][::7].T), mi.Vector3f(rays[1][::7].T)
    with dr.suspend_grad():
        params = ens.params()
        half = [np.array(out["rgb"]) for out in render_members(params, o, d)]
        full = [np.array(out["rgb"]) for out in render_members(dataclasses.replace(params, half_grid=None), o, d)]
    np.testing.assert_allclose(half, full, atol=2e-3)
    assert np.abs(np.subtract(half, full)).max() > 0


def test_dense_layouts_and_small_tables_keep_one_level_group():
    from mitsuba_active.field.grid import level_groups

    budget = 3 << 19
    dense = GridLayout.from_config(FieldConfig(n_levels=2))
    assert level_groups(dense, 64 * 16, budget) == [range(0, 2)]
    hashed = GridLayout.from_config(FieldConfig(n_levels=12, base_resolution=16, per_level_scale=1.2,
                                                log2_table_size=15))
    groups = level_groups(hashed, 16, budget)
    assert 1 < len(groups) < 12 and [lv for g in groups for lv in g] == list(range(12))
    assert len(level_groups(hashed, 64, budget)) > len(groups)
    assert level_groups(hashed, 64, budget, 6) == [range(2 * g, 2 * g + 2) for g in range(6)]
    assert level_groups(GridLayout.from_config(HASHED), 16, budget) == [range(0, 3)]


def test_half_lookups_level_group_by_level_group_match_the_reference(monkeypatch):
    """Lookups of a table too large for one level group sum each group's levels
    in lanes of their own and add the partial sums: the same features."""
    from mitsuba_active.field import grid

    K = 2
    layout = GridLayout.from_config(dataclasses.replace(HASHED, n_levels=4))
    table = random_table(layout, K)
    u = np.random.default_rng(5).uniform(-0.05, 1.05, (100, 3))
    active = np.arange(100) % 7 != 3
    monkeypatch.setattr(grid, "LOOKUP_GROUP_BYTES", 16)
    # At most half as many groups as levels.
    assert grid.level_groups(layout, 8 * K, grid.LOOKUP_GROUP_BYTES, 2) == [range(0, 2), range(2, 4)]
    got = query(half_table(mi.Float(table.ravel())), layout, K, mi.Point3f(u.T.astype(np.float32)), None,
                mi.Bool(active))
    rounded = reference_query(table.astype(np.float16).astype(np.float32), layout, u)
    for k in range(K):
        np.testing.assert_allclose(np.array(got[k]).T, np.where(active[:, None], rounded[k], 0.0),
                                   rtol=1e-5, atol=1e-5)
