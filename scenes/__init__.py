"""Scenes that ship with mitsuba-active (see README.md in this folder)."""

from pathlib import Path

#: The default scene of ``mitsuba-active plan`` and ``render``.
BUNDLED_SCENE = Path(__file__).resolve().parent / "spot" / "spot.xml"
