"""The learning rates' decay (FieldConfig.lr_decay_steps)."""

import numpy as np
import pytest

import mitsuba_active  # noqa: F401  (variant first)
from mitsuba_active.errors import UserError
from mitsuba_active.field import Ensemble
from tests.test_field import BOX, tiny_config, views
from tests.test_occupancy import FOUR_SIDES


def _rates(ens):
    """Each optimised parameter's current learning rate."""
    return {key: float(ens._opt.state[key][2]) for key in ens._opt.keys()}


def _trained(steps, **options):
    ens = Ensemble(*BOX, n_members=1, config=tiny_config(view_degree=1, view_resolution=4, lr=0.05,
                                                          lr_background=0.02, **options), seed=0)
    ens.set_rays(*views(FOUR_SIDES[:2], width=8, height=8))
    assert np.isfinite(ens.train(steps)).all()
    return ens


def test_the_rates_fall_tenfold_over_the_decay_steps():
    # Step 8's update used 0.1 ** (8 / 4) of each rate.
    rates = _rates(_trained(9, lr_decay_steps=4))
    assert set(rates) == {"grid", "background", "view"}
    assert rates["grid"] == pytest.approx(0.05 * 0.01, rel=1e-6)
    assert rates["view"] == pytest.approx(0.05 * 0.01, rel=1e-6)
    assert rates["background"] == pytest.approx(0.02 * 0.01, rel=1e-6)


def test_the_first_step_is_the_same_and_later_ones_smaller():
    constant, decayed = _trained(1), _trained(1, lr_decay_steps=4)
    np.testing.assert_allclose(constant.grid_numpy(), decayed.grid_numpy(), rtol=1e-5, atol=1e-7)
    start = _trained(0).grid_numpy()
    moved = [np.abs(_trained(12, lr_decay_steps=d).grid_numpy() - start).mean() for d in (0, 2)]
    assert moved[1] < 0.5 * moved[0]


def test_a_negative_decay_is_refused():
    with pytest.raises(UserError, match="lr_decay_steps"):
        tiny_config(lr_decay_steps=-1)
