"""Empty-space skipping (occupancy grid) and the empty-ray loss."""

import numpy as np
import pytest

import mitsuba_active  # noqa: F401  (variant first)
import drjit as dr
import mitsuba as mi

from mitsuba_active.errors import UserError
from mitsuba_active.field import Ensemble, FieldConfig, compact, render
from mitsuba_active.field.regularisers import ray_regularisers
from mitsuba_active.field.render import render_flat, render_members
from mitsuba_active.rigs import fibonacci_directions
from tests.test_field import BOX, camera_rays, psnr, tiny_config, views

FOUR_SIDES = [[0.0, 0.3, 2.2], [2.2, 0.3, 0.0], [0.0, 2.2, 0.3], [-2.2, 0.3, 0.0]]
SKIPPING = dict(n_levels=3, lr=0.1, distance_weight=1.0, empty_weight=1.0, occupancy_resolution=16,
                occupancy_warmup=32, occupancy_interval=8)


def cell_radii(ens):
    """Distance from the sphere's centre of every occupancy cell centre, [z, y, x]."""
    G = ens.config.occupancy_resolution
    idx = np.stack(np.meshgrid(*[np.arange(G)] * 3, indexing="ij"), -1)[..., ::-1]  # (x, y, z)
    p = np.asarray(ens.box_min) + (idx + 0.5) / G * np.subtract(ens.box_max, ens.box_min)
    return np.linalg.norm(p, axis=-1)


def render_without_skipping(ens, o, d, member=0):
    params = ens.params()
    params.occupancy = None
    out = render_flat(params, mi.Point3f(o.T), mi.Vector3f(d.T), member)
    return np.array(out["rgb"]).T


def test_occupancy_skips_empty_space_and_keeps_the_fit():
    train = views(FOUR_SIDES, width=24, height=24)
    ens = Ensemble(*BOX, n_members=2, config=tiny_config(**SKIPPING), seed=0)
    ens.set_rays(*train)
    ens.train(200)
    occ = ens.occupancy()
    assert occ is not None and occ.shape == (16, 16, 16)
    r = cell_radii(ens)
    # The sphere (radius 0.5) keeps its cells; the space around it is mostly
    # dropped (corners that no ray crosses keep their initial density).
    assert occ[(r > 0.42) & (r < 0.55)].mean() > 0.7
    assert occ[r > 0.8].mean() < 0.4
    assert occ.mean() < 0.5
    # Skipping drops only samples that would add nothing.
    o, d, rgb, _, hit = views([[1.5, 1.0, 1.5]], width=24, height=24)
    skipped = ens.render(o, d)["rgb"][0]
    assert psnr(skipped, render_without_skipping(ens, o, d)) > 30.0
    assert psnr(skipped[hit], rgb[hit]) > 20.0


def test_new_rays_reset_the_occupancy():
    train = views(FOUR_SIDES[:2], width=16, height=16)
    ens = Ensemble(*BOX, n_members=1, config=tiny_config(**SKIPPING), seed=0)
    ens.set_rays(*train)
    ens.train(40)
    assert ens.occupancy() is not None
    ens.set_rays(*views(FOUR_SIDES[2:], width=16, height=16))
    assert ens.occupancy() is None  # nothing skipped until the next warm-up ends
    ens.train(31)
    assert ens.occupancy() is None
    ens.train(1)
    assert ens.occupancy() is not None


def test_a_warm_up_of_zero_builds_the_grid_after_the_first_step():
    ens = Ensemble(*BOX, n_members=1, config=tiny_config(**dict(SKIPPING, occupancy_warmup=0)), seed=0)
    ens.set_rays(*views(FOUR_SIDES[:1], width=8, height=8))
    assert ens.occupancy() is None
    ens.train(1)
    assert ens.occupancy() is not None


def test_skipping_nothing_changes_neither_colours_nor_gradients():
    ens = Ensemble(*BOX, n_members=2, config=tiny_config(n_samples=16), seed=3)
    o, d = camera_rays([0.3, 0.4, 2.5], width=6, height=6)
    G = 4
    results = []
    for occupancy in (None, mi.Bool(np.ones(G ** 3, bool))):
        params = ens.params()
        params.grid = mi.Float(np.array(dr.detach(params.grid)))
        params.occupancy, params.occupancy_resolution = occupancy, G
        dr.enable_grad(params.grid)
        out = render_flat(params, mi.Point3f(o.T), mi.Vector3f(d.T), 1)
        dr.backward(dr.sum(dr.sum(out["rgb"])) + dr.sum(out["distance"]))
        results.append((np.array(out["rgb"]), np.array(dr.grad(params.grid))))
    np.testing.assert_allclose(results[0][0], results[1][0], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(results[0][1], results[1][1], rtol=1e-5, atol=1e-7)
    assert np.abs(results[1][1]).sum() > 0


def test_marches_stop_where_the_transmittance_runs_out():
    ens = Ensemble(*BOX, n_members=1, config=tiny_config(n_samples=16), seed=3)
    o, d = camera_rays([0.3, 0.4, 2.5], width=6, height=6)
    G, L = 4, ens.config.n_levels
    table = np.array(dr.detach(ens.params().grid)).reshape(-1, 4)
    table[:, 0] = (4.0 - ens.config.density_bias) / L  # an optical depth of about 1.5 a sample
    results = []
    for stop in (0.0, 1e-4):
        params = ens.params()
        params.grid = mi.Float(table.reshape(-1))
        params.occupancy, params.occupancy_resolution = mi.Bool(np.ones(G ** 3, bool)), G
        params.stop_transmittance = stop
        dr.enable_grad(params.grid)
        out = render_flat(params, mi.Point3f(o.T), mi.Vector3f(d.T), 0)
        dr.backward(dr.sum(dr.sum(out["rgb"])) + dr.sum(out["distance"]))
        results.append((np.array(out["rgb"]), np.array(out["opacity"]), np.array(dr.grad(params.grid))))
    (rgb, opacity, grad), (rgb_stop, _, grad_stop) = results
    hit = opacity > 0.5
    assert hit.sum() > 10 and (opacity[hit] > 1 - 1e-6).all()  # the rays that meet the box run out
    np.testing.assert_allclose(rgb_stop, rgb, atol=1e-3)
    np.testing.assert_allclose(grad_stop, grad, atol=1e-3 * np.abs(grad).max())
    # The corners that only samples behind the stop touch get nothing.
    assert 0 < np.count_nonzero(grad_stop) < 0.8 * np.count_nonzero(grad)


def test_the_first_steps_take_half_the_samples(monkeypatch):
    from mitsuba_active.field import ensemble as ensemble_module

    ens = Ensemble(*BOX, n_members=1, config=tiny_config(**dict(SKIPPING, coarse_steps=3, n_samples=32)), seed=0)
    ens.set_rays(*views(FOUR_SIDES[:1], width=8, height=8))
    seen = []
    real = ensemble_module.render_members

    def spy(params, *args, **kwargs):
        seen.append(params.n_samples)
        return real(params, *args, **kwargs)

    monkeypatch.setattr(ensemble_module, "render_members", spy)
    assert np.isfinite(ens.train(5)).all()
    assert seen == [16, 16, 16, 32, 32]
    assert ens.params().n_samples == 32  # renders take every sample
    with pytest.raises(UserError, match="coarse_steps"):
        tiny_config(coarse_steps=-1)


def test_save_load_keeps_the_occupancy(tmp_path):
    ens = Ensemble(*BOX, n_members=2, config=tiny_config(**SKIPPING), seed=1)
    rays = views(FOUR_SIDES[:2], width=16, height=16)
    ens.set_rays(*rays)
    ens.train(40)
    o, d = camera_rays([1.0, 1.0, 2.0], width=16, height=16)
    ens.save(tmp_path / "field.npz")
    ens2 = Ensemble.load(tmp_path / "field.npz")
    assert np.array_equal(ens2.occupancy(), ens.occupancy())
    assert np.array_equal(ens2.render(o, d)["rgb"], ens.render(o, d)["rgb"])
    # A resumed run gives the loaded ensemble back its own rays: the grid stays.
    ens2.set_rays(*rays, reset_occupancy=False)
    assert np.array_equal(ens2.occupancy(), ens.occupancy())
    ens2.set_rays(*rays)
    assert ens2.occupancy() is None


def test_a_save_during_the_warm_up_resumes_it(tmp_path):
    rays = views(FOUR_SIDES[:2], width=16, height=16)
    ens = Ensemble(*BOX, n_members=1, config=tiny_config(**SKIPPING), seed=1)
    ens.set_rays(*rays)
    ens.train(30)  # 2 steps before the warm-up (32) ends
    ens.save(tmp_path / "field.npz")
    ens2 = Ensemble.load(tmp_path / "field.npz")
    ens2.set_rays(*rays, reset_occupancy=False)
    for e in (ens, ens2):
        e.train(1)
        assert e.occupancy() is None
        e.train(1)
        assert e.occupancy() is not None
    assert np.array_equal(ens2.occupancy(), ens.occupancy())


def test_empty_ray_loss_clears_the_background():
    train = views(FOUR_SIDES[:2], width=16, height=16)
    hit = train[4]
    opacity = []
    for weight in (0.0, 1.0):
        ens = Ensemble(*BOX, n_members=1, config=tiny_config(n_levels=3, lr=0.1, empty_weight=weight), seed=0)
        ens.set_rays(*train)
        ens.train(100)
        opacity.append(ens.render(train[0], train[1])["opacity"][0][~hit].mean())
    assert opacity[1] < 0.3 * opacity[0], opacity


def test_skipping_changes_a_converged_default_render_by_less_than_half_a_decibel():
    """The default preset's field for 200-pixel images (12 levels, here hashed into a tiny table;
    skipping on a 64^3 grid), trained until it has converged: a held-out view rendered with and
    without the cells it skips scores within 0.5 dB of each other against the truth."""
    cfg = FieldConfig.preset("default", width=200, log2_table_size=12, n_samples=64, batch_rays=1024,
                             render_batch=1024, lr=0.05, occupancy_warmup=32, occupancy_interval=8)
    assert cfg.n_levels == 12 and cfg.occupancy_resolution == 64
    ens = Ensemble(*BOX, n_members=1, config=cfg, seed=0)
    ens.set_rays(*views(2.2 * fibonacci_directions(20), width=16, height=16), background=[1.0, 1.0, 1.0])
    losses = ens.train(300)
    assert losses[-20:].mean() < 0.1 * losses[:5].mean()  # measured: 0.06
    occupied = ens.occupancy()
    assert occupied is not None and occupied.mean() < 0.5  # most of the box is skipped (measured: 19 %)
    o, d, rgb, _, _ = views([[1.5, 1.0, 1.5]], width=24, height=24)
    with_skipping = psnr(ens.render(o, d)["rgb"][0], rgb)
    without = psnr(render_without_skipping(ens, o, d), rgb)
    # Measured: 22.80 dB with skipping, 23.03 dB without.
    assert abs(with_skipping - without) < 0.5, (with_skipping, without)


def _render_and_derivatives(ens, params_of, o, d, jitter, member, reg):
    """Colours, distances and opacities of a render with skipping, the grid's gradient of their
    sum (with the regularisers) and the opacity's forward derivative along a fixed tangent."""
    params = params_of()
    dr.enable_grad(params.grid)
    if member is None:
        outs = render_members(params, o, d, jitter, reg=reg)
    else:
        outs = [render_flat(params, o, d, member, jitter, reg=reg)]
    loss = sum(dr.sum(dr.squared_norm(out["rgb"]) + out["distance"] + out["opacity"] + out["regulariser"])
               for out in outs)
    dr.backward(loss)
    grad = np.array(dr.grad(params.grid))
    params = params_of()
    dr.enable_grad(params.grid)
    outs2 = render_members(params, o, d, jitter, reg=reg)
    tangent = np.random.default_rng(3).normal(size=dr.width(params.grid)).astype(np.float32)
    dr.set_grad(params.grid, mi.Float(tangent))
    dr.forward_to(outs2[0]["opacity"])
    values = [np.concatenate([np.array(out[k]).ravel() for k in ("rgb", "distance", "opacity", "regulariser")])
              for out in outs]
    return np.concatenate(values), grad, np.array(dr.grad(outs2[0]["opacity"]))


def _half_occupied_case(K: int, rng):
    """An ensemble of K members over 8x8 rays of 16 samples, and its parameters with a random
    occupancy grid of 8^3 cells (about 40 % occupied) and float32 lookups."""
    cfg = tiny_config(n_samples=16, distortion_weight=0.01, occlusion_weight=0.1, density_bias=0.0, init_scale=2.0)
    ens = Ensemble(*BOX, n_members=K, config=cfg, seed=1)
    o, d = camera_rays([0.3, 0.4, 2.5], width=8, height=8)
    o, d = mi.Point3f(o.T), mi.Vector3f(d.T)
    jitter = mi.Float(rng.uniform(size=64 * 16).astype(np.float32))
    mask = mi.Bool(rng.uniform(size=8 ** 3) < 0.4)

    def params_of():
        p = ens.params()
        p.grid = mi.Float(np.array(dr.detach(p.grid)))
        p.half_grid = None
        p.occupancy, p.occupancy_resolution = mask, 8
        return p

    return ens, params_of, o, d, jitter, cfg


def test_the_compacted_march_matches_marching_every_sample(monkeypatch):
    """Marching the occupied samples alone (render.compact_samples) gives the outputs and
    derivatives of marching every sample, skipped ones with no density."""
    rng = np.random.default_rng(0)
    for K in (1, 2):
        ens, params_of, o, d, jitter, cfg = _half_occupied_case(K, rng)
        member = None if K == 1 else mi.UInt32(np.arange(64) % K)
        compacted = _render_and_derivatives(ens, params_of, o, d, jitter, member, ray_regularisers(cfg))
        with monkeypatch.context() as m:
            m.setattr(render, "compact_samples", lambda *args, **kw: None)
            every = _render_and_derivatives(ens, params_of, o, d, jitter, member, ray_regularisers(cfg))
        for got, want in zip(compacted, every):
            assert np.abs(want).max() > 0
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


def test_the_occupancy_forgets_at_its_decay():
    """A cell's stored opacity is multiplied by occupancy_decay at every refresh: with no density
    left, a cell at 1 stays occupied (threshold 0.1) for 3 refreshes at 0.5 and 44 at 0.95."""
    for decay, refreshes in ((0.5, 3), (0.95, 44)):
        cfg = tiny_config(occupancy_resolution=4, occupancy_threshold=0.1, occupancy_decay=decay,
                          density_bias=-40.0)
        ens = Ensemble(*BOX, n_members=1, config=cfg, seed=0)
        ens._set_occupancy(dr.full(mi.Float, 1.0, 4 ** 3))
        for _ in range(refreshes):
            ens._refresh_occupancy()
        assert ens.occupancy().all()
        ens._refresh_occupancy()
        assert not ens.occupancy().any()
    for bad in (0.0, 1.5):
        with pytest.raises(UserError, match="occupancy_decay"):
            tiny_config(occupancy_decay=bad)


def test_the_rays_march_in_order_of_their_counts_with_the_same_results(monkeypatch):
    """compact.lanes_by_count puts the rays in order of their occupied samples; marching them
    in that order gives the outputs and derivatives of marching them in their own order."""
    count = mi.UInt32([3, 0, 5, 3, 1, 0, 5, 2])
    order, place = compact.lanes_by_count(count, 5)
    order, place = np.array(order), np.array(place)
    np.testing.assert_array_equal(np.sort(order), np.arange(8))
    assert (np.diff(np.array(count)[order]) >= 0).all()
    np.testing.assert_array_equal(order[place], np.arange(8))
    ens, params_of, o, d, jitter, cfg = _half_occupied_case(2, np.random.default_rng(1))
    sorted_ = _render_and_derivatives(ens, params_of, o, d, jitter, None, ray_regularisers(cfg))
    with monkeypatch.context() as m:
        m.setattr(compact, "lanes_by_count", lambda count, S: (dr.arange(mi.UInt32, dr.width(count)),) * 2)
        own = _render_and_derivatives(ens, params_of, o, d, jitter, None, ray_regularisers(cfg))
    for got, want in zip(sorted_, own):
        assert np.abs(want).max() > 0
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
