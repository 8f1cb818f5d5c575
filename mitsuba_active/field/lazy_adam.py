"""Lazy Adam over the grid table: a step updates only the entries it touched.

A training step's samples touch a small part of a many-level grid, yet
``drjit.opt.Adam`` reads and writes the whole table (parameters, gradient and
both moments) and Dr.Jit's per-thread gradient copies (``ReduceMode.Expand``)
are as large as the table, so a step's cost would grow with the table rather
than with the samples. Here the gradient goes into two sinks
(:class:`GridGradient`):

* the small coarse levels (the first ``split`` entries: every level while the
  entries up to its end number at most :data:`EXPAND_ENTRIES`) into a fresh
  zero array per step, scattered with per-thread copies (their entries are
  hit by many samples at once, where atomics would contend);
* the other levels into an array kept at zero between steps, scattered
  without atomics (``ReduceMode.NoConflicts``: their entries are spread
  thinly over the samples; two threads adding to one entry at the same
  instant may lose one of the two terms, which plain SGD tolerates as
  Hogwild! does), marking each entry it adds to in a byte array. The
  update compacts the marked rows (entries, all members' ``K*4`` floats),
  updates those alone and clears their gradient and mark again: it reads a
  byte per entry, and the rest of its work follows the samples.

As in Instant-NGP, a float whose gradient is exactly 0 keeps its value and
both moments (no decay, no momentum step); the bias correction uses the
global step count. Gradients that reach the table through Dr.Jit's automatic
differentiation instead (a loss term of one's own, the variational field's
draws, the GPU's compositing) are folded in by a dense update of the same
rule over the whole table.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from .grid import N_CHANNELS, GridLayout

#: Coarse levels' entries whose gradient is scattered with per-thread copies
#: (at most this many entries per member).
EXPAND_ENTRIES = 1 << 16


def split_entry(layout: GridLayout) -> int:
    """The first entry of the levels whose gradient is kept between steps:
    the end of the last level that ends within :data:`EXPAND_ENTRIES`."""
    split = 0
    for off, size in zip(layout.offsets, layout.sizes):
        if off + size > EXPAND_ENTRIES:
            break
        split = off + size
    return split


class GridGradient:
    """The grid's gradient of one training step, in two parts (see the module).

    Attributes:
        split: first entry (per member) of the large part.
        row: floats per entry, ``K * 4``.
        small: ``mi.Float`` ``split * row``: the coarse levels' gradient (fresh each step).
        large: ``mi.Float`` ``(n_entries - split) * row``, zero between steps.
        touched: ``mi.Bool`` ``n_entries - split``: the large part's entries
            added to this step (False between steps).
        param: the grad-enabled table this step's renders read (the sink
            serves that array only; another one gets Dr.Jit's gradient).
    """

    def __init__(self, layout: GridLayout, n_members: int):
        self.split = split_entry(layout)
        self.row = int(n_members) * N_CHANNELS
        self.n_entries = layout.n_entries
        self.small = dr.zeros(mi.Float, self.split * self.row)
        self.large = dr.zeros(mi.Float, (self.n_entries - self.split) * self.row)
        self.touched = dr.zeros(mi.Bool, self.n_entries - self.split)
        self.param = None

    def target(self, level_offset: int):
        """(array, first entry, scatter mode, marks or None) for the level starting at ``level_offset``."""
        if level_offset < self.split:
            return self.small, 0, dr.ReduceMode.Expand, None
        # Racy writes are rare among a CPU's few threads, not among a GPU's thousands.
        cpu = dr.backend_v(mi.Float) == dr.JitBackend.LLVM
        return self.large, self.split, dr.ReduceMode.NoConflicts if cpu else dr.ReduceMode.Auto, self.touched

    def renew_small(self):
        self.small = dr.zeros(mi.Float, self.split * self.row)


class LazyAdam:
    """Adam over the grid table (``mi.Float`` ``n_entries * K * 4``) with the
    update rule of the module docstring; ``m``, ``v`` and ``t`` as in
    ``drjit.opt.Adam`` (``t`` counts steps)."""

    def __init__(self, table, layout: GridLayout, n_members: int, lr: float, beta_1: float, beta_2: float,
                 epsilon: float, m=None, v=None, t: int = 0):
        self.table = mi.Float(table)
        n = dr.width(self.table)
        self.m = dr.zeros(mi.Float, n) if m is None else mi.Float(m)
        self.v = dr.zeros(mi.Float, n) if v is None else mi.Float(v)
        self.t = int(t)
        self.lr, self.beta_1, self.beta_2, self.epsilon = float(lr), float(beta_1), float(beta_2), float(epsilon)
        self.gradient = GridGradient(layout, n_members)
        dr.eval(self.table, self.m, self.v)
        self._param = None

    def param(self):
        """The table as this step's grad-enabled parameter (the same array for every call until the step)."""
        if self._param is None:
            self._param = mi.Float(self.table)
            dr.enable_grad(self._param)
            self.gradient.param = self._param
        return self._param

    def _update(self, g, m, v, p, scale):
        """Adam's new (m, v, p) of floats with gradient ``g``; unchanged where ``g`` is 0."""
        m2 = dr.lerp(g, m, self.beta_1)
        v2 = dr.lerp(dr.square(g), v, self.beta_2)
        # drjit.opt.Adam's form, so that both optimisers agree.
        if self.epsilon <= 1e-6:
            p2 = dr.fma(m2 * dr.rsqrt(v2 + self.epsilon ** 2), scale, p)
        else:
            p2 = dr.fma(m2 / (dr.sqrt(v2) + self.epsilon), scale, p)
        keep = g == 0
        return dr.select(keep, m, m2), dr.select(keep, v, v2), dr.select(keep, p, p2)

    def step(self):
        """Apply one update from this step's gradient (both sinks, plus any
        that automatic differentiation left on :meth:`param`)."""
        self.t += 1
        t = self.t
        # Opaque: the bias correction changes every step, the kernels do not.
        scale = dr.opaque(mi.Float, -self.lr * math.sqrt(1 - self.beta_2 ** t) / (1 - self.beta_1 ** t))
        G = self.gradient
        dense = None
        if self._param is not None:
            grad = dr.grad(self._param)
            if grad.state != dr.VarState.Literal:
                dense = mi.Float(grad)
        self._param = G.param = None  # the table's only reference is ours again: scatters update it in place
        if dense is not None:
            self._dense_step(dense, scale)
            return
        n_small = G.split * G.row
        if n_small:
            i = dr.arange(mi.UInt32, n_small)
            g = G.small
            m, v, p = (dr.gather(mi.Float, a, i) for a in (self.m, self.v, self.table))
            m, v, p = self._update(g, m, v, p, scale)
            dr.eval(m, v, p)  # before the scatters, as in _sparse_step
            for a, x in ((self.m, m), (self.v, v), (self.table, p)):
                dr.scatter(a, x, i)
            G.renew_small()
        if G.n_entries > G.split:
            self._sparse_step(scale)
        dr.eval(self.table, self.m, self.v, G.large, G.small, G.touched)

    def _sparse_step(self, scale):
        """Update the large part's rows with a non-zero gradient and zero them."""
        G = self.gradient
        XF = type(mi.ArrayXf())
        R = G.row
        rows = dr.compress(G.touched)
        n = dr.width(rows)
        if n == 0:
            return
        g = dr.gather(XF, G.large, rows, shape=(R, n))
        at = rows + G.split
        old = [dr.gather(XF, a, at, shape=(R, n)) for a in (self.m, self.v, self.table)]
        new = [self._update(g[c], old[0][c], old[1][c], old[2][c], scale) for c in range(R)]
        new = [XF(*[x[j] for x in new]) for j in range(3)]
        # Evaluated before the scatters: pending gathers of the arrays would make them copy the arrays first.
        dr.eval(new)
        del g, old
        # Written 4 floats at a time: Dr.Jit 1.5's plain scatters of 8 or more
        # floats a lane crashed (K >= 2) where its packet gathers do not.
        zero = mi.Vector4f(0.0)
        for k in range(R // N_CHANNELS):
            four = slice(N_CHANNELS * k, N_CHANNELS * (k + 1))
            for a, x in zip((self.m, self.v, self.table), new):
                dr.scatter(a, mi.Vector4f(*list(x)[four]), at * (R // N_CHANNELS) + k, mode=dr.ReduceMode.NoConflicts)
            dr.scatter(G.large, zero, rows * (R // N_CHANNELS) + k)
        dr.scatter(G.touched, False, rows)

    def _dense_step(self, grad, scale):
        """The same rule over the whole table, for a gradient of Dr.Jit's (plus the sinks')."""
        G = self.gradient
        i = dr.arange(mi.UInt32, G.n_entries * G.row)
        n_small = G.split * G.row
        if n_small:
            grad = grad + dr.gather(mi.Float, G.small, i, i < n_small)
        if G.n_entries > G.split:
            grad = grad + dr.gather(mi.Float, G.large, i - n_small, i >= n_small)
        self.m, self.v, self.table = self._update(grad, self.m, self.v, self.table, scale)
        G.renew_small()
        G.large = dr.zeros(mi.Float, dr.width(G.large))
        G.touched = dr.zeros(mi.Bool, dr.width(G.touched))
        dr.eval(self.table, self.m, self.v, G.large, G.small, G.touched)
