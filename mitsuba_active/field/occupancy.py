"""Empty-space skipping: one coarse occupancy grid shared by all members.

A ``G^3`` grid of cells covers the padded box. A cell is *occupied* while
some member's opacity over one sample step there (``sigma * diag /
n_samples``, the first-order opacity of the longest step a ray can take)
exceeds ``FieldConfig.occupancy_threshold``. Samples in empty cells are
dropped before the grid lookups, which is where training and rendering
spend their time; their density is 0.

During training the grid is refreshed every ``occupancy_interval`` steps
from the members' density at one jittered point per cell, keeping a
decaying maximum (as Instant-NGP does; ``FieldConfig.occupancy_decay``) so
that one unlucky point does not empty a cell. It starts fully occupied, and starts over whenever the
training rays are replaced (views added), for ``occupancy_warmup`` steps:
new views can then grow density where earlier views showed empty space.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .grid import query
from .samples import contracted_stretch, field_at, hash_u32, uniform_from_u32

def cell_index(u, resolution: int):
    """Flat cell index (``mi.UInt32``, x fastest) of box-normalised points ``u``."""
    G = int(resolution)
    c = mi.Vector3u(dr.clip(mi.Vector3f(u) * float(G), 0.0, float(G - 1)))
    return c[0] + c[1] * G + c[2] * (G * G)


def occupied(mask, resolution: int, u):
    """``mi.Bool``: whether the cells of points ``u`` are occupied."""
    return dr.gather(mi.Bool, mask, cell_index(u, resolution))


def cell_opacity(params, resolution: int, key):
    """Largest first-order opacity over members at one jittered point per cell.

    Args:
        params: :class:`~mitsuba_active.field.samples.FieldParams`.
        resolution: G, cells per axis.
        key: ``mi.UInt32`` (opaque) seed of this refresh's jitter.
    Returns:
        ``mi.Float`` of G^3 values, ``max_k sigma_k * diag / n_samples``; in
        a contracted field the step is a box sample's (``diag / (n_samples //
        2)``) times the cell's stretch (:func:`.samples.contracted_stretch`).
    """
    G = int(resolution)
    i = dr.arange(mi.UInt32, G ** 3)
    cell = mi.Vector3f(mi.Float(i % G), mi.Float((i // G) % G), mi.Float(i // (G * G)))
    h = hash_u32(hash_u32(i) ^ key)
    jitter = mi.Vector3f(uniform_from_u32(h), uniform_from_u32(hash_u32(h ^ 0x68E31DA4)),
                         uniform_from_u32(hash_u32(h ^ 0xB5297A4D)))
    u = mi.Point3f((cell + jitter) * (1.0 / G))
    step = params.diag / float(params.n_samples)
    if params.contraction:
        step = params.diag / float(params.n_samples // 2) * contracted_stretch(u)
    best = mi.Float(0.0)
    with dr.suspend_grad():
        for raw in query(params.lookup_table(), params.layout, params.n_members, u, None, True):
            sigma, _ = field_at(params, u, None, True, raw=raw)
            best = dr.maximum(best, sigma * step)
    return best
