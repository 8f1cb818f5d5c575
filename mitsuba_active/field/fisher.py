"""The Fisher information's diagonal of one ensemble member, by Hutchinson's estimator.

``J`` is the Jacobian of the rendered colours of the given rays (N rays x 3
channels) with respect to the member's P parameters (grid floats, then 3
background logits, as ``Ensemble.member_params`` orders them). For
Rademacher ``v`` (N, 3), ``(J^T v)**2`` is an unbiased estimate of ``sum_{r,c}
(dC_rc/dtheta)**2``; ``probes`` of them are averaged. Gradients of all ray
batches are accumulated before squaring (the estimate needs the whole
``J^T v``).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..checks import is_whole
from ..errors import UserError
from .inputs import padded_rays
from .render import render_flat


def fisher_diagonal(ens, origins, directions, member: int, probes: int, seed: int) -> np.ndarray:
    """(P,) float64 estimate of diag(J^T J) of member ``member`` of ensemble ``ens``
    over rays ``origins``, ``directions`` ((N, 3) each), from ``probes`` probes drawn from ``seed``."""
    if not is_whole(probes) or probes < 1:
        raise UserError(f"fisher_diag: probes must be a whole number >= 1, got {probes!r}")
    rays = padded_rays(origins, directions, ens.config.render_batch)
    n, n_pad, B = rays.n, rays.n_pad, rays.batch
    batches = list(rays.batches())  # converted once for every probe
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(int(member),)))
    grid = mi.Float(dr.detach(ens._opt["grid"]))
    bg = mi.Float(dr.detach(ens._opt["background"]))
    acc = np.zeros(ens.n_params, np.float64)
    for _ in range(int(probes)):
        v = np.zeros((n_pad, 3), np.float32)  # padding rays do not count
        v[:n] = rng.choice(np.float32([-1.0, 1.0]), size=(n, 3))
        dr.enable_grad(grid, bg)
        params = ens.params()
        params.grid, params.background = grid, bg
        for s, o, d in batches:
            out = render_flat(params, o, d, int(member))
            vb = mi.Color3f(v[s:s + B].T)
            dr.backward(dr.sum(dr.dot(out["rgb"], vb)))
        gg = np.array(dr.grad(grid), np.float64).reshape(-1, ens.n_members, 4)[:, member]
        gg = gg.ravel()
        gb = np.array(dr.grad(bg), np.float64).reshape(ens.n_members, 3)[member]
        dr.disable_grad(grid, bg)
        g = np.concatenate([gg, gb])
        acc += g * g
    return acc / int(probes)
