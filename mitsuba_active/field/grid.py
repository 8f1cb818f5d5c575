"""Multi-resolution feature grids over the unit cube, for K members at once.

The parameters of all K members live in **one** flat ``mi.Float`` table of
``n_entries * K * 4`` values, laid out as ``[entry][member][channel]`` with
the 4 channels (density logit, r, g, b logits) innermost. Interleaving makes
each corner lookup of all K members one packet gather of K*4 floats from one
cache line (and one packet scatter-add in the backward pass), which is what
lets one kernel train/render every member at little more than the cost of
one (see :mod:`mitsuba_active.field.march`).

Coarse levels are dense (vertex ``(x, y, z)`` at ``x + y*(r+1) + z*(r+1)**2``);
levels with more vertices than ``2**log2_table_size`` use the Instant-NGP
spatial hash ``(x * 1) ^ (y * 2654435761) ^ (z * 805459861) mod T``.

Lookups may read a float16 copy of the table (:func:`half_table`, the
mixed precision of Instant-NGP): a corner's packet gather then moves half
the bytes and costs about half the instructions on the CPU, while the
gradients and the optimiser's parameters stay float32. A table of hashed
levels too large for the caches is read, and its gradients added, level
group by level group (:func:`level_groups`, :func:`group_lanes`).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .config import FieldConfig

#: Channels per vertex: density logit + RGB logits.
N_CHANNELS = 4

#: Most bytes of the float16 table that one group of :func:`level_groups`
#: reads at a time: one member's twelve levels (2.5 MiB) are read at once,
#: four members' in four groups (measured: docs/field-measurements.md).
LOOKUP_GROUP_BYTES = 3 << 20

_PRIMES = (1, 2654435761, 805459861)


@dataclass(frozen=True)
class GridLayout:
    """Static description of the per-member table (Python ints only)."""

    resolutions: tuple  #: cells per axis of each level
    sizes: tuple  #: vertices (table entries) of each level
    offsets: tuple  #: first entry of each level
    dense: tuple  #: True where the level is stored without hashing
    n_entries: int  #: table entries per member (each holds 4 floats)
    #: None, or one weight per level (opaque ``mi.Float`` scalars) scaling its features (annealing)
    weights: tuple | None = None

    @property
    def n_grid_params(self) -> int:
        """Floats of grid parameters per member."""
        return self.n_entries * N_CHANNELS

    @staticmethod
    def from_config(cfg: FieldConfig) -> "GridLayout":
        table = 1 << int(cfg.log2_table_size)
        res, sizes, offs, dense = [], [], [], []
        off = 0
        for level in range(int(cfg.n_levels)):
            r = max(1, int(round(cfg.base_resolution * cfg.per_level_scale ** level)))
            n_vert = (r + 1) ** 3
            is_dense = n_vert <= table
            size = n_vert if is_dense else table
            res.append(r)
            sizes.append(size)
            offs.append(off)
            dense.append(is_dense)
            off += size
        return GridLayout(tuple(res), tuple(sizes), tuple(offs), tuple(dense), off)


def init_grid(layout: GridLayout, cfg: FieldConfig, seeds) -> np.ndarray:
    """Initial tables for the members' seeds: float32 array (K, n_entries, 4)
    (member-major; transpose to (n_entries, K, 4) for the Dr.Jit table).

    Each member draws from its own ``numpy`` generator so member ``k`` of an
    ensemble is the same whatever K is.
    """
    out = np.empty((len(seeds), layout.n_entries, N_CHANNELS), np.float32)
    for k, s in enumerate(seeds):
        rng = np.random.default_rng(s)
        out[k] = rng.uniform(-cfg.init_scale, cfg.init_scale,
                             size=(layout.n_entries, N_CHANNELS))
    return out


def anneal_weights(n_levels: int, anneal_steps: int, step: int) -> np.ndarray:
    """Coarse-to-fine weights of the levels (float64 (n_levels,), in [0, 1]) at
    training step ``step``: level 0 always 1, level ``l`` ramping linearly
    from 0 to 1 over the ``l``-th of ``n_levels - 1`` equal parts of
    ``anneal_steps`` steps; all 1 when ``anneal_steps`` is 0 or has passed."""
    L, n = int(n_levels), int(anneal_steps)
    if n == 0 or step >= n or L == 1:
        return np.ones(L)
    return np.clip(step / n * (L - 1) - np.arange(L) + 1.0, 0.0, 1.0)


def reduce_mode():
    """Scatter mode of the gathers' adjoint (the backward pass).

    On the CPU, ``ReduceMode.Expand`` gives every thread a private copy of
    the gradient table and sums them afterwards; Dr.Jit only picks it
    automatically below ``dr.expand_threshold()`` (1 M entries), and
    with contended atomics instead the backward pass is ~6x slower here. On
    the GPU, Dr.Jit's default atomics are the right choice.
    """
    if dr.backend_v(mi.Float) == dr.JitBackend.LLVM:
        return dr.ReduceMode.Expand
    return dr.ReduceMode.Auto


def level_groups(layout: GridLayout, entry_bytes: int, budget: int, most: int = None) -> list:
    """The levels in equal groups of consecutive ones (a list of ``range``):
    for a layout with hashed levels, as few groups as keep each one's share
    of a table of ``entry_bytes`` an entry within ``budget`` bytes, or
    ``most`` groups (default: one a level) where that takes more; else one
    group of all.

    A pass that reads the table group after group keeps its random accesses
    within that share, which the caches hold (see :func:`group_lanes`).
    Dense levels alone gain nothing from it: they stay in one group.
    """
    L = len(layout.resolutions)
    if all(layout.dense):
        return [range(L)]
    wanted = min(-(-layout.n_entries * int(entry_bytes) // int(budget)), L if most is None else int(most))
    n = next(d for d in range(1, L + 1) if L % d == 0 and d >= min(wanted, L))
    return [range(g * L // n, (g + 1) * L // n) for g in range(n)]


def group_lanes(n: int, n_groups: int):
    """Lanes for ``n`` items (rays or samples) in ``n_groups`` level groups:
    one chunk of the items per thread, each chunk's lanes group after group,
    in whole SIMD packets (of at most 16 lanes), so that every thread walks
    every group and a group's lanes come one after another.

    Returns:
        (item ``mi.UInt32``, group ``mi.UInt32``, real ``mi.Bool``) per lane:
        the item (clamped to ``n - 1`` in the padding, where ``real`` is
        False) and its group; and the lanes a chunk has in each group
        (opaque ``mi.UInt32``): item ``i``'s lane of group ``g`` is
        ``(i // per_chunk * n_groups + g) * per_chunk + i % per_chunk``.
    """
    chunks = max(1, dr.thread_count())
    lanes = chunks * n_groups * (-(-int(n) // (chunks * 16)) * 16)
    # Opaque: counts that change from call to call (skipping's samples) reuse the kernels.
    per_chunk, last = dr.opaque(mi.UInt32, lanes // (chunks * n_groups)), dr.opaque(mi.UInt32, int(n) - 1)
    lane = dr.arange(mi.UInt32, lanes)
    chunk = lane // (n_groups * per_chunk)
    group = lane // per_chunk - chunk * n_groups
    item = chunk * per_chunk + lane % per_chunk
    return dr.minimum(item, last), group, item <= last, per_chunk


def corners(layout: GridLayout, u, levels=None):
    """Yield (level, table entry index, trilinear weight) for the 8 corners
    of every level (or of those in ``levels``) around normalised positions
    ``u`` (``mi.Point3f``), the weights scaled by ``layout.weights`` where given."""
    x_unit = dr.clip(mi.Vector3f(u), 0.0, 1.0)
    for level, r in enumerate(layout.resolutions):
        if levels is not None and level not in levels:
            continue
        x = x_unit * float(r)
        # Cell index clamped to r-1 so that corner x0+1 <= r stays in the grid.
        x0f = dr.minimum(dr.floor(x), float(r - 1))
        f = x - x0f
        x0 = mi.Vector3u(x0f)
        stride = r + 1
        for corner in range(8):
            bits = ((corner >> 0) & 1, (corner >> 1) & 1, (corner >> 2) & 1)
            w = None
            c = []
            for a in range(3):
                wa = f[a] if bits[a] else 1.0 - f[a]
                w = wa if w is None else w * wa
                c.append(x0[a] + 1 if bits[a] else x0[a])
            if layout.weights is not None:
                w = w * layout.weights[level]
            if layout.dense[level]:
                idx = c[0] + c[1] * stride + c[2] * (stride * stride)
            else:
                idx = (c[0] * _PRIMES[0]) ^ (c[1] * _PRIMES[1]) ^ (c[2] * _PRIMES[2])
                idx = idx & (layout.sizes[level] - 1)
            yield level, idx + layout.offsets[level], w


def half_table(grid):
    """A float16 copy (``Float16`` of the same backend, no derivatives) of
    a table ``grid`` (``mi.Float``) for :func:`query` to read."""
    return dr.float16_array_t(mi.Float)(dr.detach(grid))


def query(grid, layout: GridLayout, n_members: int, u, member=None, active=True, by_groups=True):
    """Summed trilinear grid features at positions ``u`` of the unit cube.

    The table is member-interleaved: entry ``e`` of member ``k`` occupies
    floats ``(e*K + k)*4 ... +3``. All K members' features of one vertex thus
    share a cache line and are read by *one* packet gather, and the corner
    indices/weights are computed once for all members: a K-member query
    costs little more than a single-member one.

    Args:
        grid: ``mi.Float`` table of ``n_entries * K * 4`` values, or its
           float16 copy (:func:`half_table`; the sums are float32 alike).
        layout: :class:`GridLayout`; n_members: K.
        u: ``mi.Point3f`` positions in ``[0, 1]^3`` (box-normalised; values
           outside are clamped to the border cells).
        member: None for all members, or an int / ``mi.UInt32`` per point.
        active: mask; inactive lanes read nothing and return 0.
        by_groups: a float16 table of :func:`level_groups` is read group by
           group (:func:`_query_by_groups`); False: in one lane per point,
           for counts that change from call to call (empty-space skipping's
           samples), whose grouped kernel Dr.Jit would compile anew each time.

    Returns:
        ``mi.Vector4f`` raw (density logit, r, g, b logits) summed over
        levels when ``member`` is given, else a list of K of them.
    """
    K = int(n_members)
    mode = reduce_mode()
    half = dr.type_v(grid) == dr.VarType.Float16
    if member is None and half and by_groups:
        groups = level_groups(layout, 2 * N_CHANNELS * K, LOOKUP_GROUP_BYTES, len(layout.resolutions) // 2)
        if len(groups) > 1:
            return _query_by_groups(grid, layout, K, u, active, groups)
    if member is None:
        XF = type(mi.ArrayXf())
        packet = dr.float16_array_t(XF) if half else XF
        acc = [[mi.Float(0.0)] * N_CHANNELS for _ in range(K)]
        for _, idx, w in corners(layout, u):
            # One K*4-wide packet gather per corner (index in units of K*4).
            v = dr.gather(packet, grid, idx, active, mode=mode, shape=(K * N_CHANNELS, dr.width(idx)))
            for k in range(K):
                for ch in range(N_CHANNELS):
                    acc[k][ch] = dr.fma(mi.Float(v[k * N_CHANNELS + ch]), w, acc[k][ch])
        return [mi.Vector4f(*a) for a in acc]
    mem = mi.UInt32(member)
    acc = [mi.Float(0.0)] * N_CHANNELS
    packet = dr.float16_array_t(mi.Vector4f) if half else mi.Vector4f
    for _, idx, w in corners(layout, u):
        v = dr.gather(packet, grid, idx * K + mem, active, mode=mode)
        for ch in range(N_CHANNELS):
            acc[ch] = dr.fma(mi.Float(v[ch]), w, acc[ch])
    return mi.Vector4f(*acc)


def _query_by_groups(grid, layout: GridLayout, K: int, u, active, groups):
    """:func:`query` of every member from a float16 table, one lane per
    point and level group (:func:`group_lanes`): each lane sums its group's
    levels into a buffer of partial sums, which the result adds up."""
    n = max(dr.width(u), dr.width(active))
    item, group, real, per_chunk = group_lanes(n, len(groups))
    u = dr.gather(mi.Point3f, mi.Point3f(u), item)
    active = dr.gather(mi.Bool, mi.Bool(active) & dr.full(mi.Bool, True, n), item) & real
    XF = type(mi.ArrayXf())
    C = K * N_CHANNELS

    def partial(levels):
        def f(u, active):
            acc = None
            for _, idx, w in corners(layout, u, levels):
                v = XF(dr.gather(dr.float16_array_t(XF), grid, idx, active, shape=(C, dr.width(idx))))
                acc = v * w if acc is None else dr.fma(v, w, acc)
            return tuple(acc[c] for c in range(C))
        return f

    def nothing(u, active):
        return tuple(dr.zeros(mi.Float, dr.width(active)) for _ in range(C))

    sums = [mi.Float(0.0)] * C
    for index, levels in enumerate(groups):
        # A group's lanes are whole SIMD packets: the others skip its corners.
        part = dr.if_stmt((u, active), group == index, partial(levels), nothing)
        sums = [a + b for a, b in zip(sums, part)]
    lanes = dr.width(item)
    buffer = dr.empty(mi.Float, lanes * C)
    dr.scatter(buffer, XF(*sums), dr.arange(mi.UInt32, lanes))
    # Point i's partial sums: its lane in each group (see group_lanes).
    i = dr.arange(mi.UInt32, n)
    chunk = i // per_chunk
    total = None
    for index in range(len(groups)):
        p = dr.gather(XF, buffer, (chunk * len(groups) + index) * per_chunk + (i - chunk * per_chunk),
                      shape=(C, n))
        total = p if total is None else total + p
    return [mi.Vector4f(*[total[k * N_CHANNELS + ch] for ch in range(N_CHANNELS)]) for k in range(K)]


def accumulate(table, layout: GridLayout, n_members: int, u, values, member=None, active=True):
    """Add ``values`` at positions ``u`` to ``table``, spread over the grid
    corners with the trilinear weights: the adjoint of :func:`query` (its
    gradient with respect to the table), in the same layout.

    Args:
        table: ``mi.Float`` of the grid table's size (the gradient being summed).
        values: ``K*4`` ``mi.Float`` (every member's 4, member after member)
            when ``member`` is None, else 4 (that member's).
        layout, n_members, u, member, active: as for :func:`query`.
    """
    K = int(n_members)
    mode = reduce_mode()
    XF = type(mi.ArrayXf())
    mem = None if member is None else mi.UInt32(member)
    for _, idx, w in corners(layout, u):
        if mem is None:  # one K*4-wide packet per corner, as query gathers it
            dr.scatter_add(table, XF(*[v * w for v in values]), idx, active, mode=mode)
        else:
            dr.scatter_add(table, mi.Vector4f(*[v * w for v in values]), idx * K + mem, active, mode=mode)
