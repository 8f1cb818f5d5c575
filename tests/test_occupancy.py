"""Empty-space skipping (occupancy grid) and the empty-ray loss."""

import numpy as np

import mitsuba_active  # noqa: F401  (variant first)
import drjit as dr
import mitsuba as mi

from mitsuba_active.field import Ensemble, FieldConfig
from mitsuba_active.field.render import render_flat
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
    assert losses[-20:].mean() < 0.05 * losses[:5].mean()  # measured: 0.02
    occupied = ens.occupancy()
    assert occupied is not None and occupied.mean() < 0.5  # most of the box is skipped (measured: 17 %)
    o, d, rgb, _, _ = views([[1.5, 1.0, 1.5]], width=24, height=24)
    with_skipping = psnr(ens.render(o, d)["rgb"][0], rgb)
    without = psnr(render_without_skipping(ens, o, d), rgb)
    # Measured: 24.31 dB with skipping, 24.27 dB without.
    assert abs(with_skipping - without) < 0.5, (with_skipping, without)
