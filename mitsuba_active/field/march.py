"""Compositing of ray samples: blocked reductions, or a march per ray with its derivatives.

:func:`composite` composites blocks of S samples with blocked reductions
(``dr.block_prefix_sum`` for transmittance, ``dr.block_sum`` for the
outputs; the GPU's way). :func:`composite_marched` composites blocks of S samples one ray per lane,
keeping transmittance and the running sums in registers; its backward pass
marches once more and writes only the gradient of each sample's raw
features. :class:`_MarchedGrid` differentiates the grid table itself: the
backward march adds each sample's gradient straight to the sample's grid
corners, or, with empty-space skipping, to those of the occupied samples
alone after the march.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .grid import accumulate, query


def _raw_to_field(raw, valid, density_bias: float, inv_diag: float):
    """Density and colour of raw features, as in :func:`field_at`: (sigma,
    rgb, live); ``live`` marks where the density's gradient flows (inside
    the box, below the overflow guard)."""
    logit = raw[0] + density_bias
    # min(): exp overflow guard.
    sigma = dr.select(valid, dr.exp(dr.minimum(logit, 15.0)) * inv_diag, 0.0)
    rgb = mi.Color3f(dr.rcp(1.0 + dr.exp(-raw[1])), dr.rcp(1.0 + dr.exp(-raw[2])),
                     dr.rcp(1.0 + dr.exp(-raw[3])))
    return sigma, rgb, valid & (logit < 15.0)


class _MarchedComposite(dr.CustomOp):
    """:func:`composite_marched` with its derivatives (see there), for a
    tuple of members' raw features marched side by side.

    With regularisers ``reg`` (see :mod:`.regularisers`) each member has a
    fourth output, their weighted sum per ray. Their derivatives fit the
    compositing's closed form: the distortion's derivative with respect to
    the weight ``w_i`` is ``u_i = 2 sum_j w_j |m_i - m_j| + 2/3 w_i / S``,
    from the running sums before ``i`` and the totals (opacity, distance
    sum), and joins ``s_i`` below; the occlusion adds a constant to the
    derivative of the leading samples' optical depth.
    """

    def eval(self, raws, t, delta, valid, S, density_bias, inv_diag, reg=None):
        self.t, self.valid, self.S, self.K = t, valid, S, len(raws)
        self.density_bias, self.inv_diag = density_bias, inv_diag
        self.reg = reg
        self._pack(raws, delta)
        self.first = dr.arange(mi.UInt32, dr.width(t) // S) * S  # each ray's first sample
        self.delta = dr.gather(mi.Float, delta, self.first)
        self.per_ray = dr.width(valid) == dr.width(self.first)
        return self._outputs()

    def _pack(self, raws, *also):
        """Keep the members' raw features for the marches (``self.raws``),
        evaluated with ``self.t`` and the arrays ``also``."""
        # Several members' features of a sample side by side (K*4 floats):
        # the loop reads them with one packet load per ray instead of K*4
        # strided gathers. One member's 4 are read faster as they are (the
        # packing's transposes cost more than 4 gathers). Where the lookups are
        # not yet evaluated, one kernel traces them, writes them (packed) and
        # writes t and delta.
        n = dr.width(self.t)
        self.XF = type(mi.ArrayXf())  # for the packet gathers and scatters
        if self.K > 1:
            self.raws = dr.empty(mi.Float, 4 * self.K * n)
            # Dr.Jit's packet scatter cannot read arrays that a scatter has yet to
            # write (empty-space skipping's lookups are such): those go first.
            dr.eval([c for r in raws for c in r if c.state == dr.VarState.Dirty])
            dr.scatter(self.raws, self.XF(*[r[ch] for r in raws for ch in range(4)]), dr.arange(mi.UInt32, n))
        else:
            self.raws = raws[0]
        dr.eval(self.raws, self.t, *also)

    def _outputs(self):
        """March the rays (after :meth:`eval` has set ``first``, ``delta``
        and ``per_ray``) and return the members' outputs."""
        # The distortion's distances are normalised by the ray's length in the box.
        self.inv_length = dr.select(self.delta > 0, dr.rcp(self.delta * self.S), 0.0)
        out, _ = self._march()
        # Evaluated here so that the derivative passes read the outputs
        # instead of marching the rays again.
        dr.eval(out)
        self.out = out
        if self.reg is None:
            return out
        dw, ow, _ = self.reg
        return tuple((rgb, dsum, opac, dw * dist + ow * occ) for rgb, dsum, opac, dist, occ in out)

    #: Transmittance below which a ray's march stops (early ray termination, see
    #: ``FieldConfig.stop_transmittance``); 0: every sample is marched.
    stop = 0.0

    def _more(self, i):
        """Whether a ray's march goes on to its step ``i``."""
        return i < self.S

    def _going(self, i, states):
        """Whether a ray's march goes on to its step ``i``, given the members'
        loop states (transmittance first): some member still sees through."""
        more = self._more(i)
        if not self.stop:
            return more
        seen = states[0][0] > self.stop
        for state in states[1:]:
            seen |= state[0] > self.stop
        return more & seen

    def _distortion(self, w, t_i, p_dsum, p_opac):
        """A sample's share of the distortion loss (weight ``w`` at ``t_i``,
        the distance and opacity sums before it ``p_dsum``, ``p_opac``)."""
        return w * dr.fma(2.0 * self.inv_length, dr.fma(t_i, p_opac, -p_dsum), w * (1.0 / (3 * self.S)))

    def _distortion_slope(self, k, w, t_i, p_dsum, p_opac):
        """``u_i``: the distortion's derivative with respect to the weight of
        a sample of member ``k`` (arguments as for :meth:`_distortion`)."""
        _, dsum, opac = self.out[k][:3]
        inner = dr.fma(t_i, dr.fma(2.0, p_opac, -opac), dr.fma(-2.0, p_dsum, dsum))
        return dr.fma(2.0 * self.inv_length, inner, w * (2.0 / (3 * self.S)))

    def _leading(self, i, j):
        """Whether step ``i`` of the march (sample ``j``) is among the samples the occlusion penalty covers."""
        return i < self.reg[2]

    def _sample(self, i):
        """What the loop reads at step ``i`` of every ray: the sample index
        ``j``, its validity, distance, and each member's raw features."""
        j = self.first + i
        valid = self.valid if self.per_ray else dr.gather(mi.Bool, self.valid, j)
        t_i = dr.gather(mi.Float, self.t, j)  # read once for all members
        if self.K > 1:
            packed = dr.gather(self.XF, self.raws, j, shape=(4 * self.K, dr.width(j)))
            raws = [mi.Vector4f(*[packed[4 * k + ch] for ch in range(4)]) for k in range(self.K)]
        else:
            raws = [dr.gather(mi.Vector4f, self.raws, j)]
        return j, valid, t_i, raws

    def _alpha(self, raw, valid, trans):
        """Density, colour, where the density's gradient flows, weight and
        transmittance behind one sample of a member (transmittance ``trans``
        in front of it)."""
        sigma, c, live = _raw_to_field(raw, valid, self.density_bias, self.inv_diag)
        alpha_c = dr.exp(-sigma * self.delta)  # 1 - alpha
        return sigma, c, live, trans * (1.0 - alpha_c), trans * alpha_c

    def _march(self, visit=None, acc=()):
        """March every ray through its samples, all members in one loop:
        returns the members' final (rgb, dsum, opac[, distortion, occlusion])
        and ``acc``. After :meth:`eval`, ``acc = visit(k, i, j, sigma, c, t_i,
        live, w, trans_after, before, rest, acc)`` is called at step ``i``
        (sample ``j``) of each member ``k``, where ``before`` holds the
        (dsum, opac) sums before this sample and ``rest`` is what the samples
        behind it contribute to (rgb, dsum, opac): the outputs minus the
        running sums up to and including this sample; ``acc`` is loop state
        (per ray)."""
        z = dr.zeros(mi.Float, dr.width(self.delta))

        def step(i, sums, acc):
            j, valid, t_i, raws = self._sample(i)
            marched = []
            for k, (raw, state) in enumerate(zip(raws, sums)):
                trans, p_rgb, p_dsum, p_opac = state[:4]
                sigma, c, live, w, trans_after = self._alpha(raw, valid, trans)
                new = [trans_after, dr.fma(c, w, p_rgb), dr.fma(w, t_i, p_dsum), p_opac + w]
                if self.reg is not None:
                    new += [state[4] + self._distortion(w, t_i, p_dsum, p_opac),
                            state[5] + dr.select(self._leading(i, j), sigma * self.delta, 0.0)]
                if visit is not None:
                    out = self.out[k]
                    rest = (out[0] - new[1], out[1] - new[2], out[2] - new[3])
                    acc = visit(k, i, j, sigma, c, t_i, live, w, trans_after, (p_dsum, p_opac), rest, acc)
                marched.append(tuple(new))
            return i + 1, tuple(marched), acc

        extra = () if self.reg is None else (mi.Float(z), mi.Float(z))
        start = tuple((z + 1.0, mi.Color3f(z), mi.Float(z), mi.Float(z)) + extra for _ in range(self.K))
        _, sums, acc = dr.while_loop((mi.UInt32(0), start, acc), lambda i, sums, _: self._going(i, sums), step)
        return tuple(member[1:] for member in sums), acc

    def _march_gradients(self):
        """March the rays once more and hand each sample's gradient of the
        raw features (all members', K*4 values) to :meth:`_write_gradients`.

        For a member with outputs ``O = (rgb, dsum, opac)`` and output gradient
        ``g``, a sample's value ``s_i = <g, (colour_i, t_i, 1)>`` gives
        ``d<g, O>/d tau_i = T_{i+1} s_i - sum_{j>i} w_j s_j``; the sum behind
        ``i`` is ``<g, O>`` minus the running sum up to ``i``, so each member
        carries two scalars through the loop (transmittance and that sum).
        ``d<g, O>/d colour_i = w_i g_rgb``.

        With regularisers, the distortion's ``g dw u_i`` joins ``s_i`` (its
        ``sum_i w_i u_i`` is twice the distortion) and each member carries
        its (dsum, opac) running sums too; the occlusion's ``g ow`` is added
        to ``d/d tau_i`` of the leading samples.
        """
        g_out = self.grad_out()
        total = [dr.dot(g[0], out[0]) + g[1] * out[1] + g[2] * out[2] for g, out in zip(g_out, self.out)]
        if self.reg is not None:
            dw, ow, _ = self.reg
            total = [tot + 2.0 * dw * g[3] * out[3] for tot, g, out in zip(total, g_out, self.out)]

        def step(i, state):
            j, valid, t_i, raws = self._sample(i)
            grads, marched = [], []
            for k, (raw, member) in enumerate(zip(raws, state)):
                trans, before = member[:2]
                g_rgb, g_dsum, g_opac = g_out[k][:3]
                sigma, c, live, w, trans_after = self._alpha(raw, valid, trans)
                s_i = dr.dot(g_rgb, c) + dr.fma(g_dsum, t_i, g_opac)
                if self.reg is not None:
                    p_dsum, p_opac = member[2:]
                    s_i = dr.fma(dw * g_out[k][3], self._distortion_slope(k, w, t_i, p_dsum, p_opac), s_i)
                before = dr.fma(w, s_i, before)
                g_tau = dr.fma(trans_after, s_i, before - total[k])
                if self.reg is not None:
                    g_tau = g_tau + dr.select(self._leading(i, j), ow * g_out[k][3], 0.0)
                    marched.append((trans_after, before, dr.fma(w, t_i, p_dsum), p_opac + w))
                else:
                    marched.append((trans_after, before))
                grads.append(dr.select(live, g_tau * self.delta * sigma, 0.0))
                grads += [g_rgb[ch] * w * c[ch] * (1.0 - c[ch]) for ch in range(3)]
            self._write_gradients(j, grads, valid)
            return i + 1, tuple(marched)

        z = dr.zeros(mi.Float, dr.width(self.delta))
        extra = () if self.reg is None else (mi.Float(z), mi.Float(z))
        dr.while_loop((mi.UInt32(0), tuple((z + 1.0, mi.Float(z)) + extra for _ in range(self.K))),
                      self._going, step)

    def _write_gradients(self, j, grads, valid):
        """Store sample ``j``'s gradients (``grads``: K*4 ``mi.Float``, laid
        out as the packed features): one packet store per lane."""
        dr.scatter(self.grads, self.XF(*grads), j)

    def backward(self):
        n = dr.width(self.t)
        self.grads = dr.empty(mi.Float, 4 * self.K * n)  # the loop writes every sample
        self._march_gradients()
        g = dr.gather(self.XF, self.grads, dr.arange(mi.UInt32, n), shape=(4 * self.K, n))
        self.set_grad_in("raws", tuple(mi.Vector4f(*[g[4 * k + ch] for ch in range(4)]) for k in range(self.K)))

    def _march_tangents(self, d_raws):
        """Forward-mode derivatives of the outputs along the members' raw
        feature tangents ``d_raws`` (one ``mi.Vector4f`` per member)."""
        def visit(k, i, j, sigma, c, t_i, live, w, trans_after, before, rest, acc):
            d = dr.gather(mi.Vector4f, d_raws[k], j)
            d_tau = dr.select(live, d[0] * self.delta * sigma, 0.0)
            d_c = mi.Color3f(*[d[ch + 1] * c[ch] * (1.0 - c[ch]) for ch in range(3)])
            d_rgb, d_dsum, d_opac = acc[k][:3]
            member = (d_rgb + d_tau * dr.fma(c, trans_after, -rest[0]) + w * d_c,
                      d_dsum + d_tau * dr.fma(t_i, trans_after, -rest[1]),
                      d_opac + d_tau * (trans_after - rest[2]))
            if self.reg is not None:
                # The distortion's tangent: sum_i d_tau_i (T_(i+1) u_i - sum_(j>i) w_j u_j).
                dw, ow, _ = self.reg
                d_reg, wu = acc[k][3:]
                u = self._distortion_slope(k, w, t_i, *before)
                wu = dr.fma(w, u, wu)
                rest_u = 2.0 * self.out[k][3] - wu
                slope = dw * dr.fma(trans_after, u, -rest_u) + dr.select(self._leading(i, j), ow, 0.0)
                member += (dr.fma(d_tau, slope, d_reg), wu)
            return acc[:k] + (member,) + acc[k + 1:]

        z = dr.zeros(mi.Float, dr.width(self.delta))
        extra = () if self.reg is None else (mi.Float(z), mi.Float(z))
        start = tuple((mi.Color3f(z), mi.Float(z), mi.Float(z)) + extra for _ in range(self.K))
        tangents = self._march(visit, start)[1]
        self.set_grad_out(tuple(member[:3] + member[3:4] for member in tangents))

    def forward(self):
        self._march_tangents(self.grad_in("raws"))

    def name(self):
        return "composite_marched"


class _MarchedGrid(_MarchedComposite):
    """:class:`_MarchedComposite` of features looked up from a grid table,
    differentiated with respect to the table itself.

    Its backward march adds each sample's gradient straight to the sample's
    grid corners (the adjoint of :func:`.grid.query`) instead of writing it
    out for a separate scatter kernel to read back: for K members that saves
    writing and reading K*4 floats a sample and tracing the corners twice.
    """

    def eval(self, grid, raws, lookup, t, delta, valid, S, density_bias, inv_diag, reg=None):
        # lookup: (layout, n_members, u, member, active), the arguments the features were queried with.
        self.grid_width, self.lookup = dr.width(grid), lookup
        return super().eval(raws, t, delta, valid, S, density_bias, inv_diag, reg)

    def _write_gradients(self, j, grads, valid):
        if not self.per_ray:  # stored, and added to the occupied samples' corners after the march
            return super()._write_gradients(j, grads, valid)
        layout, n_members, u, member, _ = self.lookup
        if member is not None and dr.width(member) > 1:
            member = dr.gather(mi.UInt32, member, j)
        accumulate(self.table_grads, layout, n_members, dr.gather(mi.Point3f, u, j), grads, member, valid)

    def backward(self):
        self.table_grads = dr.zeros(mi.Float, self.grid_width)
        if self.per_ray:
            self._march_gradients()
        else:
            # Inside the march every lane would trace its corners, skipped or not
            # (with 12 levels most of a step): only the occupied samples' here.
            self.grads = dr.empty(mi.Float, 4 * self.K * dr.width(self.t))
            self._march_gradients()
            layout, n_members, u, member, _ = self.lookup
            ids = dr.compress(self.valid)
            if dr.width(ids) > 0:
                g = dr.gather(self.XF, self.grads, ids, shape=(4 * self.K, dr.width(ids)))
                if member is not None and dr.width(member) > 1:
                    member = dr.gather(mi.UInt32, member, ids)
                accumulate(self.table_grads, layout, n_members, dr.gather(mi.Point3f, u, ids),
                           [g[c] for c in range(4 * self.K)], member, True)
        self.set_grad_in("grid", self.table_grads)

    def forward(self):
        layout, n_members, u, member, active = self.lookup
        d_raws = query(self.grad_in("grid"), layout, n_members, u, member, active)
        self._march_tangents(d_raws if member is None else [d_raws])

    def name(self):
        return "composite_marched_grid"


def composite_marched(raw, t, delta, valid, S: int, density_bias: float, inv_diag: float, reg=None):
    """Alpha-composite blocks of S samples from their raw features, one ray
    per lane, without per-sample intermediates.

    The same outputs as :func:`.samples.field_at` followed by :func:`composite`
    (transmittance as a running product instead of the exponential of a
    prefix sum: equal to rounding), as a ``drjit.CustomOp``: the forward pass
    marches each ray through its samples in a loop, keeping transmittance and
    the running sums in registers; the backward pass marches once more and
    writes only the gradient of each sample's raw features, using the
    outputs for what the samples behind it contribute (the closed form of
    Instant-NGP's renderer). This avoids the per-sample arrays of the blocked
    reductions and their adjoints, whose memory traffic grows with the
    members of an ensemble. Several members' features (a list) are marched
    in the same loop, which reads the samples' distances once for all.

    Args:
        raw: ``mi.Vector4f`` summed grid features per sample (R*S), or a
            list of them, one per member;
        t, delta: per-sample distance and bin length (R*S; ``delta`` is
            read at each ray's first sample), not differentiated;
        valid: ``mi.Bool`` per sample (R*S), or per ray (R) where all of a
            ray's samples share it; invalid samples (outside the box,
            skipped) have no density;
        reg: the regularisers' (distortion weight, occlusion weight,
            occlusion samples), see :mod:`.regularisers`, or None.
    Returns:
        (rgb ``mi.Color3f``, distance sum ``sum w t``, opacity ``sum w``),
        each of length R, as :func:`composite` returns them, and with
        ``reg`` the regularisers' weighted sum per ray; for a list, a list
        of such tuples, one per member.
    """
    raws = tuple(raw) if isinstance(raw, (list, tuple)) else (raw,)
    out = dr.custom(_MarchedComposite, raws, t, delta, valid, int(S), float(density_bias), float(inv_diag), reg)
    return list(out) if isinstance(raw, (list, tuple)) else out[0]


def composite(tau, rgb_s, t, S: int):
    """Alpha-composite blocks of S samples.

    Args:
        tau: per-sample optical depth ``sigma * delta`` (``mi.Float``, R*S).
        rgb_s: per-sample colour (``mi.Color3f``, R*S).
        t: per-sample distance from the origin (``mi.Float``, R*S).
    Returns:
        (weights (R*S), rgb (R, un-normalised, without background),
        distance sum ``sum w t`` (R), opacity ``sum w`` (R)).
    """
    # Transmittance up to (excluding) each sample: exp(-exclusive prefix sum).
    trans = dr.exp(-dr.block_prefix_sum(tau, S))
    w = trans * (1.0 - dr.exp(-tau))
    # One blocked reduction over a 5-component struct instead of five calls.
    red = dr.block_sum(mi.Vector4f(w * rgb_s[0], w * rgb_s[1], w * rgb_s[2], w * t), S)
    opac = dr.block_sum(w, S)
    return w, mi.Color3f(red[0], red[1], red[2]), red[3], opac
