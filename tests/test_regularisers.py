"""Tests of the few-view regularisers: distortion, near-camera occlusion, random backgrounds, grid smoothness."""

import numpy as np
import pytest

import mitsuba_active  # noqa: F401  (variant first)
import drjit as dr
import mitsuba as mi

from mitsuba_active.errors import UserError
from mitsuba_active.field import Ensemble, FieldConfig, VariationalField
from mitsuba_active.field import render
from mitsuba_active.field.grid import GridLayout
from mitsuba_active.field.regularisers import grid_smoothness, occlusion_samples, ray_regularisers
from tests.test_field import BOX, _composite_inputs, camera_rays, outputs_and_derivatives, tiny_config, views

S, BIAS, DIAG = 16, -1.0, 1.5


def numpy_regularisers(raw, t, delta, valid, reg):
    """Distortion (the O(S^2) double sum) and leading optical depth per ray, straight from the definitions."""
    dw, ow, M = reg
    logit = raw[0] + BIAS
    sigma = np.where(valid, np.exp(np.minimum(logit, 15.0)) / DIAG, 0.0).reshape(-1, S).astype(np.float64)
    tau = sigma * delta.reshape(-1, S)
    trans = np.exp(-np.concatenate([np.zeros((len(tau), 1)), np.cumsum(tau, 1)[:, :-1]], 1))
    w = trans * (1 - np.exp(-tau))
    length = delta.reshape(-1, S)[:, :1] * S
    m = t.reshape(-1, S) / length
    pairs = np.einsum("ri,rj,rij->r", w, w, np.abs(m[:, :, None] - m[:, None, :]))
    distortion = pairs + (w ** 2).sum(1) / (3 * S)
    return dw * distortion + ow * tau[:, :M].sum(1)


def _marched_or_blocked(raw_np, t_np, delta_np, valid_np, G, reg, marched):
    """Outputs, gradient of a fixed linear function of (rgb, dsum, opac,
    regulariser) and its forward derivative along a fixed tangent."""
    params = type("Params", (), dict(density_bias=BIAS, diag=DIAG))

    def project(raw):
        if marched:
            rgb, dsum, opac, r = render.composite_marched(raw, mi.Float(t_np), mi.Float(delta_np),
                                                          mi.Bool(valid_np), S, BIAS, 1 / DIAG, reg)
        else:
            sigma, rgb_s = render.field_at(params, None, 0, mi.Bool(valid_np), raw=raw)
            tau = sigma * mi.Float(delta_np)
            w, rgb, dsum, opac = render.composite(tau, rgb_s, mi.Float(t_np), S)
            r = render.blocked_regulariser(w, tau, mi.Float(t_np), mi.Float(delta_np), S, reg)
        y = (dr.dot(rgb, mi.Color3f(G[:3])) + dsum * mi.Float(G[3]) + opac * mi.Float(G[4])
             + 3.0 * r * mi.Float(np.abs(G[0])))
        return y, [np.array(dr.detach(v)) for v in (rgb, dsum, opac, r)]

    return outputs_and_derivatives(project, raw_np)


@pytest.mark.parametrize("reg", [(1.0, 0.0, 4), (0.0, 1.0, 4), (0.7, 0.3, 1)])
def test_regularisers_match_numpy_and_their_derivatives_the_blocked_ones(reg):
    """The marched regularisers equal the O(S^2) NumPy definitions, and their
    closed-form gradient and forward derivative equal the autodiff of the
    blocked reductions' (which equal NumPy's too)."""
    raw, t, delta, valid, G = _composite_inputs(S=S)
    raw[0] += 1.5  # denser: weights spread along the rays
    want = numpy_regularisers(raw, t, delta, valid, reg)
    marched = _marched_or_blocked(raw, t, delta, valid, G, reg, True)
    blocked = _marched_or_blocked(raw, t, delta, valid, G, reg, False)
    np.testing.assert_allclose(marched[3], want, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(blocked[3], want, rtol=1e-4, atol=1e-6)
    assert want.max() > 0.05
    for name, a, b in zip(("rgb", "dsum", "opacity", "regulariser", "gradient", "forward derivative"),
                          marched, blocked):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-4, err_msg=name)  # closed form: rounding of sums
    plain = _marched_or_blocked(raw, t, delta, valid, G, (0.0, 0.0, 1), True)
    assert np.abs(marched[4][0] - plain[4][0]).max() > 1e-3  # the regulariser moves the density gradient
    np.testing.assert_allclose(marched[4][1:], plain[4][1:], rtol=1e-5, atol=1e-6)  # but not the colours'


@pytest.mark.parametrize("n_members", [1, 3])
def test_regularisers_of_whole_renders_match_the_blocked_path(monkeypatch, n_members):
    """Renders of the grid (members marched together, empty-space skipping):
    the marched regularisers and their grid gradient are the blocked path's;
    weights 0 leave the outputs and gradients of a render without them."""
    ens = Ensemble(*BOX, n_members=n_members, config=tiny_config(n_samples=8, init_scale=1.0), seed=3)
    o, d = camera_rays([0.3, 0.4, 2.5], width=5, height=5)
    rng = np.random.default_rng(1)
    jitter = mi.Float(rng.uniform(size=len(o) * 8).astype(np.float32))
    grid = np.array(ens.params().grid)

    def rendered(reg, marching=True):
        if not marching:
            monkeypatch.setattr(render, "_marching", lambda s, return_weights: False)
        params = ens.params()
        params.grid = mi.Float(grid)
        params.occupancy, params.occupancy_resolution = mi.Bool(rng.uniform(size=64) > 0.3), 4
        dr.enable_grad(params.grid)
        outs = render.render_members(params, mi.Point3f(o.T), mi.Vector3f(d.T), jitter=jitter, reg=reg)
        loss = sum(dr.sum(dr.sum(out["rgb"])) + (dr.sum(out["regulariser"]) if reg else 0.0) for out in outs)
        dr.backward(loss)
        monkeypatch.undo()
        keys = ("rgb", "opacity") + (("regulariser",) if reg else ())
        return [np.array(out[k]) for out in outs for k in keys] + [np.array(dr.grad(params.grid))]

    rng_state = rng.bit_generator.state
    reg = (0.5, 0.2, 2)
    marched = rendered(reg)
    rng.bit_generator.state = rng_state
    blocked = rendered(reg, marching=False)
    for a, b in zip(marched, blocked):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
    assert max(np.abs(r).max() for r in marched[2:-1:3]) > 1e-3
    rng.bit_generator.state = rng_state
    off = rendered(None)
    rng.bit_generator.state = rng_state
    zero = rendered((0.0, 0.0, 2))
    np.testing.assert_allclose(zero[-1], off[-1], rtol=1e-5, atol=1e-7)
    for a, b in zip([v for i, v in enumerate(zero[:-1]) if i % 3 != 2], off[:-1]):
        np.testing.assert_allclose(a, b, rtol=1e-6)


def test_options_are_off_by_default_and_checked():
    cfg = FieldConfig()
    assert cfg.distortion_weight == 0 and cfg.occlusion_weight == 0 and cfg.random_background == 0
    assert ray_regularisers(cfg) is None
    assert ray_regularisers(FieldConfig(distortion_weight=0.01, n_samples=64)) == (0.01, 0.0, 6)
    assert occlusion_samples(FieldConfig(occlusion_fraction=0.001)) == 1
    assert cfg.smoothness_weight == 0
    for bad in (dict(distortion_weight=-1.0), dict(occlusion_weight=-0.1), dict(occlusion_fraction=0.0),
                dict(occlusion_fraction=1.5), dict(random_background=2), dict(smoothness_weight=-0.1)):
        with pytest.raises(UserError):
            FieldConfig(**bad)


def _trained(steps=40, **options):
    """An ensemble fitted to two views of the textured sphere with ``options``."""
    ens = Ensemble(*BOX, n_members=1, config=tiny_config(**{"init_scale": 0.5, **options}), seed=0)
    o, d, rgb, dist, hit = views([[0.0, 0.3, 2.2], [2.2, 0.3, 0.0]], width=16, height=16)
    ens.set_rays(o, d, rgb, dist, hit, background=(1.0, 1.0, 1.0))
    ens.train(steps)
    return ens, o, d


def test_a_zero_weight_trains_as_no_regulariser():
    """Weights 0 with the other settings of the regularisers changed train
    the field of the defaults (to the rounding of the threads' gradient
    sums), unlike a weight that is on."""
    base, _, _ = _trained(steps=5)
    same, _, _ = _trained(steps=5, occlusion_fraction=0.5, random_background=0)
    np.testing.assert_allclose(base.grid_numpy(), same.grid_numpy(), rtol=0, atol=1e-5)
    for option in ("distortion_weight", "occlusion_weight", "smoothness_weight"):
        other, _, _ = _trained(steps=5, occlusion_fraction=0.5, **{option: 0.5})
        assert np.abs(other.grid_numpy() - base.grid_numpy()).max() > 1e-3, option


def _regulariser_of(ens, o, d, reg):
    out = render.render_flat(ens.params(), mi.Point3f(o.T), mi.Vector3f(d.T), 0, reg=reg)
    return float(np.mean(np.array(out["regulariser"])))


@pytest.mark.parametrize("name, reg", [("distortion_weight", (1.0, 0.0, 3)), ("occlusion_weight", (0.0, 1.0, 3))])
def test_each_regulariser_lowers_its_term(name, reg):
    """Training with the term lowers it on the training rays, against training without."""
    without, o, d = _trained()
    ens, _, _ = _trained(**{name: 0.5, "occlusion_fraction": 3 / 32})
    a, b = _regulariser_of(without, o, d, reg), _regulariser_of(ens, o, d, reg)
    assert b < 0.7 * a, (a, b)


def test_random_background_swaps_the_background_of_empty_rays():
    """With random backgrounds an empty field scores 0 on the rays known
    empty whatever its learnt background, and that background gets no
    gradient from them; without, the wrong background costs."""
    def mse(random_background, background, all_empty=False):
        ens = Ensemble(*BOX, n_members=2, config=tiny_config(random_background=random_background, batch_rays=64),
                       seed=0)
        o, d, rgb, dist, hit = views([[0.0, 0.3, 2.2]], width=8, height=8)
        if all_empty:
            rgb, hit = np.ones_like(rgb), np.zeros_like(hit)
        ens.set_rays(o, d, rgb, dist, hit, empty=~hit, background=background)
        grid = ens.grid_numpy()
        grid[:, :, 0] = -30.0  # an empty volume
        ens._opt["grid"] = mi.Float(np.ascontiguousarray(np.transpose(grid, (1, 0, 2))).ravel())
        ens._opt["background"] = mi.Float(np.full(6, -4.0, np.float32))  # dark, far from white
        value, loss = ens.training_loss()
        dr.backward(loss)
        idx, _ = ens._batch()
        return float(value[0]), np.array(dr.grad(ens._opt["background"])), np.asarray(~hit)[np.array(idx)].mean()

    value, _, share = mse(1, (1.0, 1.0, 1.0))
    assert 0.2 < share < 1  # the batch holds empty rays and others
    off, g_off, _ = mse(0, (1.0, 1.0, 1.0))
    unknown, _, _ = mse(1, None)  # no known background: nothing to swap
    assert off > 0.3 and np.all(g_off != 0)
    np.testing.assert_allclose(unknown, off, rtol=1e-6)
    assert value < 0.5 * off  # only the rays that hit the (missing) sphere miss their colour
    value, g_bg, _ = mse(1, (1.0, 1.0, 1.0), all_empty=True)
    assert value < 1e-10 and np.all(g_bg == 0)


def test_random_background_clears_white_fog():
    """White fog in front of a white background costs nothing but with
    random backgrounds: on a tiny scene the rays known empty clear with
    them, and keep the fog without."""
    def opacity(random_background):
        ens = Ensemble(*BOX, n_members=1, config=tiny_config(random_background=random_background), seed=0)
        o, d, rgb, dist, hit = views([[0.0, 0.3, 2.2], [2.2, 0.3, 0.0]], width=16, height=16)
        ens.set_rays(o, d, rgb, dist, hit, background=(1.0, 1.0, 1.0))
        grid = ens.grid_numpy()
        grid[:, :, 0], grid[:, :, 1:] = 1.0, 3.0  # white fog everywhere
        ens._opt["grid"] = mi.Float(np.ascontiguousarray(np.transpose(grid, (1, 0, 2))).ravel())
        before = ens.render(o, d)["opacity"][0][~hit].mean()
        ens.train(30)
        return before, float(ens.render(o, d)["opacity"][0][~hit].mean())

    (start, on), (_, off) = opacity(1), opacity(0)
    assert start > 0.5 and off > 0.5 * start
    assert on < 0.5 * off, (on, off)


def test_variational_field_takes_the_regularisers():
    field = VariationalField(*BOX, config=tiny_config(distortion_weight=0.1, occlusion_weight=0.1,
                                                      random_background=1))
    o, d, rgb, dist, hit = views([[0.0, 0.3, 2.2]], width=8, height=8)
    field.set_rays(o, d, rgb, dist, hit, background=(1.0, 1.0, 1.0))
    losses = field.train(3)
    assert np.all(np.isfinite(losses))


def numpy_smoothness(table, layout):
    """The grid's total variation and its gradient, from the definition, over
    a table (entries, K, 4) in float64."""
    value, grad = 0.0, np.zeros_like(table)
    for r, off, dense in zip(layout.resolutions, layout.offsets, layout.dense):
        if not dense:
            continue
        n = r + 1
        level = table[off:off + n ** 3].reshape(n, n, n, *table.shape[1:])  # z, y, x
        g = np.zeros_like(level)
        for axis in (0, 1, 2):
            diff = np.diff(level, axis=axis)
            value += (diff ** 2).sum() / (3 * n ** 3)
            pad = [(0, 0)] * level.ndim
            pad[axis] = (1, 0)
            g += np.pad(2 * diff, pad) / (3 * n ** 3)  # d/d f(v + e)
            pad[axis] = (0, 1)
            g -= np.pad(2 * diff, pad) / (3 * n ** 3)  # d/d f(v)
        grad[off:off + n ** 3] = g.reshape(n ** 3, *table.shape[1:])
    return value, grad


def test_grid_smoothness_matches_numpy_and_its_gradient():
    """The total variation of the dense levels (the hashed one left out) and
    its gradient equal NumPy's, for two members side by side."""
    layout = GridLayout.from_config(tiny_config())
    assert layout.dense == (True, False)
    K = 2
    table = np.random.default_rng(3).normal(size=(layout.n_entries, K, 4))
    grid = mi.Float(table.astype(np.float32).ravel())
    dr.enable_grad(grid)
    value = grid_smoothness(grid, layout, K)
    dr.backward(value)
    want, want_grad = numpy_smoothness(table, layout)
    np.testing.assert_allclose(float(value[0]), want, rtol=1e-5)
    got_grad = np.array(dr.grad(grid)).reshape(table.shape)
    np.testing.assert_allclose(got_grad, want_grad, rtol=1e-4, atol=1e-7)
    assert np.all(got_grad[layout.offsets[1]:] == 0) and np.any(got_grad != 0)
    flat = mi.Float(np.ones(table.size, np.float32))
    assert float(grid_smoothness(flat, layout, K)[0]) == 0.0


def test_smoothness_lowers_the_grids_variation():
    """Training with the smoothness prior leaves a smoother grid than training without."""
    def variation(ens):
        return float(grid_smoothness(mi.Float(np.ascontiguousarray(np.transpose(ens.grid_numpy(), (1, 0, 2))).ravel()),
                                     ens.layout, 1)[0])

    without, _, _ = _trained()
    ens, _, _ = _trained(smoothness_weight=0.5)
    assert variation(ens) < 0.7 * variation(without), (variation(ens), variation(without))
