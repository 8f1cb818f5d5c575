"""Training batches: each step's rays and sample jitter, drawn in-kernel, optionally spatially coherent.

A training step marches ``batch_rays`` rays, one per group of SIMD lanes. When
each lane's ray is drawn independently, neighbouring lanes march unrelated
rays and the fine grid levels' lookups miss the caches. Sorting the training
rays once (by camera position, then by direction along a Morton curve) and
drawing one ray from each of ``batch_rays`` equal strata of that order makes
neighbouring lanes march neighbouring rays of one view, while every ray keeps
the same probability of being drawn (``batch_rays / n_rays`` per step).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .samples import hash_u32, uniform_from_u32

#: Bits per axis of the Morton codes (3 x 21 = 63 bits in a uint64).
MORTON_BITS = 21


def _spread(v: np.ndarray) -> np.ndarray:
    """uint64 with the low 21 bits of ``v`` moved to every third bit."""
    x = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def morton_codes(points: np.ndarray) -> np.ndarray:
    """uint64 (N,) Morton codes of (N, 3) points, quantised within their own bounds."""
    p = np.asarray(points, np.float64)
    lo, hi = p.min(axis=0), p.max(axis=0)
    scale = np.where(hi > lo, ((1 << MORTON_BITS) - 1) / np.where(hi > lo, hi - lo, 1.0), 0.0)
    q = np.rint((p - lo) * scale).astype(np.uint64)
    return _spread(q[:, 0]) | (_spread(q[:, 1]) << np.uint64(1)) | (_spread(q[:, 2]) << np.uint64(2))


def ray_order(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """uint32 (M,) permutation of M rays ((M, 3) origins and unit directions):
    by the Morton code of the origin (a camera's rays stay together), then by
    that of the direction (tiles of an image). Deterministic (a stable sort)."""
    return np.lexsort((morton_codes(directions), morton_codes(origins))).astype(np.uint32)


def stratified_indices(n: int, n_rays, u):
    """``n`` indices into ``n_rays`` sorted rays, lane ``i`` drawing
    ``floor((i + u_i) * n_rays / n)``, in increasing order.

    Args:
        n: lanes (rays per batch).
        n_rays: ``mi.UInt32`` (opaque) or int, the rays to draw from.
        u: ``mi.UInt32`` (n,) uniform 32-bit draws (``u_i = u / 2**32``).

    Returns:
        ``mi.UInt32`` (n,). Lane ``i``'s draw is uniform over the integers
        ``[i * n_rays, (i + 1) * n_rays)`` divided by ``n``: each ray covers
        ``n`` of the ``n * n_rays`` integers, so each is drawn equally often
        on average, ``n / n_rays`` times a step.
    """
    U64 = dr.uint64_array_t(mi.UInt32)
    m = mi.UInt32(n_rays)
    i = dr.arange(mi.UInt32, int(n))
    # floor((i + u) M / n) = floor((i M + floor(u M)) / n) for a whole n; i M < 2^55 fits 64 bits.
    x = U64(i) * U64(m) + U64(dr.mul_hi(mi.UInt32(u), m))
    return mi.UInt32(x // U64(int(n)))


def draw_batch(seed: int, step: int, n_rays: int, n: int, samples: int, order=None):
    """Ray indices and per-sample jitter of training step ``step``.

    Args:
        seed: the ensemble's seed.
        step: the step (each draws anew).
        n_rays: training rays to draw from.
        n: rays per batch.
        samples: samples per ray.
        order: None (independent uniform draws), or ``mi.UInt32`` (n_rays,)
            the rays' coherent order (:func:`ray_order`): one ray per stratum.

    Returns:
        ``(idx, jitter)``: ``mi.UInt32`` (n,) ray indices and ``mi.Float``
        (n * samples,) jitter in [0, 1).
    """
    # Opaque keys: the step and ray count change every call but must not
    # be baked into the kernel as literals (that would recompile per step).
    base = (seed * 0x9E3779B1 + step * 0x85EBCA77) & 0xFFFFFFFF
    key = dr.opaque(mi.UInt32, base)
    key2 = dr.opaque(mi.UInt32, base ^ 0x5BD1E995)
    m = dr.opaque(mi.UInt32, n_rays)
    i = dr.arange(mi.UInt32, n)
    if order is not None:
        idx = dr.gather(mi.UInt32, order, stratified_indices(n, m, hash_u32(hash_u32(i) ^ key)))
    else:  # mul_hi maps a 32-bit hash uniformly onto [0, M) without modulo bias.
        idx = dr.mul_hi(hash_u32(hash_u32(i) ^ key), m)
    jitter = uniform_from_u32(hash_u32(hash_u32(dr.arange(mi.UInt32, n * samples)) ^ key2))
    return idx, jitter
