"""Bootstrap weights of an ensemble's members: each fits its own resample of the training rays.

Members that differ only by their random start agree wherever the views
pin the field down, and also where some views merely could. With a
bootstrap, every member but the first (which fits every ray) weighs each
ray, or each view (the rays that share an origin, as a camera's do), by a
Poisson(1) count hashed from the seed, the member and the ray's index or
origin: about a third of the rays or views are left out of each such
member, so members disagree where few views constrain the field. A ray
keeps its weight as views are added after it.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .samples import hash_u32, uniform_from_u32

#: How an ensemble's members may resample the training rays (``bootstrap``):
#: not at all, per ray, or per view (the rays that share an origin).
BOOTSTRAP_KINDS = ("none", "rays", "views")
#: Cumulative Poisson(1) probabilities of 0 to 5: a ray's weight in a
#: member's resample counts how many of them its uniform draw exceeds (at
#: most 6; 1 in 12000 would draw more).
POISSON_CDF = (0.36787944, 0.73575888, 0.91969860, 0.98101184, 0.99634015, 0.99940582)


def bootstrap_weights(bootstrap: str, seed: int, n_members: int, idx, o):
    """Per-member loss weights (a list of K ``mi.Float``, one value per ray) of
    rays ``idx`` (``mi.UInt32``, their indices among the training rays) from
    origins ``o`` (``mi.Point3f``), or None where ``bootstrap`` is ``"none"``."""
    if bootstrap == "none":
        return None
    if bootstrap == "rays":
        ident = idx
    else:  # a view's rays share their origin: its bits name the view
        ident = hash_u32(dr.reinterpret_array(mi.UInt32, o.x))
        ident = hash_u32(ident ^ dr.reinterpret_array(mi.UInt32, o.y))
        ident = hash_u32(ident ^ dr.reinterpret_array(mi.UInt32, o.z))
    weights = [dr.full(mi.Float, 1.0, dr.width(idx))]  # the first member fits every ray
    for k in range(1, n_members):
        key = dr.opaque(mi.UInt32, (seed * 0x27D4EB2F + k * 0x165667B1) & 0xFFFFFFFF)
        u = uniform_from_u32(hash_u32(hash_u32(ident) ^ key))
        weights.append(sum(dr.select(u >= p, 1.0, 0.0) for p in POISSON_CDF))
    return weights


def weighted(out: dict, term):
    """A member's per-ray loss ``term`` times its bootstrap weights, if it has them."""
    return term * out["weight"] if "weight" in out else term
