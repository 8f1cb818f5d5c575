"""Few-view regularisers of a training render: distortion, near-camera occlusion, random backgrounds, grid smoothness.

Per ray of S samples with weights ``w_i``, distances ``t_i`` (sorted) and
optical depths ``tau_i``:

* the distortion loss of mip-NeRF 360, over distances normalised by the
  ray's length in the box ``L = S * delta`` (``m_i = t_i / L``, bins of
  ``1 / S``): ``sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 / S``, in O(S)
  as ``sum_i w_i (2 (m_i W_i - X_i) + w_i / (3 S))`` with the exclusive
  running sums ``W_i = sum_(j<i) w_j`` and ``X_i = sum_(j<i) w_j m_j``;
  it pulls a ray's weight together into one short stretch (no floaters,
  no fog spread along the ray);
* FreeNeRF's occlusion penalty: the optical depth of the ray's first
  ``M`` samples in the box, ``sum_(i<M) tau_i`` (density there, in front of
  every training camera, is what few views fit with floaters).

and of the grid itself, the total variation of Plenoxels: the mean over a
dense level's vertices and the three axes of ``|f(v + e_a) - f(v)|^2`` (the
4 features of a vertex; pairs that leave the level count as 0), summed
over the dense levels (:func:`grid_smoothness`).

The marched compositing (:class:`.march._MarchedComposite`) computes their
weighted sum as a fourth output with closed-form derivatives;
:func:`blocked_regulariser` is the same from the blocked reductions' weights.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .samples import hash_u32, uniform_from_u32
from .sky import background_colour



def ray_regularisers(config, n_samples: int | None = None) -> tuple | None:
    """The regularisers a :class:`.FieldConfig` asks of its training renders
    of ``n_samples`` samples a ray (None: ``config.n_samples``): (distortion
    weight, occlusion weight, occlusion samples ``M``), or None when both
    weights are 0."""
    dw, ow = float(config.distortion_weight), float(config.occlusion_weight)
    if dw == 0 and ow == 0:
        return None
    return dw, ow, occlusion_samples(config, n_samples)


def occlusion_samples(config, n_samples: int | None = None) -> int:
    """``M``: the leading samples of a ray of ``n_samples`` (None:
    ``config.n_samples``) that the occlusion penalty covers
    (``occlusion_fraction`` of them, at least 1)."""
    n = int(config.n_samples if n_samples is None else n_samples)
    return max(1, int(round(float(config.occlusion_fraction) * n)))


def blocked_regulariser(w, tau, t, delta, S: int, reg: tuple):
    """The weighted regularisers of blocks of S samples (see the module docstring).

    Args:
        w, tau, t, delta: per-sample weight, optical depth, distance and bin
            length (``mi.Float``, R*S; differentiable).
        reg: as :func:`ray_regularisers` gives it.
    Returns:
        ``mi.Float`` (R): ``dw * distortion + ow * occlusion`` per ray.
    """
    dw, ow, M = reg
    k = dr.arange(mi.UInt32, dr.width(w))
    k = k - (k // S) * S  # each sample's index along its ray
    inv_length = dr.select(delta > 0, dr.rcp(delta * S), 0.0)
    m = t * inv_length
    before_w = dr.block_prefix_sum(w, S)  # exclusive
    before_x = dr.block_prefix_sum(w * m, S)
    per = dw * w * (2.0 * (m * before_w - before_x) + w * (1.0 / (3 * S)))
    per = per + ow * dr.select(k < M, tau, 0.0)
    return dr.block_sum(per, S)


def _dense_levels(layout, n_members: int):
    """Per dense level: (its vertices' and members' first float in the table,
    vertices per axis ``n``, the (vertex, member) pairs' ``i``, and each
    pair's vertex coordinates (x, y, z))."""
    K = int(n_members)
    for r, off, dense in zip(layout.resolutions, layout.offsets, layout.dense):
        if dense:
            n = int(r) + 1
            i = dr.arange(mi.UInt32, n ** 3 * K)
            v = i // K
            yield off * K, n, i, (v % n, (v // n) % n, v // (n * n))


class _GridSmoothness(dr.CustomOp):
    """:func:`grid_smoothness` with its gradient in closed form: a vertex's is
    ``2 sum_a (2 f(v) - f(v + e_a) - f(v - e_a)) / (3 n^3)`` over the
    neighbours it has, gathered per vertex and written once, where Dr.Jit's
    own adjoint of the gathers would add them with atomics."""

    def eval(self, grid, layout, n_members):
        self.grid, self.layout, self.K = grid, layout, int(n_members)
        total = mi.Float(0.0)
        for first, n, i, coords in _dense_levels(layout, n_members):
            a = dr.gather(mi.Vector4f, grid, i + first)
            for stride, c in zip((1, n, n * n), coords):
                inside = c < n - 1
                b = dr.gather(mi.Vector4f, grid, i + first + stride * self.K, inside)
                total += dr.sum(dr.select(inside, dr.squared_norm(b - a), 0.0)) * (1.0 / (3 * n ** 3))
        return total

    def backward(self):
        g = self.grad_out()
        out = dr.zeros(mi.Float, dr.width(self.grid))
        for first, n, i, coords in _dense_levels(self.layout, self.K):
            a = dr.gather(mi.Vector4f, self.grid, i + first)
            lap = mi.Vector4f(0.0)
            for stride, c in zip((1, n, n * n), coords):
                step = stride * self.K
                for there, ok in ((i + first + step, c < n - 1), (i + first - step, c > 0)):
                    lap += dr.select(ok, a - dr.gather(mi.Vector4f, self.grid, there, ok), 0.0)
            dr.scatter(out, lap * (g * (2.0 / (3 * n ** 3))), i + first)
        self.set_grad_in("grid", out)

    def name(self):
        return "grid_smoothness"


def grid_smoothness(grid, layout, n_members: int):
    """The grid's total variation (see the module docstring), summed over members.

    Args:
        grid: the table (``mi.Float``, ``n_entries * n_members * 4``, laid out
            ``[entry][member][channel]``; differentiable).
        layout: its :class:`.grid.GridLayout`; hashed levels are left out.
    Returns:
        ``mi.Float`` scalar (0 when no level is dense).
    """
    return dr.custom(_GridSmoothness, grid, layout, int(n_members))


def random_background(params, rays: dict, idx, target, outs: list, seed: int, step: int):
    """A training batch's targets and renders with a random colour per ray as the
    background of its rays known empty (``FieldConfig.random_background``).

    ``params``: the field's :class:`~.samples.FieldParams`; ``rays``: its training
    rays (``mi`` arrays ``d``, ``empty``); ``idx``: the batch's ray indices;
    ``target``: their colours; ``outs``: the members' renders. Each render is
    ``C + (1 - opacity) bg``; adding ``(1 - opacity) (random - bg)`` swaps the
    background without another render, and the learnt background gets no
    gradient from those rays."""
    empty = dr.gather(mi.Bool, rays["empty"], idx)
    key = dr.opaque(mi.UInt32, (seed * 0x2C1B3C6D + step * 0x297A2D39 + 7) & 0xFFFFFFFF)
    i = dr.arange(mi.UInt32, dr.width(idx)) * 3
    colour = mi.Color3f(*[uniform_from_u32(hash_u32(hash_u32(i + c) ^ key)) for c in range(3)])
    d = dr.gather(mi.Vector3f, rays["d"], idx)
    swapped = []
    for k, out in enumerate(outs):
        bg = background_colour(params, d, k, dr.width(idx))
        rgb = out["rgb"] + dr.select(empty, (1.0 - out["opacity"]) * (colour - bg), 0.0)
        swapped.append({**out, "rgb": rgb})
    return dr.select(empty, colour, target), swapped
