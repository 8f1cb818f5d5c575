"""mitsuba-active: active view planning of radiance fields on Mitsuba 3 and Dr.Jit.

Importing the package selects a Mitsuba variant (``llvm_ad_rgb`` unless the
caller already chose an RGB autodiff variant or set
``$MITSUBA_ACTIVE_VARIANT``) after checking that Dr.Jit can find LLVM >= 19.
"""

from .errors import UserError
from .variant import set_variant

__version__ = "0.1.0"

try:
    set_variant()
except UserError as exc:
    # One line with the fix, not a traceback from deep inside Dr.Jit; exit
    # code 2, as for every other bad input.
    import sys

    print(f"mitsuba-active: error: {exc}", file=sys.stderr)
    raise SystemExit(2) from None

try:  # Mitsuba plugins (the "radiance_field" integrator): cheap, and never fatal
    from .plugins import register as _register_plugins

    _register_plugins()
except Exception as exc:  # pragma: no cover
    import warnings

    warnings.warn(f"mitsuba-active: Mitsuba plugins not registered ({exc})")

__all__ = ["UserError", "set_variant", "__version__"]
