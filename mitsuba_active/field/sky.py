"""Directional background: a latitude-longitude map of colour per member, behind the volume.

A field's background is one learnt colour per member: right for objects on
white, black or transparent backdrops, and for rooms, whose rays always hit.
A real capture's background is the world beyond the object's box (trees,
walls, a sky), seen from each camera in another direction. With a constant
background the volume has to paint that world in, as fog that hides the
object from new views. The sky map gives every ray a background colour by
its direction alone (as an environment map at infinity), so the volume can
stay empty around the object.

The map has ``resolution`` rows (polar angle from +y, 0 to pi) and ``2 *
resolution`` columns (azimuth, wrapping around), each texel holding three
colour-logit residuals per member, member-interleaved as the grid's table is
(``[texel][member][channel]``). Texels are bilinearly interpolated and the
result is added to the member's constant background logits, so the map
starts at 0: an untrained field's background is the constant one.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from .grid import reduce_mode

def sky_size(resolution: int, n_members: int) -> int:
    """Floats of the map of ``resolution`` rows, all ``n_members`` members."""
    r = int(resolution)
    return r * 2 * r * int(n_members) * 3


def sky_texels(d, resolution: int):
    """The four texels around unit directions ``d`` (``mi.Vector3f``) and their
    bilinear weights: a list of four (``mi.UInt32`` texel index, ``mi.Float`` weight)."""
    rows, cols = int(resolution), 2 * int(resolution)
    # Polar angle from +y and azimuth about it, in texel units (texel centres at half steps).
    theta = dr.acos(dr.clip(d[1], -1.0, 1.0))
    phi = dr.atan2(d[2], d[0])
    v = theta * (rows / math.pi) - 0.5
    u = (phi * (0.5 / math.pi) + 0.5) * cols - 0.5
    v0, u0 = dr.floor(v), dr.floor(u)
    fv, fu = v - v0, u - u0
    r0 = mi.Int32(dr.clip(v0, 0, rows - 1))
    r1 = mi.Int32(dr.clip(v0 + 1, 0, rows - 1))
    c0 = mi.Int32(u0)
    c0 = dr.select(c0 < 0, c0 + cols, c0)
    c0 = dr.select(c0 >= cols, c0 - cols, c0)
    c1 = dr.select(c0 + 1 >= cols, c0 + 1 - cols, c0 + 1)
    out = []
    for r, wr in ((r0, 1.0 - fv), (r1, fv)):
        for c, wc in ((c0, 1.0 - fu), (c1, fu)):
            out.append((mi.UInt32(r * cols + c), wr * wc))
    return out


def sky_logits(table, resolution: int, n_members: int, d, member):
    """Background colour-logit residual (``mi.Color3f``, per ray) along unit
    directions ``d`` (``mi.Vector3f``) of member ``member`` (an int or a
    ``mi.UInt32`` per ray), differentiable with respect to ``table``
    (``mi.Float``, :func:`sky_size` floats)."""
    K = int(n_members)
    mem = mi.UInt32(member)
    out = mi.Vector3f(0.0)
    for idx, w in sky_texels(d, resolution):
        out = dr.fma(dr.gather(mi.Vector3f, table, idx * K + mem, mode=reduce_mode()), w, out)
    return mi.Color3f(out)


def background_colour(params, d, member, n: int):
    """Member ``member``'s background colour (``mi.Color3f``, ``n`` rays) behind
    rays along unit directions ``d`` (``mi.Vector3f``): its constant colour, plus
    the directional map's residual where the field has one (see :mod:`.sky`)."""
    # One background index per ray: the gradient of a background read once and
    # broadcast to every ray would take a reduction kernel per channel and member.
    logits = mi.Color3f(dr.gather(mi.Vector3f, params.background, dr.zeros(mi.UInt32, n) + mi.UInt32(member)))
    if params.sky is not None:
        logits = logits + sky_logits(params.sky, params.sky_resolution, params.n_members, mi.Vector3f(d), member)
    return mi.Color3f(*[dr.rcp(1.0 + dr.exp(-logits[c])) for c in range(3)])
