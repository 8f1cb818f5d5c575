"""Ctrl-C held back while libraries load.

An interrupt that lands inside the import of a compiled extension (Dr.Jit,
Mitsuba) can leave it half-initialised, so that the program fails with an
unrelated error or aborts; some libraries' imports catch ``BaseException``
and swallow it. :func:`interrupts_deferred` lets the import finish and
raises the ``KeyboardInterrupt`` after it; :func:`interruptible_imports`
does so for a module's imports, and a ``KeyboardInterrupt`` that then ends
the program does so with one line, not a traceback. :func:`waiting_for`
keeps the main thread out of work that Mitsuba's own SIGINT handler could
interrupt unsafely.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading


def sigterm_as_interrupt(signum, frame):
    """SIGTERM handler of the command line: ``kill``, ``timeout`` or a job
    scheduler stops a command as Ctrl-C does, through its clean-up rather than
    halfway through writing its output; a second SIGTERM does not interrupt
    that clean-up."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise KeyboardInterrupt


@contextlib.contextmanager
def interrupts_deferred():
    """Run the block with SIGINT held back; raise ``KeyboardInterrupt`` after it if one came.

    Only in the main thread, and only while Python's own SIGINT handler is set
    (a caller's handler is left alone); SIGTERM likewise while its handler is
    :func:`sigterm_as_interrupt`.
    """
    held = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: sigterm_as_interrupt}
    held = {signum: handler for signum, handler in held.items() if signal.getsignal(signum) is handler}
    if threading.current_thread() is not threading.main_thread() or not held:
        yield
        return
    caught = []
    for signum in held:
        signal.signal(signum, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        for signum, handler in held.items():
            # A SIGTERM that came is answered as its handler would: any later one is ignored.
            signal.signal(signum, signal.SIG_IGN if signum == signal.SIGTERM and signum in caught else handler)
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


def waiting_for(fn, *args, **kwargs):
    """``fn(*args, **kwargs)``, run in a helper thread while the calling main thread waits for it.

    Mitsuba's render installs a SIGINT handler of its own, which logs (and so
    allocates memory) inside the signal handler. A Ctrl-C reaches the main
    thread; had it been inside an allocation of its own (compiling a kernel),
    the process would deadlock. Waiting here, it holds no allocator lock. The
    handler cancels the render and hands the signal on: the
    ``KeyboardInterrupt`` is raised here once the helper has finished.
    """
    if threading.current_thread() is not threading.main_thread():
        return fn(*args, **kwargs)
    outcome, ended = {}, threading.Event()

    def run():
        try:
            outcome["value"] = fn(*args, **kwargs)
        except BaseException as exc:  # handed to the caller below
            outcome["error"] = exc
        finally:
            ended.set()

    # An Event, not Thread.join(): a join interrupted by Ctrl-C marks the thread as ended though it runs on.
    threading.Thread(target=run, name="mitsuba-active-render", daemon=True).start()
    try:
        ended.wait()
    except KeyboardInterrupt:
        with interrupts_deferred():  # the render ends (cancelled) before the interrupt goes on
            ended.wait()
        raise
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]
