"""What the commands share: one-line errors, case-blind choices, and the options given.

Every command turns bad input (:class:`~mitsuba_active.errors.UserError`)
and files it cannot read or write (``OSError``) into one line on stderr and
exit code 2 (:func:`one_line_errors`).
"""

from __future__ import annotations

import functools
import gc
import os
import signal
import sys
import threading
import traceback
import warnings
from pathlib import Path

import click
from click.core import ParameterSource

from ..checks import nearest
from ..console import mitsuba_log_as_warnings, one_line, show_warning
from ..errors import FolderError, UserError, os_error_line
from ..interrupts import interrupts_deferred, sigterm_as_interrupt

#: Where a command keeps the output folder it writes (``ctx.meta``), once its default is filled in.
OUT = "mitsuba_active.out"


def _output_option() -> tuple[str, Path] | None:
    """The current command's option that names its output (``--out``, ``-o/--output``) and the path it names."""
    ctx = click.get_current_context(silent=True)
    option = next((p for p in ctx.command.params if p.name == "out"), None) if ctx else None
    path = ctx.meta.get(OUT, ctx.params.get("out")) if option else None
    return ("/".join(option.opts), Path(path)) if path is not None else None


def _naming_output(paths, around: bool) -> str | None:
    """``--out runs/x`` when one of ``paths`` is the current command's output
    (with ``around``, also a path inside it or above it); else None."""
    output = _output_option()
    if output is None:
        return None
    option, out = output
    target = Path(os.path.abspath(out))
    for p in paths:
        if isinstance(p, (str, os.PathLike)):
            p = Path(os.path.abspath(p))
            if p == target or (around and (target in p.parents or p in target.parents)):
                return f"{option} {out}"
    return None


def _error_line(exc: Exception) -> str:
    """The line that reports a UserError or an OSError, naming the output's option when it is about the output."""
    if isinstance(exc, FolderError):
        named = _naming_output([exc.folder], around=False)
        return f"{named}: {exc.reason}" if named else str(exc)
    if isinstance(exc, OSError):
        line = os_error_line(exc)
        named = _naming_output([exc.filename, exc.filename2], around=True)
        return f"{named}: {line}" if named else line
    return str(exc)


def _load_libraries() -> None:
    """Load the libraries that the package loads when first used, trimesh and
    matplotlib's pyplot (with its file-only backend), with Ctrl-C held back (see
    :mod:`.interrupts`) and SIGTERM handled: an interrupt then stops the
    command cleanly, not an import halfway (trimesh's imports swallow it, and
    a swallowed interrupt ends the process by SIGINT after a successful command)."""
    # Here, not above: under the command's SIGTERM handler, and only for the commands that use them.
    import trimesh  # noqa: F401

    from ..report import _plt

    _plt()


def _close_progress_bars() -> None:
    """Close the progress bars an interruption left open, so that the next message starts a line of its own."""
    tqdm = sys.modules.get("tqdm")
    for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", ())):
        bar.close()


def _chain(exc):
    """``exc``, then what caused it, and so on (each once)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


def _caused_by_interrupt(exc) -> bool:
    """Whether ``exc`` is, or wraps, a KeyboardInterrupt: Dr.Jit's loops and
    custom operations re-raise what their Python bodies raised (Ctrl-C, or
    SIGTERM through :func:`~.interrupts.sigterm_as_interrupt`) as a RuntimeError caused by it."""
    return any(isinstance(e, KeyboardInterrupt) for e in _chain(exc))


def exit_interrupted():
    """End the command after Ctrl-C (or SIGTERM): one line on stderr, exit code 130."""
    _close_progress_bars()
    click.echo("mitsuba-active: interrupted", err=True)
    # An interrupt that landed inside exec() of a source string (dataclasses
    # make their methods so, during a late import) leaves CPython's flag for
    # an unhandled KeyboardInterrupt set, and under `python -m` the process
    # would then end by SIGINT instead of this exit code. Each exec() of a
    # string starts by clearing that flag.
    exec("None")
    sys.exit(130)


def _drop_unraisable(info) -> None:
    """Report nothing (see :func:`_free_interrupted_frames`)."""


def _free_interrupted_frames(exc) -> None:
    """Free, now, what the frames that ``exc`` (and what caused it) unwound still
    hold, with failing finalisers unreported: among those objects are any the
    interrupt cut short in their making (a PNG writer stopped inside its
    constructor fails in its finaliser), whose errors are no news to the user."""
    previous, sys.unraisablehook = sys.unraisablehook, _drop_unraisable
    try:
        for e in _chain(exc):
            traceback.clear_frames(e.__traceback__)  # frames still running are left as they are
        gc.collect()
    finally:
        sys.unraisablehook = previous


def one_line_errors(fn=None, *, libraries: bool = True):
    """A command that ends bad input, unwritable files and interrupts with one line and an exit code.

    ``libraries``: load trimesh and pyplot first (:func:`_load_libraries`); the viewer uses neither.
    """
    if fn is None:
        return functools.partial(one_line_errors, libraries=libraries)

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if sys.stderr is None:  # started with stderr closed (2>&-): progress bars and messages go nowhere
            sys.stderr = open(os.devnull, "w")
        # Signal handlers belong to the main thread (a command may be invoked from another).
        handled = threading.current_thread() is threading.main_thread()
        previous = signal.signal(signal.SIGTERM, sigterm_as_interrupt) if handled else None
        try:
            with warnings.catch_warnings(), mitsuba_log_as_warnings():
                warnings.showwarning = show_warning
                if libraries:
                    with interrupts_deferred():
                        _load_libraries()
                return fn(*args, **kwargs)
        # OSError: an output folder that cannot be created or written, a full disk...
        except (UserError, OSError) as exc:
            click.echo(f"mitsuba-active: error: {one_line(_error_line(exc))}", err=True)
            sys.exit(2)
        except (KeyboardInterrupt, RuntimeError) as exc:
            if not _caused_by_interrupt(exc):
                raise
            _free_interrupted_frames(exc)
            exit_interrupted()
        finally:
            if handled:  # None: a handler not set from Python, which cannot be put back
                signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)
    return wrapper


class Choice(click.Choice):
    """A choice given in any case (``--rig Sphere``); a mistyped one is answered with the nearest choice."""

    def __init__(self, choices):
        super().__init__(choices, case_sensitive=False)

    def get_invalid_choice_message(self, value, ctx) -> str:
        near = nearest(value, self.choices)
        return super().get_invalid_choice_message(value, ctx) + (f" (Did you mean '{near}'?)" if near else "")


class Command(click.Command):
    """A command whose summary in ``mitsuba-active --help`` is its docstring's first sentence whole."""

    def get_short_help_str(self, limit: int = 45) -> str:
        return super().get_short_help_str(limit=1000)  # click cuts it to fit the terminal, with "..."


def given_options() -> set[str]:
    """Names of the current command's options given on the command line (not defaults)."""
    ctx = click.get_current_context()
    return {name for name in ctx.params if ctx.get_parameter_source(name) is ParameterSource.COMMANDLINE}

