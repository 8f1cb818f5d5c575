"""The exceptions that the command line and the package turn into one-line messages."""

import os
from pathlib import Path


class UserError(Exception):
    """Bad input from the user (a file, an option, a budget).

    The CLI prints ``error: <message>`` on one line and exits with code 2;
    library callers can catch it like any other exception.
    """


class SetupError(UserError, ImportError):
    """This machine cannot run mitsuba-active as set up (no usable LLVM, no GPU
    for ``cuda_ad_rgb``): raised by ``import mitsuba_active``.

    An ``ImportError``, so that a pipeline with optional dependencies can catch
    it; left uncaught, it ends the program with its one line, not a traceback,
    and exit code 1 (it stops the import, before the command line can run).
    """


class TrainingDiverged(UserError):
    """A field's training loss became NaN or infinite: its parameters are no
    longer finite, and training the same way again diverges again."""


class FolderError(UserError):
    """An output folder that cannot take what is to be written there (it holds
    another run, say): the ``folder`` and the ``reason`` apart, so that the
    command line names the folder by its option (``--out runs/x: ...``)."""

    def __init__(self, folder, reason: str):
        self.folder, self.reason = os.fspath(folder), reason
        super().__init__(f"{self.folder}: {reason}")

    def __reduce__(self):  # bench's worker processes send it back pickled
        return type(self), (self.folder, self.reason)


class RepeatedView(UserError, ValueError):
    """A step to a candidate that the episode has captured already, in an
    environment that does not allow repeats (its ``action_mask`` says which)."""


class FolderInUse(FolderError):
    """A run folder that another run is writing (in this process or another):
    raised before anything in it is touched, so nothing of the other run's is undone."""


def first_line(exc: BaseException) -> str:
    """The first line of an exception's message (its type's name when it has none):
    what a library reports about a file it cannot read may run over many lines."""
    return (str(exc).splitlines() or [type(exc).__name__])[0]


def brief(exc) -> str:
    """An exception's message on one line, cut to 300 characters: what a library
    says of a file it cannot load, quoted in a message of ours."""
    text = " ".join(str(exc).split())
    return text if len(text) <= 300 else text[:297] + "..."


def os_error_line(exc: OSError) -> str:
    """One line for a failed file operation; names the file that stands where a folder must be."""
    if isinstance(exc, (FileExistsError, NotADirectoryError)) and exc.filename:
        path = Path(exc.filename)
        blocker = next((p for p in [path, *path.parents] if p.is_file()), None)
        if blocker is not None:
            return f"{blocker} is a file, where a folder is needed"
    # A failed rename (every output is written to a hidden temporary name, then
    # renamed) names the output it was to become, not the temporary file.
    name = exc.filename2 or exc.filename
    where = f"{name}: " if name else ""
    return f"{where}{exc.strerror or exc}"
