"""Checks of the arrays a field is given: points, 3-vectors and rays.

Rays of another kind would not fail, only give wrong fields: a direction of
length 2 halves every distance, a NaN spreads through training. So every
array that enters an ensemble is checked here, with a message that names
the call and the argument.
"""

from __future__ import annotations

import numpy as np

from ..errors import UserError


def triples(values, what: str, name: str) -> np.ndarray:
    """(N,3) float32 from an array whose last axis holds 3 values ((N,3), (H,W,3)...)."""
    a = np.asarray(values, np.float32)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise UserError(f"{what}: {name} must be an array of 3-vectors, shape (N, 3), not {a.shape}")
    return a.reshape(-1, 3)


def point(values, what: str, name: str) -> np.ndarray:
    """(3,) float64 from a 3-vector, else UserError naming ``what`` and ``name``."""
    try:
        p = np.asarray(values, np.float64)
    except (TypeError, ValueError):
        p = None
    if p is None or p.size != 3:
        raise UserError(f"{what}: {name} must be a point (x, y, z), got "
                        f"{'shape ' + str(p.shape) if p is not None else repr(values)}")
    return p.reshape(3)


def checked_rays(origins, directions, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(N,3) float32 origins and directions, checked: finite, unit directions, as many of each.

    Rays of another kind would not fail, only give wrong fields: a direction
    of length 2 halves every distance, a NaN spreads through training.
    """
    o, d = triples(origins, what, "origins"), triples(directions, what, "directions")
    if o.shape[0] != d.shape[0]:
        raise UserError(f"{what}: {o.shape[0]} origins but {d.shape[0]} directions")
    if not (np.isfinite(o).all() and np.isfinite(d).all()):
        raise UserError(f"{what}: origins and directions must be finite numbers")
    norms = np.linalg.norm(d, axis=1)
    if norms.size and np.abs(norms - 1.0).max() > 1e-3:
        raise UserError(f"{what}: directions must be unit vectors (lengths from {norms.min():.4g} "
                        f"to {norms.max():.4g})")
    return o, d
