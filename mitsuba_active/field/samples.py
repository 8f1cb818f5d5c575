"""Samples along rays: the field's parameters, its box, the contraction, and the field at a point.

Rays are flat Dr.Jit arrays of length R; every ray owns a contiguous block of
S = ``n_samples`` samples, so the sample arrays have length R*S.

Units: positions and distances are in scene units; directions are unit
vectors, so the sample parameter ``t`` is the metric distance from the ray
origin (the camera's optical centre).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .grid import GridLayout, query
from .march import _raw_to_field


@dataclass
class FieldParams:
    """Everything the renderer needs: Dr.Jit parameters plus static layout.

    Attributes:
        grid: ``mi.Float`` table, ``layout.n_entries * K * 4`` values
            (member-interleaved, see :mod:`.grid`).
        background: ``mi.Float`` ``K * 3`` background colour logits.
        layout: :class:`GridLayout` of one member.
        box_min, box_max: padded bounding box (3 Python floats each).
        n_samples: samples per ray.
        density_bias: added to the density logit.
        n_members: K.
        occupancy: ``mi.Bool`` of ``occupancy_resolution**3`` cells, or None
            (no empty-space skipping; see :mod:`.occupancy`).
        occupancy_resolution: cells per axis of ``occupancy``.
        stop_transmittance: where a march over the occupied samples stops
            (``FieldConfig.stop_transmittance``).
        view: ``mi.Float`` table of the view-dependent colour's coefficients
            (see :mod:`.view`), or None (a diffuse field).
        view_degree, view_resolution: its spherical-harmonic degree and
            cells per axis.
        contraction: 0, or how far the contracted scene reaches in half
            box sizes (``FieldConfig.contraction``).
        near: distance from a ray's origin where its samples may start
            (scene units; ``FieldConfig.near`` times the diagonal).
        sky: ``mi.Float`` table of the directional background (see
            :mod:`.sky`), or None (one colour per member).
        sky_resolution: its rows (``FieldConfig.background_resolution``).
        half_grid, half_of: a float16 copy (:func:`.grid.half_table`) of the
            table ``half_of``, or None; the lookups read it while ``grid``
            is that table (one that replaces ``grid`` is read as it is)
            and no derivatives of it are traced (see :meth:`lookup_table`).
    """

    grid: object
    background: object
    layout: GridLayout
    box_min: tuple
    box_max: tuple
    n_samples: int
    density_bias: float
    n_members: int = 1
    occupancy: object = None
    occupancy_resolution: int = 0
    stop_transmittance: float = 0.0
    view: object = None
    view_degree: int = 0
    view_resolution: int = 0
    contraction: float = 0.0
    near: float = 0.0
    sky: object = None
    sky_resolution: int = 0
    half_grid: object = None
    half_of: object = None

    def lookup_table(self):
        """The table the grid lookups read: ``half_grid`` where it copies
        ``grid`` and no derivatives of ``grid`` are traced, else ``grid``."""
        if self.half_grid is None or self.half_of is not self.grid or dr.grad_enabled(self.grid):
            return self.grid
        return self.half_grid

    @property
    def diag(self) -> float:
        return float(np.linalg.norm(np.subtract(self.box_max, self.box_min)))


def hash_u32(x):
    """Integer hash (lowbias32) of ``mi.UInt32`` values: stateless, per-lane
    random numbers whose seed can be an opaque variable (no recompiles)."""
    x = x ^ (x >> 16)
    x = x * 0x7FEB352D
    x = x ^ (x >> 15)
    x = x * 0x846CA68B
    return x ^ (x >> 16)


def uniform_from_u32(h):
    """Float in [0, 1) from the top 24 bits of a hash."""
    return mi.Float(h >> 8) * (1.0 / 16777216.0)


def ray_box(o, d, box_min, box_max, near: float = 0.0):
    """Entry/exit distances of rays with an axis-aligned box.

    Args:
        o: ``mi.Point3f`` origins; d: ``mi.Vector3f`` unit directions;
        near: the least distance returned as entry (scene units).
    Returns:
        (t_near, t_far) ``mi.Float``; ``t_near`` is clamped to ``near`` (a
        camera inside the box starts sampling there) and ``t_far <= t_near``
        means the ray misses.
    """
    # Avoid 0 * inf = NaN for axis-parallel rays.
    eps = 1e-9
    d = mi.Vector3f(d)
    d_safe = dr.select(dr.abs(d) < eps, dr.copysign(eps, d), d)
    inv = dr.rcp(d_safe)
    t0 = (mi.Vector3f(box_min) - o) * inv
    t1 = (mi.Vector3f(box_max) - o) * inv
    tmin = dr.minimum(t0, t1)
    tmax = dr.maximum(t0, t1)
    t_near = dr.maximum(dr.max(tmin), near)
    t_far = dr.min(tmax)
    return t_near, t_far


def box_normalised(params: FieldParams, p):
    """Points ``p`` (``mi.Point3f``, scene units) in the unit cube of the field's padded box."""
    return mi.Point3f((p - mi.Vector3f(params.box_min)) * mi.Vector3f(1.0 / np.subtract(params.box_max,
                                                                                         params.box_min)))


def field_position(params: FieldParams, p):
    """Grid coordinates in the unit cube (``mi.Point3f``) of points ``p`` (scene
    units): box-normalised, or for a contracted field the contracted cube
    ``[-2, 2]^3`` mapped onto it (the box is its middle half)."""
    u = box_normalised(params, p)
    if not params.contraction:
        return u
    x = mi.Vector3f(u) * 2.0 - 1.0
    r = dr.max(dr.abs(x))
    x = dr.select(r > 1.0, x * ((2.0 - dr.rcp(r)) * dr.rcp(r)), x)
    return mi.Point3f(dr.fma(x, 0.25, 0.5))


def contracted_stretch(u):
    """Scene length per unit of contracted length at grid coordinates ``u``
    (``mi.Float``, relative to the box: 1 inside it, ``R**2`` on the shell of
    points ``R`` half box sizes out)."""
    r = dr.max(dr.abs(mi.Vector3f(u) * 4.0 - 2.0))
    return dr.select(r > 1.0, dr.rcp(dr.square(dr.maximum(2.0 - r, 1e-6))), 1.0)


def _box_exit(q, e, radius):
    """Distance at which rays ``q + t e`` (box-normalised, centred: the box is
    ``[-1, 1]^3``) leave the cube ``[-radius, radius]^3``."""
    eps = 1e-9
    e_safe = dr.select(dr.abs(e) < eps, dr.copysign(eps, e), e)
    return dr.min((dr.copysign(mi.Vector3f(radius), e_safe) - q) * dr.rcp(e_safe))


def _contracted_samples(o, d, params: FieldParams, jitter):
    """:func:`sample_along_rays` of a contracted field: the first half of a
    ray's samples uniform over its stretch in the box, the rest evenly spaced
    in contracted space from the box (a ray that misses it: from its point
    nearest the centre, with all its samples) out to ``params.contraction``
    half box sizes, each sample inside its bin ``[t0, t1]``."""
    S = int(params.n_samples)
    S_in = S // 2
    R = max(dr.width(o), dr.width(d))
    t_near, t_far = ray_box(o, d, params.box_min, params.box_max, params.near)
    i = dr.arange(mi.UInt32, R * S)
    ray = i // S
    k = i - ray * S
    tn = dr.gather(mi.Float, t_near, ray)
    tf = dr.gather(mi.Float, t_far, ray)
    oo = dr.gather(mi.Point3f, o, ray) if dr.width(o) > 1 else mi.Point3f(o)
    dd = dr.gather(mi.Vector3f, d, ray) if dr.width(d) > 1 else mi.Vector3f(d)
    hit = tf > tn
    frac = 0.5 if jitter is None else jitter
    # The box: bins of equal length.
    delta_in = dr.maximum(tf - tn, 0.0) * (1.0 / S_in)
    t_in = dr.fma(mi.Float(k) + frac, delta_in, tn)
    # Beyond it: bins of equal contracted length, c = 2 - 1/r for the shell r.
    lo, hi = np.asarray(params.box_min, np.float64), np.asarray(params.box_max, np.float64)
    centre, inv_half = mi.Point3f(0.5 * (lo + hi)), mi.Vector3f(2.0 / (hi - lo))
    q, e = (oo - centre) * inv_half, dd * inv_half
    t_star = dr.maximum(dr.dot(centre - oo, dd), 0.0)
    r_start = dr.select(hit, 1.0, dr.maximum(dr.max(dr.abs(dr.fma(e, t_star, q))), 1.0))
    c_start, c_end = 2.0 - dr.rcp(r_start), 2.0 - 1.0 / float(params.contraction)
    n_out = dr.select(hit, mi.Float(S - S_in), mi.Float(S))
    k_out = dr.select(hit, mi.Float(k) - S_in, mi.Float(k))
    step = dr.maximum(c_end - c_start, 0.0) / n_out
    c0 = dr.fma(k_out, step, c_start)

    def at(c):  # distance where the ray leaves the shell of contracted radius c
        return dr.maximum(_box_exit(q, e, dr.rcp(2.0 - c)), 0.0)

    t0, t1 = at(c0), at(c0 + step)
    inner = hit & (mi.Float(k) < S_in)
    t = dr.select(inner, t_in, at(dr.fma(frac, step, c0)))
    delta = dr.select(inner, delta_in, t1 - t0)
    p = dr.fma(dd, t, oo)
    u = field_position(params, p)
    valid = dr.select(inner, hit, mi.Bool(True))
    return dict(ray=ray, t=t, delta=delta, p=p, u=u, valid=valid, ray_valid=dr.full(mi.Bool, True, R), o=o, d=d,
                uniform=False)


def _per_ray(values, R: int, ray):
    """Per-ray ``values`` (a tuple of ``mi.Float`` and 3-vectors, each of
    length R, or 1 for all rays) at the rays ``ray`` (``mi.UInt32``).

    Gathering them keeps the samples in one flat kernel. Those of length R
    are written side by side, ray after ray, and read with one packet
    gather a sample instead of a gather a float (each sample of a ray reads
    the same few floats).
    """
    flat = [(v, c) for v in values if dr.width(v) > 1 for c in (range(3) if dr.size_v(v) == 3 else (None,))]
    if not flat:
        return values
    width = 1 << (len(flat) - 1).bit_length()
    XF = type(mi.ArrayXf())
    packed = dr.empty(mi.Float, width * R)
    floats = [v if c is None else v[c] for v, c in flat]
    dr.scatter(packed, XF(*(floats + [mi.Float(0.0)] * (width - len(flat)))), dr.arange(mi.UInt32, R))
    got = dr.gather(XF, packed, ray, shape=(width, dr.width(ray)))
    out, n = [], 0
    for v in values:
        if dr.width(v) == 1:
            out.append(v)
        elif dr.size_v(v) == 3:
            out.append(type(v)(got[n], got[n + 1], got[n + 2]))
            n += 3
        else:
            out.append(got[n])
            n += 1
    return tuple(out)


def sample_along_rays(o, d, params: FieldParams, jitter=None, index=None):
    """Stratified sample positions, one block of S samples per ray.

    Args:
        o, d: per-ray ``mi.Point3f`` / ``mi.Vector3f`` (length R; either
            may have length 1, shared by all rays).
        jitter: per-sample ``mi.Float`` in [0, 1) (length R*S, or that of
            ``index``), or None for bin midpoints (deterministic rendering).
        index: None (every sample), or ``mi.UInt32`` indices among the R*S
            samples of those to make (uniform bins only: not in a contracted field).
    Returns:
        dict of per-sample arrays (length R*S, or that of ``index``):
        ``ray`` (UInt32 ray index), ``t`` (distance from origin), ``delta``
        (bin length), ``p`` (Point3f), ``u`` (Point3f box-normalised),
        ``valid`` (Bool); per ray (length R) ``ray_valid`` (Bool: the ray
        meets the box), ``ray_delta`` (its bin length), ``o`` and ``d`` (the
        rays, as given); ``uniform`` (a Python bool: the bins of a ray are
        of one length) and ``jitter`` (as given). A contracted field
        (``params.contraction``) samples the box and the space beyond it
        (see :func:`_contracted_samples`): ``u`` is then in contracted
        coordinates (:func:`field_position`) and every ray is valid.
    """
    if params.contraction:
        if index is not None:
            raise ValueError("sample_along_rays: index is for uniform bins, not a contracted field's")
        return {**_contracted_samples(o, d, params, jitter), "jitter": jitter}
    S = int(params.n_samples)
    R = max(dr.width(o), dr.width(d))  # one origin (a pinhole camera's) may serve every ray
    t_near, t_far = ray_box(o, d, params.box_min, params.box_max, params.near)
    i = dr.arange(mi.UInt32, R * S) if index is None else mi.UInt32(index)
    ray = i // S
    k = mi.Float(i - ray * S)
    tn, tf, oo, dd = _per_ray((t_near, t_far, mi.Point3f(o), mi.Vector3f(d)), R, ray)
    valid = tf > tn
    length = dr.maximum(tf - tn, 0.0)
    delta = length * (1.0 / S)
    frac = (k + (0.5 if jitter is None else jitter))
    t = dr.fma(frac, delta, tn)
    p = dr.fma(dd, t, oo)
    u = box_normalised(params, p)
    return dict(ray=ray, t=t, delta=delta, p=p, u=u, valid=valid, ray_valid=t_far > t_near,
                ray_delta=dr.maximum(t_far - t_near, 0.0) * (1.0 / S), o=o, d=d, uniform=True, jitter=jitter)


def field_at(params: FieldParams, u, member, active=True, raw=None):
    """Density (1/scene-unit) and colour in [0,1] at normalised positions.

    ``raw`` (the summed grid features, ``mi.Vector4f``) may be passed when
    the caller already evaluated it.
    """
    if raw is None:
        raw = query(params.lookup_table(), params.layout, params.n_members, u, member, active)
    sigma, rgb, _ = _raw_to_field(raw, mi.Bool(active), params.density_bias, 1.0 / params.diag)
    return sigma, rgb
