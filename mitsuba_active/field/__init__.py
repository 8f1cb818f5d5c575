"""Radiance-field ensembles on Dr.Jit: multi-resolution grids, volume
rendering of flat ray batches, fused K-member training, Fisher diagonals,
and a stochastic field with variational uncertainty.

Public API::

    from mitsuba_active.field import FieldConfig, Ensemble, VariationalField

Lower level (Dr.Jit arrays, no numpy): :mod:`~mitsuba_active.field.samples`
(``FieldParams``, ``sample_along_rays``, ``field_at``),
:mod:`~mitsuba_active.field.march` (``composite``, ``composite_marched``),
:mod:`~mitsuba_active.field.render` (``render_flat``, ``render_members``) and
:mod:`~mitsuba_active.field.render_dr` (``render_rays_dr``).
See docs/field.md.
"""

import mitsuba_active  # noqa: F401  (selects the Mitsuba variant and LLVM first)

from .config import FieldConfig
from .ensemble import Ensemble
from .render_dr import render_rays_dr
from .samples import FieldParams
from .variational import VariationalField

__all__ = ["FieldConfig", "Ensemble", "VariationalField", "FieldParams", "render_rays_dr"]
