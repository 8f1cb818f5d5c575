"""Ctrl-C held back while libraries load.

An interrupt that lands inside the import of a compiled extension (Dr.Jit,
Mitsuba) can leave it half-initialised, so that the program fails with an
unrelated error or aborts; some libraries' imports catch ``BaseException``
and swallow it. :func:`interrupts_deferred` lets the import finish and
raises the ``KeyboardInterrupt`` after it; :func:`interruptible_imports`
does so for a module's imports, and a ``KeyboardInterrupt`` that then ends
the program does so with one line, not a traceback.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading


@contextlib.contextmanager
def interrupts_deferred():
    """Run the block with SIGINT held back; raise ``KeyboardInterrupt`` after it if one came.

    Only in the main thread, and only while Python's own SIGINT handler is set
    (a caller's handler is left alone).
    """
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield
        return
    caught = []
    signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if caught:
        raise KeyboardInterrupt


def _one_line_interrupt(exc_type, exc, tb, _previous=sys.excepthook):
    """Print an uncaught KeyboardInterrupt as one line (any other exception goes to the previous hook)."""
    if issubclass(exc_type, KeyboardInterrupt):
        print("mitsuba-active: interrupted", file=sys.stderr)
    else:
        _previous(exc_type, exc, tb)


@contextlib.contextmanager
def interruptible_imports():
    """:func:`interrupts_deferred` for a module's imports: the ``KeyboardInterrupt``
    raised after them, if it ends the program, is printed as one line."""
    try:
        with interrupts_deferred():
            yield
    except KeyboardInterrupt:
        sys.excepthook = _one_line_interrupt
        raise
