"""Tests of the variational field (mitsuba_active.field.variational) and its planner."""

import numpy as np
import pytest

import mitsuba_active  # noqa: F401  (variant first)
import drjit as dr
import mitsuba as mi

from mitsuba_active.errors import UserError
from mitsuba_active.field import Ensemble, VariationalField
from mitsuba_active.field.variational import standard_normal4
from mitsuba_active.planners import make_planner
from mitsuba_active.run import Run, RunConfig
from tests.conftest import tiny_source
from tests.test_field import BOX, camera_rays, psnr, tiny_config, views
from tests.test_run import TINY


@pytest.fixture(scope="module")
def spot_source(spot_xml):
    return tiny_source(spot_xml, n_candidates=10, n_heldout=3, resolution=16)


def test_standard_normal_draws_are_standard_and_independent():
    x = np.array(standard_normal4(dr.arange(mi.UInt32, 200_000), mi.UInt32(7)))  # (4, N)
    assert np.all(np.isfinite(x))
    assert np.allclose(x.mean(1), 0.0, atol=0.01) and np.allclose(x.std(1), 1.0, atol=0.01)
    assert np.abs(np.corrcoef(x) - np.eye(4)).max() < 0.01
    # Another key draws other values.
    y = np.array(standard_normal4(dr.arange(mi.UInt32, 1000), mi.UInt32(8)))
    assert np.abs(np.corrcoef(x[0, :1000], y[0])[0, 1]) < 0.1


def _trained(steps=120, **kw):
    train = views([[0.0, 0.2, 2.2], [0.8, 0.2, 2.0]], width=24, height=24)
    field = VariationalField(*BOX, config=tiny_config(n_levels=3, lr=0.05), seed=3, **kw)
    field.set_rays(*train)
    return field, train, field.train(steps)


def test_fits_its_views_and_is_less_certain_about_unseen_ones():
    field, train, losses = _trained()
    assert field.n_outputs == 1 and losses[-10:].mean() < 0.3 * losses[:10].mean()
    seen = field.predict(train[0], train[1])
    assert psnr(seen["rgb_mean"], train[2]) > 20.0
    unseen = views([[0.0, 0.2, -2.2]], width=24, height=24)
    st = field.predict(unseen[0], unseen[1])
    assert seen["rgb_var"].mean() < 0.5 * st["rgb_var"].mean(), (seen["rgb_var"].mean(), st["rgb_var"].mean())
    # render reports one image per draw.
    assert field.render(unseen[0], unseen[1])["rgb"].shape == (field.draws, unseen[0].shape[0], 3)


def test_the_variance_comes_from_the_learnt_spread():
    o, d = camera_rays([0.0, 0.3, 2.2], width=8, height=8)
    tiny = VariationalField(*BOX, config=tiny_config(), seed=0, max_std=1e-6)
    wide = VariationalField(*BOX, config=tiny_config(), seed=0, max_std=3.0)
    # It starts from seeded means and a spread of max_std / 2 (scale logits 0) everywhere.
    start = wide.grid_numpy()
    assert np.all(start[1] == 0) and np.abs(start[0]).max() > 0
    assert tiny.predict(o, d)["rgb_var"].max() < 1e-9
    assert wide.predict(o, d)["rgb_var"].mean() > 1e-4
    # The same rays give the same prediction (fixed draws).
    assert np.array_equal(wide.predict(o, d)["rgb_var"], wide.predict(o, d)["rgb_var"])


def test_the_entropy_term_widens_the_spread_where_no_view_constrains_it():
    spreads = []
    for weight in (0.0, 0.05):
        field, _, _ = _trained(steps=60, entropy_weight=weight)
        scale_logits = field.grid_numpy()[1]  # slot 1: the scale logits, 0 at the start
        spreads.append(scale_logits.mean())
    assert spreads[1] > spreads[0] + 0.1, spreads


def test_save_load_gives_back_a_variational_field(tmp_path):
    field, train, _ = _trained(steps=10, max_std=1.5, draws=4)
    o, d = camera_rays([1.0, 1.0, 2.0], width=8, height=8)
    before = field.predict(o, d)
    field.save(tmp_path / "v.npz")
    again = Ensemble.load(tmp_path / "v.npz")  # the file says what it holds
    assert type(again) is VariationalField and again.options() == {"max_std": 1.5, "entropy_weight": 1e-3,
                                                                   "draws": 4}
    after = again.predict(o, d)
    for key in before:
        assert np.array_equal(before[key], after[key]), key
    again.set_rays(*train)
    assert np.isfinite(again.train(2)).all()
    Ensemble(*BOX, n_members=2, config=tiny_config(), seed=1).save(tmp_path / "e.npz")
    with pytest.raises(UserError, match="e.npz is a saved Ensemble, not a VariationalField"):
        VariationalField.load(tmp_path / "e.npz")
    # Options edited by hand are named with the file.
    with np.load(tmp_path / "v.npz") as z:
        arrays = {key: z[key] for key in z.files}
    np.savez(tmp_path / "edited.npz", **{**arrays, "options": np.array('{"draws": 1}')})
    with pytest.raises(UserError, match=r"edited.npz: the variational field needs .* draws=1"):
        Ensemble.load(tmp_path / "edited.npz")


@pytest.mark.parametrize("kw", [dict(max_std=0), dict(max_std=float("inf")), dict(entropy_weight=-1),
                                dict(draws=1), dict(draws=2.5), dict(n_members=3)])
def test_bad_options_are_refused(kw):
    with pytest.raises(UserError):
        VariationalField(*BOX, config=tiny_config(), **kw)


def test_what_it_does_not_do_is_refused():
    with pytest.raises(UserError, match="no empty-space skipping"):
        VariationalField(*BOX, config=tiny_config(occupancy_resolution=8))
    field = VariationalField(*BOX, config=tiny_config())
    with pytest.raises(UserError, match="fisher_diag needs an Ensemble"):
        field.fisher_diag(*camera_rays([0.0, 0.0, 2.0], width=4, height=4))
    from mitsuba_active.field import render_rays_dr

    o, d = camera_rays([0.0, 0.0, 2.0], width=4, height=4)
    o, d = mi.Point3f(o.T), mi.Vector3f(d.T)
    with pytest.raises(UserError, match="renders here as member 0 only"):
        render_rays_dr(field, o, d, 1)  # slot 1: the features' scales, no field
    assert dr.width(render_rays_dr(field, o, d, 0)[0]) == 16


def test_planner_options():
    p = make_planner("variational", draws=4, max_std=1.0)
    assert p.options() == {"form": "sum", "draws": 4, "max_std": 1.0, "entropy_weight": 1e-3}
    assert p.ensemble_size(4) == 1
    for bad in (dict(draws=0), dict(max_std=-1.0), dict(form="max")):
        with pytest.raises(UserError):
            make_planner("variational", **bad)


def test_a_run_trains_and_resumes_a_variational_field(spot_source, tmp_path):
    def run(budget):
        cfg = RunConfig(scene=str(spot_source.scene.path), planner="variational",
                        **{**TINY, "budget": budget, "eval_views": [2]})
        r = Run(spot_source, cfg, tmp_path / "r", progress=False, log=lambda m: None)
        return r, r.execute()

    _, short = run(3)
    assert type(Ensemble.load(tmp_path / "r" / short["ensemble_file"])) is VariationalField
    assert all(np.isfinite(short["rounds"][0]["scores"])) and np.ptp(short["rounds"][0]["scores"]) > 0
    resumed, longer = run(4)  # goes on from the saved field
    assert isinstance(resumed.ensemble, VariationalField)
    assert longer["captured"][:3] == short["captured"] and len(set(longer["captured"])) == 4
