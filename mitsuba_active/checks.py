"""Type checks of user settings (TOML, JSON and library values alike).

``bool`` is an ``int`` in Python, but ``true`` is never a count or a number
here; a Python ``int`` may be too large for a float.
"""

from __future__ import annotations

import math
import numbers
import os
import tomllib


def is_whole(value) -> bool:
    """A whole number (numpy integers too), not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def is_number(value, finite: bool = False) -> bool:
    """A real number (numpy scalars too), not a bool; with ``finite``, also
    finite as a float."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return False
    if not finite:
        return True
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def setting_value(text: str):
    """A setting given as text on the command line, read as a TOML value
    (``4``, ``0.02``, ``[5, 10]``, ``true``) or a number Python reads
    (``.5``); any other text is a string (``interior``, ``log``)."""
    text = text.strip()
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except (tomllib.TOMLDecodeError, RecursionError):  # nested past Python's stack: text, refused where used
        pass
    try:
        return float(text)
    except ValueError:
        return text


def not_a_file(path, what: str) -> str:
    """Why ``path``, which must be a plain file (``what``: "mesh file"), is
    not one: missing, a folder, or something else (a pipe, a device)."""
    if not os.path.exists(path):  # a link to nothing too
        return f"{what} not found: {path}"
    if os.path.isdir(path):
        return f"{what} {path} is a folder, not a file"
    return f"{what} {path} is not a regular file (a pipe, a socket or a device)"
