"""Rendering Dr.Jit rays with one member of a field, as a Mitsuba integrator does.

What the ``radiance_field`` integrator plugin calls from inside
``mi.render``: no numpy, the rays as they come (``ray.o``, ``ray.d``).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from ..errors import UserError
from .render import render_flat
from .variational import VariationalField


def render_rays_dr(field, o, d, member=0):
    """Render Dr.Jit rays with one ensemble member (deterministic midpoints).

    Args:
        field: an :class:`~mitsuba_active.field.Ensemble` or a
            :class:`FieldParams`.
        o: ``mi.Point3f`` ray origins (or one for every ray), d: ``mi.Vector3f`` unit directions
            (e.g. ``ray.o``, ``ray.d`` of an ``mi.Ray3f`` inside an
            integrator), member: int or ``mi.UInt32`` per ray, in [0, K)
            (UserError otherwise; per-ray values are checked except while a
            kernel is being traced).
    Returns:
        (rgb ``mi.Color3f``, distance ``mi.Float``, opacity ``mi.Float``).
    """
    params = field.params() if hasattr(field, "params") and callable(field.params) else field
    # An index past the table reads another member's values or none. Inside a kernel being traced
    # (an integrator's sample()) per-ray values cannot be read: keeping them in range is the caller's part.
    top = None
    if isinstance(member, (int, np.integer)):
        top = int(member)
    elif not dr.flag(dr.JitFlag.SymbolicScope):
        member = mi.UInt32(member)
        top = int(dr.max(member)[0]) if dr.width(member) else None
    if top is not None and not 0 <= top < params.n_members:
        raise UserError(f"member index {top} out of range: the field has {params.n_members} member(s)")
    if isinstance(field, VariationalField) and top not in (None, 0):  # its slot 1 holds the scales
        raise UserError("a VariationalField renders here as member 0 only: its features' mean "
                        "(its draws: predict, or the radiance_field plugin)")
    out = render_flat(params, mi.Point3f(o), mi.Vector3f(d), mi.UInt32(member))
    return out["rgb"], out["distance"], out["opacity"]
