"""mitsuba-active: active view planning of radiance fields on Mitsuba 3 and Dr.Jit.

Importing the package selects a Mitsuba variant (``llvm_ad_rgb`` unless the
caller already chose an RGB autodiff variant or set
``$MITSUBA_ACTIVE_VARIANT``) after checking that Dr.Jit can find LLVM >= 19.
Where it cannot run (no usable LLVM, no GPU for ``cuda_ad_rgb``) the import
raises :class:`~mitsuba_active.errors.SetupError`, an ``ImportError`` whose
message names the fix; uncaught, it ends the program with that one line.
Ctrl-C during the import is held back until Mitsuba and Dr.Jit have loaded
(an interrupted extension import fails in unrelated ways), then raised;
uncaught, it ends the program with "mitsuba-active: interrupted".
The import also registers the gymnasium environment :data:`ENV_ID`
(made by :func:`mitsuba_active.env.make_env`).
"""

import sys
import warnings

import gymnasium

from .errors import SetupError, UserError
from .interrupts import interruptible_imports
from .variant import set_variant

__version__ = "0.2.0"

#: The environment's gymnasium id: ``gymnasium.make(ENV_ID, scene=..., ...)``.
ENV_ID = "mitsuba_active/ActiveView-v0"


def _one_line_setup_error(exc_type, exc, tb, _previous=sys.excepthook):
    """Print an uncaught SetupError as one line with its fix, not a traceback
    (any other exception goes to the previous hook)."""
    if issubclass(exc_type, SetupError):
        print(f"mitsuba-active: error: {exc}", file=sys.stderr)
    else:
        _previous(exc_type, exc, tb)


try:
    with interruptible_imports():
        set_variant()
        try:  # Mitsuba plugins (the "radiance_field" integrator): cheap, and never fatal
            # Imported here, not above: the plugins load Mitsuba's variant, which set_variant() chose.
            from .plugins import register as _register_plugins

            _register_plugins()
        except Exception as exc:  # pragma: no cover
            warnings.warn(f"mitsuba-active: Mitsuba plugins not registered ({exc})")
except UserError as exc:
    sys.excepthook = _one_line_setup_error
    raise SetupError(str(exc)) from None

if ENV_ID not in gymnasium.registry:  # a reloaded package keeps its registration
    gymnasium.register(ENV_ID, entry_point="mitsuba_active.env:make_env")

__all__ = ["ENV_ID", "SetupError", "UserError", "set_variant", "__version__"]
