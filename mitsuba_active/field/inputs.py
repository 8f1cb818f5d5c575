"""Checks of the arrays a field is given: points, 3-vectors and rays.

Rays of another kind would not fail, only give wrong fields: a direction of
length 2 halves every distance, a NaN spreads through training. So every
array that enters an ensemble is checked here, with a message that names
the call and the argument.
"""

from __future__ import annotations

from dataclasses import dataclass

import mitsuba as mi
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


@dataclass(frozen=True)
class PaddedRays:
    """Rays padded to whole inference batches (see :func:`padded_rays`).

    Attributes:
        o, d: (n_pad, 3) float32 origins and unit directions, ``n_pad`` a
            whole number (>= 1) of batches; the padding rays start at the
            origin and look along +z.
        n: rays given (the first ``n`` rows).
        batch: rays per batch.
    """

    o: np.ndarray
    d: np.ndarray
    n: int
    batch: int

    @property
    def n_pad(self) -> int:
        """Rows, padding included."""
        return self.o.shape[0]

    def batches(self):
        """Each batch as ``(offset, origins, directions)``: its first row, and
        ``mi.Point3f`` / ``mi.Vector3f`` of ``batch`` rays."""
        for s in range(0, self.n_pad, self.batch):
            yield s, mi.Point3f(self.o[s:s + self.batch].T), mi.Vector3f(self.d[s:s + self.batch].T)


def padded_rays(origins, directions, render_batch: int, what: str = "rendering") -> PaddedRays:
    """(N, 3) rays, checked (:func:`checked_rays`), padded to whole batches of
    the next power of two of N (at least 64) capped at ``render_batch``: small
    calls (a planner's 256 rays per candidate) then do not pay for a full batch
    of padding, and the few distinct sizes keep compiled kernels reused."""
    o, d = checked_rays(origins, directions, what)
    n = o.shape[0]
    batch = min(int(render_batch), max(64, 1 << max(0, int(n) - 1).bit_length()))
    n_pad = max(batch, -(-n // batch) * batch)
    op = np.zeros((n_pad, 3), np.float32)
    dp = np.zeros((n_pad, 3), np.float32)
    dp[:, 2] = 1.0
    op[:n], dp[:n] = o, d
    return PaddedRays(op, dp, n, batch)
