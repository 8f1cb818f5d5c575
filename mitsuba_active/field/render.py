"""Volume rendering of flat ray batches with Dr.Jit arrays (no numpy).

Looks up the samples of :mod:`.samples` in the grid (with an occupancy
grid, only those in occupied cells), composites them (:mod:`.march`:
marching one ray per lane on the CPU, blocked reductions otherwise) and puts
each member's background behind them, plus the view-dependent colour where
the field has it. Each ray carries the index of the ensemble member it
belongs to, which selects that member's slice of the shared parameter
table: K members are rendered by one set of kernels over K*R rays instead
of K Python-driven passes.

Units: positions and distances are in scene units; directions are unit
vectors, so the returned distance is metric from the ray origin (the
camera's optical centre).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .compact import compact_samples, march_compact
from .grid import query
from .march import _MarchedGrid, composite, composite_marched
from .occupancy import occupied
from .regularisers import blocked_regulariser
from .samples import FieldParams, field_at, field_position, sample_along_rays
from .sky import background_colour
from .view import view_residual


def lookup_samples(params: FieldParams, s: dict, member=None):
    """Summed grid features of the samples ``s`` (see :func:`.grid.query`).

    With an occupancy grid, samples in empty cells are dropped from
    ``s["valid"]`` and only the others are looked up: they are compacted
    (``dr.compress``), queried, and scattered back, so the cost follows
    the occupied samples rather than all ``R*S``. Dropped samples read 0.

    Args:
        member: None (all members: returns a list of K ``mi.Vector4f``),
            an int, or a per-sample ``mi.UInt32``.
    """
    table = params.lookup_table()
    if params.occupancy is None:
        return query(table, params.layout, params.n_members, s["u"], member, s["valid"])
    s["valid"] = s["valid"] & occupied(params.occupancy, params.occupancy_resolution, s["u"])
    n = dr.width(s["valid"])
    ids = dr.compress(s["valid"])
    n_members = params.n_members if member is None else 1
    if dr.width(ids) == 0:
        zero = dr.zeros(mi.Vector4f, n)
        return [zero] * n_members if member is None else zero
    u = dr.gather(mi.Point3f, s["u"], ids)
    if member is not None and not isinstance(member, int) and dr.width(member) > 1:
        member = dr.gather(mi.UInt32, member, ids)
    raw = query(table, params.layout, params.n_members, u, member, True, by_groups=False)

    def expand(r):
        full = dr.zeros(mi.Vector4f, n)
        dr.scatter(full, r, ids)
        return full

    return [expand(r) for r in raw] if member is None else expand(raw)


def _marching(s: dict, return_weights: bool) -> bool:
    """Whether to composite with :func:`composite_marched`: on the CPU, where
    it saves the per-sample arrays' memory traffic, unless the weights are
    wanted or the sample distances carry gradients (it differentiates the
    raw features only), or the bins of a ray differ in length (it reads one
    per ray: a contracted field's samples). The GPU keeps the blocked reductions: a loop over
    S samples in one lane per ray would occupy few of its threads (not
    measured there)."""
    return (not return_weights and dr.backend_v(mi.Float) == dr.JitBackend.LLVM
            and not dr.grad_enabled(s["t"], s["delta"]) and s.get("uniform", True))


def _marched_valid(params: FieldParams, s: dict):
    """Validity of the samples for :func:`composite_marched`: per ray without
    empty-space skipping (a sample is valid where its ray is), else per sample."""
    return s["valid"] if params.occupancy is not None else s["ray_valid"]


def _composited(params: FieldParams, s: dict, raws: list, members: list, return_weights=False, reg=None) -> list:
    """Composite the raw features of the members ``members`` (one ``raws``
    each, evaluated or not): marched together, or one by one with the blocked
    reductions; returns one render_flat dict per member."""
    S = int(params.n_samples)
    if _marching(s, return_weights):
        sums = composite_marched(raws, s["t"], s["delta"], _marched_valid(params, s), S, params.density_bias,
                                 1.0 / params.diag, reg)
        sums = [(*member[:3], None, member[3] if reg else None) for member in sums]
    else:
        sums = []
        for raw, member in zip(raws, members):
            sigma, rgb_s = field_at(params, s["u"], member, s["valid"], raw=raw)
            tau = sigma * s["delta"]
            w, rgb, dsum, opac = composite(tau, rgb_s, s["t"], S)
            sums.append((rgb, dsum, opac, w, blocked_regulariser(w, tau, s["t"], s["delta"], S, reg) if reg else None))
    return _over_background(params, s, sums, members, return_weights)


def _over_background(params: FieldParams, s: dict, sums: list, members: list, return_weights: bool) -> list:
    """render_flat dicts of the members ``members`` from their composited
    (rgb, distance sum, opacity, weights or None, regularisers or None) of
    the samples ``s``, with the view-dependent colour where the field has it."""
    outs = []
    for member, (rgb, dsum, opac, w, reg) in zip(members, sums):
        bg = background_colour(params, s["d"], member, dr.width(opac))
        distance = dsum / dr.maximum(opac, 1e-6)
        rgb = rgb + (1.0 - opac) * bg
        if params.view is not None:
            rgb = rgb + dr.detach(opac) * _view_colour(params, s, dr.detach(distance), member)
            if not dr.grad_enabled(params.view):  # a render, not a training step: colours as images hold them
                rgb = dr.clip(rgb, 0.0, 1.0)
        out = dict(rgb=rgb, distance=distance, opacity=opac)
        if return_weights:
            out["weights"] = w
        if reg is not None:
            out["regulariser"] = reg
        outs.append(out)
    return outs


def _view_colour(params: FieldParams, s: dict, distance, member):
    """The view-dependent colour residual (``mi.Color3f``, per ray) at the
    rays' expected hits ``distance`` away (see :mod:`.view`)."""
    o, d = mi.Point3f(s["o"]), mi.Vector3f(s["d"])
    u = field_position(params, dr.fma(d, distance, o))
    return view_residual(params.view, params.view_resolution, params.view_degree, params.n_members, u, d, member)


def _rendered(params: FieldParams, s: dict, member, members: list, return_weights=False, reg=None) -> list:
    """Look up and composite the samples ``s``: ``member`` as for
    :func:`lookup_samples` (None: every member), ``members`` the member of
    each output (see render_flat), ``reg`` as for :func:`composite_marched`."""
    if not _marching(s, return_weights):
        raws = lookup_samples(params, s, member)
        raws = raws if member is None else [raws]
        # Evaluated once, in one kernel: otherwise every blocked reduction and every
        # backward kernel would re-trace and re-run the 8 * n_levels gathers.
        dr.eval(raws, s["t"], s["delta"])
        return _composited(params, s, raws, members, return_weights, reg)
    c = compact_samples(params, s, member) if params.occupancy is not None else None
    if c is not None:  # the occupied samples alone (see .compact)
        with dr.suspend_grad():
            raws = query(params.lookup_table(), params.layout, params.n_members, c["u"], c["member"], True,
                         by_groups=False)
        raws = tuple(raws) if member is None else (raws,)
        sums = march_compact(params, c, raws, reg)
        return _over_background(params, s, [(*m[:3], None, m[3] if reg else None) for m in sums], members,
                                return_weights)
    # The samples first, in a kernel of their own: the lookups' kernel and the
    # backward march read them instead of each clipping and jittering the rays
    # again (measured: a training step 8 % faster with one member, 14 % with four).
    dr.eval(s["u"], s["valid"], s["t"], s["delta"])
    with dr.suspend_grad():  # _MarchedGrid differentiates the table itself
        raws = lookup_samples(params, s, member)
    raws = tuple(raws) if member is None else (raws,)
    lookup = (params.layout, params.n_members, s["u"], member, s["valid"])
    sums = dr.custom(_MarchedGrid, params.grid, raws, lookup, s["t"], s["delta"], _marched_valid(params, s),
                     int(params.n_samples), float(params.density_bias), 1.0 / params.diag, reg)
    return _over_background(params, s, [(*m[:3], None, m[3] if reg else None) for m in sums], members,
                            return_weights)


def render_flat(params: FieldParams, o, d, member, jitter=None, return_weights=False, reg=None):
    """Render R rays, ray ``r`` with member ``member[r]`` (or one int member).

    Args:
        o: ``mi.Point3f`` (R, or 1: one origin for every ray), d: ``mi.Vector3f`` (R, unit length),
        member: int, or ``mi.UInt32`` (R) member index per ray.
        jitter: per-sample ``mi.Float`` (R*S) in [0,1) or None (midpoints).
    Returns:
        dict: ``rgb`` (Color3f, composited over the member's background),
        ``distance`` (Float, expected distance of the hit,
        ``sum w t / max(sum w, 1e-6)``: given a hit, so faint density gives
        its depth too; 0 where the ray misses the box), ``opacity`` (Float),
        ``weights`` (Float, R*S) if ``return_weights``, and with ``reg``
        (see :func:`.regularisers.ray_regularisers`) ``regulariser`` (Float, R),
        the regularisers' weighted sum per ray.
    """
    s = sample_along_rays(o, d, params, jitter)
    mem = mi.UInt32(member)
    m = dr.gather(mi.UInt32, mem, s["ray"]) if dr.width(mem) > 1 else mem
    return _rendered(params, s, m, [mem], return_weights, reg)[0]


def render_members(params: FieldParams, o, d, jitter=None, return_weights=False, reg=None):
    """Render R rays with *every* member, sharing samples and lookups.

    The corner indices and weights are computed once per sample and one
    packet gather reads all K members' features (member-interleaved table),
    so this costs far less than K calls of :func:`render_flat`.

    Returns:
        list of K dicts as returned by :func:`render_flat`.
    """
    s = sample_along_rays(o, d, params, jitter)
    return _rendered(params, s, None, list(range(params.n_members)), return_weights, reg)
