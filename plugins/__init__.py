"""Mitsuba plugins shipped with mitsuba-active."""
