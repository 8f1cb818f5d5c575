"""Radiance-field ensembles on Dr.Jit: multi-resolution grids, volume
rendering of flat ray batches, fused K-member training, Fisher diagonals,
and a stochastic field with variational uncertainty.

Public API::

    from mitsuba_active.field import FieldConfig, Ensemble, VariationalField

Lower level (Dr.Jit arrays, no numpy): :mod:`mitsuba_active.field.render`
(``render_rays_dr``, ``render_flat``, ``composite``, ``composite_marched``,
``sample_along_rays``).
See docs/field.md.
"""

import mitsuba_active  # noqa: F401  (selects the Mitsuba variant and LLVM first)

from .config import FieldConfig
from .ensemble import Ensemble
from .render import FieldParams, render_rays_dr
from .variational import VariationalField

__all__ = ["FieldConfig", "Ensemble", "VariationalField", "FieldParams", "render_rays_dr"]
