"""Mitsuba plugins shipped with mitsuba-active.

:func:`register` makes them available to ``mi.load_dict`` / ``mi.load_file``:

* integrator ``radiance_field`` (:mod:`.radiance_field`): renders a saved
  radiance-field ensemble from any sensor, with variance, distance and
  opacity AOVs.

Registration is cheap (no field code is imported until a scene uses the
plugin), is repeated automatically when the Mitsuba variant changes, and
never raises: a failure becomes a warning.
"""

from __future__ import annotations

import warnings

_callback_added = False


def register() -> bool:
    """Register the plugins for the current Mitsuba variant (and future ones). Returns success."""
    global _callback_added
    try:
        import mitsuba as mi

        from . import radiance_field

        if mi.variant() is not None:
            mi.register_integrator(radiance_field.NAME, radiance_field.create)
        if not _callback_added:
            # Mitsuba's registry is per variant: register again after mi.set_variant().
            mi.detail.add_variant_callback(_on_variant_change)
            _callback_added = True
        return True
    except Exception as exc:  # a plugin must never break importing the library
        warnings.warn(f"mitsuba-active: could not register the Mitsuba plugins ({exc})", stacklevel=2)
        return False


def _on_variant_change(old, new):
    try:
        import mitsuba as mi

        from . import radiance_field

        if new is not None:
            # Also where the integrator cannot run: loading it there then says
            # which variants it needs, instead of "plugin not found".
            mi.register_integrator(radiance_field.NAME, radiance_field.create)
    except Exception as exc:
        warnings.warn(f"mitsuba-active: could not register the Mitsuba plugins for {new} ({exc})")


__all__ = ["register"]
