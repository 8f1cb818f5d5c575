"""Empty-space skipping's march over the occupied samples alone, compacted ray by ray.

With an occupancy grid (:mod:`.occupancy`) most of a ray's S samples lie
in empty cells, where the density is 0: they leave the transmittance and
every running sum of the compositing exactly as they are. Here the occupied
samples are compacted (``dr.compress``, which keeps their order, so each
ray's come one after another), their positions, distances and features are
made for them alone, and each ray's march loops over its own ones only
(one ray per lane, a lane stopping after its count), forward and backward.
The outputs and derivatives are those of marching all S samples (tested);
what no longer grows with S is the work per skipped sample: writing its
position and features, reading them back in both marches, and writing its
gradient.

The rays' occupied counts differ widely (a trained field's: most rays
none, a few dozens), and a SIMD packet of lanes marches as long as its
longest ray. The marches therefore take the rays in order of their
counts (:func:`lanes_by_count`), so that a packet's rays march about
as long; each ray's outputs and its samples' gradients are those it
gets in any lane.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .grid import accumulate
from .march import _MarchedGrid
from .occupancy import occupied
from .samples import sample_along_rays


def compact_samples(params, s: dict, member=None) -> dict | None:
    """The occupied samples of ``s`` (:func:`.samples.sample_along_rays`
    of uniform bins, with ``params.occupancy``), compacted.

    Args:
        member: None, an int, or a per-sample ``mi.UInt32`` (R*S).
    Returns:
        None where no sample is occupied, else a dict of per-occupied-sample
        arrays (length M, ray after ray): ``u`` (``mi.Point3f``), ``t``,
        ``k`` (``mi.UInt32``, its index along its ray), ``member`` (as
        given, gathered where per sample); and per ray (length R):
        ``first`` (``mi.UInt32``, the index of its first occupied sample),
        ``count`` (``mi.UInt32``, how many it has), ``delta`` (bin length).
    """
    S = int(params.n_samples)
    R = dr.width(s["ray_valid"])
    ids = dr.compress(s["valid"] & occupied(params.occupancy, params.occupancy_resolution, s["u"]))
    M = dr.width(ids)
    if M == 0:
        return None
    jitter = None if s["jitter"] is None else dr.gather(mi.Float, s["jitter"], ids)
    at = sample_along_rays(s["o"], s["d"], params, jitter, index=ids)
    # Each ray's run of samples: its first and one past its last, written by
    # the samples where the ray changes (no atomics, no prefix sum).
    m = dr.arange(mi.UInt32, M)
    last = dr.opaque(mi.UInt32, M - 1)  # opaque: M changes from step to step, the kernels do not
    ray = ids // S
    starts = (m == 0) | (dr.gather(mi.UInt32, ids, m - 1, m > 0) // S != ray)
    ends = (m == last) | (dr.gather(mi.UInt32, ids, m + 1, m < last) // S != ray)
    first, end = dr.zeros(mi.UInt32, R), dr.zeros(mi.UInt32, R)
    dr.scatter(first, m, ray, starts)
    dr.scatter(end, m + 1, ray, ends)
    if member is not None and not isinstance(member, int) and dr.width(member) > 1:
        member = dr.gather(mi.UInt32, member, ids)
    out = {"u": at["u"], "t": at["t"], "k": ids - ray * S, "member": member, "first": first, "count": end - first,
           "delta": at["ray_delta"]}
    dr.eval(out["u"], out["t"], out["k"], first, end, out["delta"])
    return out


def lanes_by_count(count, S: int):
    """The march's lanes for rays with ``count`` occupied samples each
    (``mi.UInt32``, R, each at most ``S``), the counts ascending: ``order``
    (lane ``l`` marches ray ``order[l]``) and ``place`` (ray ``r`` is
    marched in lane ``place[r]``), both ``mi.UInt32`` (R).

    A counting sort in three small kernels, without reading anything back:
    the rays of one count take its lanes in any order (atomics), which
    changes nothing a ray computes.
    """
    n = dr.width(count)
    bins = dr.zeros(mi.UInt32, int(S) + 1)
    rank = dr.scatter_inc(bins, count)  # a ray's place among those of its count
    dr.eval(rank)  # Dr.Jit evaluates scatter_inc's result once, in the kernel of its own
    b = dr.arange(mi.UInt32, int(S) + 1)
    # The lanes before count b's: the rays with fewer samples.
    _, start = dr.while_loop((mi.UInt32(0), dr.zeros(mi.UInt32, int(S) + 1)), lambda i, acc: i < b,
                             lambda i, acc: (i + 1, acc + dr.gather(mi.UInt32, bins, i)))
    place = dr.gather(mi.UInt32, start, count) + rank
    order = dr.empty(mi.UInt32, n)
    dr.scatter(order, dr.arange(mi.UInt32, n), place)
    dr.eval(order, place)
    return order, place


def _permuted(values, index):
    """``values`` (nested tuples of per-ray Dr.Jit arrays, or None) gathered
    at ``index``; arrays of width 1 (a literal zero gradient) stay as they are."""
    if isinstance(values, (tuple, list)):
        return type(values)(_permuted(v, index) for v in values)
    if values is None or dr.width(values) == 1:
        return values
    return dr.gather(type(values), values, index)


class _CompactMarchedGrid(_MarchedGrid):
    """:class:`.march._MarchedGrid` over compacted samples (see the module
    docstring): ray ``r``'s march reads samples ``first[r]`` to
    ``first[r] + count[r] - 1``; the backward march adds each sample's
    gradient straight to its grid corners (no lane is left with skipped
    samples to trace corners for, and none waits long for the others: the
    lanes go by count). Lane ``l`` marches ray ``order[l]`` (:func:`lanes_by_count`):
    the outputs and their gradients are put back in ray order. A march stops
    early where the transmittance of every member falls below ``stop``."""

    def eval(self, grid, raws, lookup, t, first, count, k, delta, S, density_bias, inv_diag, stop, reg=None):
        self.grid_width, self.lookup, self.stop = dr.width(grid), lookup, stop
        self.t, self.valid, self.S, self.K = t, mi.Bool(True), S, len(raws)
        self.density_bias, self.inv_diag, self.reg = density_bias, inv_diag, reg
        self.k = k
        self._pack(raws)
        self.order, self.place = lanes_by_count(count, S)
        self.count, self.first, self.delta = _permuted((count, first, delta), self.order)
        self.per_ray = True
        return _permuted(self._outputs(), self.place)

    def grad_out(self):
        return _permuted(super().grad_out(), self.order)

    def set_grad_out(self, value):
        super().set_grad_out(_permuted(value, self.place))

    def _more(self, i):
        return i < self.count

    def _leading(self, i, j):
        return dr.gather(mi.UInt32, self.k, j) < self.reg[2]

    def _write_gradients(self, j, grads, valid):
        layout, n_members, u, member, _ = self.lookup
        if member is not None and dr.width(member) > 1:
            member = dr.gather(mi.UInt32, member, j)
        accumulate(self.table_grads, layout, n_members, dr.gather(mi.Point3f, u, j), grads, member, True)

    def backward(self):
        self.table_grads = dr.zeros(mi.Float, self.grid_width)
        self._march_gradients()
        self.set_grad_in("grid", self.table_grads)

    def name(self):
        return "composite_marched_compact"


def march_compact(params, c: dict, raws, reg=None):
    """Composite compacted samples ``c`` (:func:`compact_samples`) from their
    raw features ``raws`` (a tuple, one ``mi.Vector4f`` per member, length
    M), differentiable with respect to ``params.grid``: one (rgb, distance
    sum, opacity[, regularisers]) tuple per member, per ray (length R),
    each march stopping at ``params.stop_transmittance``."""
    lookup = (params.layout, params.n_members, c["u"], c["member"], True)
    return dr.custom(_CompactMarchedGrid, params.grid, raws, lookup, c["t"], c["first"], c["count"], c["k"],
                     c["delta"], int(params.n_samples), float(params.density_bias), 1.0 / params.diag,
                     float(params.stop_transmittance), reg)
