"""How commands show warnings: plain lines on stderr, Mitsuba's too.

``mitsuba-active: warning: ...``, once per message, above any progress bar,
never among a command's output on stdout. The command line and ``bench``'s
worker processes use these; a program that imports the package keeps its own
warning display and Mitsuba's logging.
"""

from __future__ import annotations

import contextlib
import sys
import warnings

import mitsuba as mi


def one_line(message: str) -> str:
    """``message`` on one line: line breaks (in a file's name, or quoted from a
    library's message) shown as ``\\n``, so that an error or a warning is always one line."""
    return message.replace("\r", "\\r").replace("\n", "\\n")


def show_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings (skipped dataset frames, a scene without lights) as one plain line,
    above any progress bar rather than into it."""
    text = f"mitsuba-active: warning: {one_line(str(message))}"
    tqdm = sys.modules.get("tqdm")
    if tqdm is not None:
        tqdm.tqdm.write(text, file=sys.stderr)
    else:
        print(text, file=sys.stderr)


@contextlib.contextmanager
def mitsuba_log_as_warnings():
    """Mitsuba's log messages (its warnings: a scene it accepts with a
    complaint) as Python warnings, so one plain line each on stderr, once per
    message, instead of coloured lines among the command's output on stdout.
    Mitsuba's own appenders and format are put back afterwards."""
    class Appender(mi.Appender):
        def append(self, level, text):
            # Called from Mitsuba's C++ (also its worker threads): an exception raised here
            # (warnings turned into errors) would turn into a failed scene load.
            try:
                warnings.warn(text.strip(), stacklevel=1)
            except Exception:
                print(f"mitsuba-active: warning: {text.strip()}", file=sys.stderr)

        def log_progress(self, progress, name, formatted, eta, ptr=None):
            pass

    logger = mi.logger()
    formatter = logger.formatter()
    shown = (formatter.has_date(), formatter.has_thread(), formatter.has_log_level())
    previous = [logger.appender(i) for i in range(logger.appender_count())]
    ours = Appender()
    logger.clear_appenders()
    logger.add_appender(ours)
    formatter.set_has_date(False)
    formatter.set_has_thread(False)
    formatter.set_has_log_level(False)
    try:
        yield
    finally:
        logger.remove_appender(ours)
        for appender in previous:
            logger.add_appender(appender)
        formatter.set_has_date(shown[0])
        formatter.set_has_thread(shown[1])
        formatter.set_has_log_level(shown[2])
