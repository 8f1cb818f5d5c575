"""Checks of user settings (TOML, JSON and library values alike): their types, and names of choices.

``bool`` is an ``int`` in Python, but ``true`` is never a count or a number
here; a Python ``int`` may be too large for a float.
"""

from __future__ import annotations

import difflib
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


def choice_named(name, choices):
    """``name`` as ``choices`` spell it when it is one of them in any case
    (``RFE`` is ``rfe``); any other value as it is."""
    if not isinstance(name, str) or name in choices:
        return name
    same = [c for c in choices if c.casefold() == name.casefold()]
    return same[0] if len(same) == 1 else name


def nearest(name, choices) -> str | None:
    """The one of ``choices`` nearest to a mistyped ``name`` (in any case), or None when none is near."""
    if not isinstance(name, str):
        return None
    folded = {c.casefold(): c for c in choices}
    near = difflib.get_close_matches(name.casefold(), list(folded), n=1)
    return folded[near[0]] if near else None


def unknown_choice(what: str, name, choices) -> str:
    """The message refusing ``name`` as a ``what`` ("planner"): it names the
    nearest of ``choices`` to a mistyped name, and lists them all."""
    near = nearest(name, choices)
    hint = f" (did you mean '{near}'?)" if near else ""
    return f"unknown {what} {name!r}{hint}; choose one of {', '.join(choices)}"
