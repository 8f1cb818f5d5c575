"""A stochastic radiance field with variational uncertainty (Stochastic NeRF style).

Instead of K fields, one field whose raw features (density logit, colour
logits) at a sample point are random, Gaussian with a mean and a standard
deviation that are both grid features:

    raw(x) ~ N(mu(x), std(x)^2),   std(x) = max_std * sigmoid(s(x)),

drawn independently at every sample point, as in S-NeRF (Shen et al. 2021).
A training step renders its batch with one draw (the reparameterisation
``raw = mu + std * eps``, ``eps ~ N(0, 1)``) and minimises the photometric
loss minus ``entropy_weight`` times the mean log-std over the samples, the
entropy of the variational distribution: it keeps ``std`` near ``max_std``
wherever no view constrains the field. A ray's uncertainty is the variance
of its colour over ``draws`` renders.

The parameters live in the ensemble's member-interleaved table with two
slots per entry (``n_members == 2``): slot 0 holds the mean features, slot 1
the scale logits ``s`` (starting at 0, ``std = max_std / 2``). One packet
gather reads both. The background colour is slot 0's.
"""

from __future__ import annotations

import json
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..checks import is_number, is_whole
from ..errors import UserError
from .ensemble import Ensemble
from .render import _composited, lookup_samples
from .samples import hash_u32, sample_along_rays

#: Defaults: the largest standard deviation of a raw feature (in logit
#: units), the weight of the entropy term, and the renders whose colour
#: variance a prediction reports.
DEFAULT_MAX_STD = 2.0
DEFAULT_ENTROPY_WEIGHT = 1e-3
DEFAULT_DRAWS = 8
#: Most draws of one prediction (each is a render of every ray).
MAX_DRAWS = 64


def _log_sigmoid(x):
    """``log(sigmoid(x))``, smooth everywhere (the scale logits start at 0,
    where a formula with ``abs`` or ``maximum`` would have no gradient); ``x``
    is clamped to +-30, beyond which the sigmoid of a float32 is 0 or 1."""
    return -dr.log(1.0 + dr.exp(-dr.clip(x, -30.0, 30.0)))


def _open_unit(h):
    """Float in (0, 1) from the top 24 bits of a hash (never 0: it goes into a log)."""
    return (mi.Float(h >> 8) + 0.5) * (1.0 / 16777216.0)


def standard_normal4(index, key):
    """Four independent N(0, 1) values per lane (Box-Muller on hashed uniforms).

    Args:
        index: ``mi.UInt32`` per lane (e.g. the global sample index).
        key: ``mi.UInt32`` (opaque) seed of this draw.
    Returns:
        ``mi.Vector4f``.
    """
    h = hash_u32(hash_u32(index) ^ key)
    out = []
    for pair in range(2):
        h1 = hash_u32(h ^ (0x9E3779B9 * (2 * pair + 1) & 0xFFFFFFFF))
        h2 = hash_u32(h ^ (0x85EBCA6B * (2 * pair + 2) & 0xFFFFFFFF))
        r = dr.sqrt(-2.0 * dr.log(_open_unit(h1)))
        s, c = dr.sincos((2.0 * math.pi) * _open_unit(h2))
        out += [r * c, r * s]
    return mi.Vector4f(*out)


class VariationalField(Ensemble):
    """One radiance field with a Gaussian over its raw features at every point.

    Trains and saves like an :class:`Ensemble` (``set_rays``, ``train``,
    ``save``/``load``); ``render`` and ``predict`` report ``draws`` renders
    in place of members.

    Args:
        bbox_min, bbox_max, config, seed: as for :class:`Ensemble`.
        n_members: the table's slots, always 2 (mean and scale).
        max_std: largest standard deviation of a raw feature (logit units, > 0).
        entropy_weight: weight of the entropy term (>= 0).
        draws: renders per prediction (2 to ``MAX_DRAWS``).
    """

    KIND = "mitsuba_active.field.VariationalField"

    def __init__(self, bbox_min, bbox_max, n_members: int = 2, config=None, seed: int = 0,
                 max_std: float = DEFAULT_MAX_STD, entropy_weight: float = DEFAULT_ENTROPY_WEIGHT,
                 draws: int = DEFAULT_DRAWS):
        check_options(max_std, entropy_weight, draws)
        if n_members != 2:
            raise UserError(f"a VariationalField has 2 table slots (mean and scale), not n_members={n_members!r}")
        super().__init__(bbox_min, bbox_max, 2, config, seed)
        if self.config.occupancy_resolution > 0:
            raise UserError("a VariationalField has no empty-space skipping: set occupancy_resolution = 0")
        if self.config.view_degree > 0:
            raise UserError("a VariationalField is diffuse: set view_degree = 0")
        self.max_std, self.entropy_weight, self.draws = float(max_std), float(entropy_weight), int(draws)

    def _initial_grid(self, grid: np.ndarray) -> np.ndarray:
        grid[1] = 0.0  # scale logits: every point starts at std = max_std / 2
        return grid

    def _half_grid(self, evaluate: bool = True):
        # Training differentiates the lookups themselves: renders read the same float32 table.
        return None

    def options(self) -> dict:
        """The options beyond :class:`FieldConfig` (stored in saved files)."""
        return {"max_std": self.max_std, "entropy_weight": self.entropy_weight, "draws": self.draws}

    @property
    def n_outputs(self) -> int:
        """Renders per training step: one draw."""
        return 1

    def _lookup(self, params, s, offset: int = 0):
        """Mean features and log-std (``mi.Vector4f`` each) of the samples ``s``,
        and each sample's index among all rendered (its draws' seed), for rays
        from the ``offset``-th on."""
        mean, scale = lookup_samples(params, s)
        dr.eval(mean, scale, s["t"], s["delta"])  # one gather kernel for both slots
        first = dr.opaque(mi.UInt32, offset * int(self.config.n_samples))
        index = dr.arange(mi.UInt32, dr.width(s["t"])) + first
        return mean, math.log(self.max_std) + _log_sigmoid(scale), index

    def _training_outputs(self, o, d, jitter, reg=None):
        params = self.params()
        s = sample_along_rays(o, d, params, jitter)
        mean, log_std, index = self._lookup(params, s)
        key = dr.opaque(mi.UInt32, (self.seed * 0x27D4EB2F + self._step * 0x165667B1) & 0xFFFFFFFF)
        out = _composited(params, s, [mean + dr.exp(log_std) * standard_normal4(index, key)], [0], reg=reg)[0]
        # Entropy of the Gaussian, up to a constant: the log-std summed over the
        # channels of the batch's samples inside the box, per channel and sample.
        entropy = dr.sum(dr.select(s["valid"], dr.sum(log_std), 0.0)) * (1.0 / (4 * dr.width(s["t"])))
        return [out], -self.entropy_weight * entropy

    def render_dr(self, params, o, d, offset: int = 0):
        s = sample_along_rays(o, d, params)
        mean, log_std, index = self._lookup(params, s, offset)
        std = dr.exp(log_std)
        outs = []
        for k in range(self.draws):
            # Fixed draws: the same rays, in the same order, give the same prediction.
            key = dr.opaque(mi.UInt32, (self.seed * 0x9E3779B1 + k * 0x7FEB352D + 1) & 0xFFFFFFFF)
            outs.append(_composited(params, s, [mean + std * standard_normal4(index, key)], [0])[0])
        return outs

    def __repr__(self):
        return (f"VariationalField(P={self.n_params}, rays={self._n_rays}, step={self._step}, "
                f"options={json.dumps(self.options())}, config={json.dumps(self.config.to_dict())})")

    def fisher_diag(self, *args, **kwargs):
        raise UserError("fisher_diag needs an Ensemble; a VariationalField's parameters are a distribution's")


def check_options(max_std, entropy_weight, draws) -> None:
    """UserError unless the options are a finite max_std > 0, a finite
    entropy_weight >= 0 and a whole number of draws in [2, MAX_DRAWS]."""
    if not (is_number(max_std, finite=True) and max_std > 0 and is_number(entropy_weight, finite=True)
            and entropy_weight >= 0 and is_whole(draws) and 2 <= draws <= MAX_DRAWS):
        raise UserError(f"the variational field needs a finite max_std > 0, a finite entropy_weight >= 0 and a "
                        f"whole number of draws in [2, {MAX_DRAWS}], got max_std={max_std!r}, "
                        f"entropy_weight={entropy_weight!r}, draws={draws!r}")
