"""Image files: EXR (float, via OpenEXR) and PNG (8-bit, via imageio), written atomically.

Every writer goes through :func:`atomic_write`: the file appears whole under
its final name or not at all, so an interrupted run leaves nothing half-written.
:func:`replaced_folder` replaces a folder whole; :func:`new_entries` and
:func:`remove_new` undo what a failed command added; :func:`folder_lock` keeps
two runs out of one folder.

The EXR readers raise ValueError for a file that OpenEXR cannot read whole,
and keep what the library prints about it off stdout and stderr.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import io
import os
import re
import secrets
import shutil
import sys
import tempfile
from pathlib import Path

import imageio.v3 as iio
import matplotlib
import numpy as np
import OpenEXR

from .errors import FolderInUse, first_line
from .interrupts import interrupts_deferred

#: The C library, whose stdio buffers C and C++ code print through (None where it cannot be loaded so).
_LIBC = ctypes.CDLL(None) if os.name == "posix" else None


@contextlib.contextmanager
def atomic_write(path, suffix=""):
    """Yield a temporary path in the same folder for the caller to write;
    rename it onto ``path`` on success, remove it otherwise.

    The name is chosen before anything is created, so an interruption at any
    point (Ctrl-C, a stopped worker) leaves no temporary file behind.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}{suffix or path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as exc:  # a full disk: name the output, not its temporary name
        if exc.filename is None or exc.filename in (tmp, str(tmp)):  # a failed write names no file
            exc.filename = str(path)
        if exc.filename2 in (tmp, str(tmp)):  # shutil's copies name the source first
            exc.filename2 = str(path)
        raise
    finally:
        if os.path.lexists(tmp):
            os.unlink(tmp)


@contextlib.contextmanager
def replaced_folder(path):
    """Yield a new, empty folder beside ``path`` for the caller to fill; on
    success it takes the place of ``path`` and everything ``path`` held,
    otherwise it is removed. Ctrl-C is held back during the swap, so that
    ``path`` is always whole: the earlier folder or the new one.
    """
    path = Path(path)
    stage = path.with_name(f".{path.name}.{secrets.token_hex(6)}")
    earlier = path.with_name(f"{stage.name}.old")
    try:
        stage.mkdir(parents=True)
        yield stage
        with interrupts_deferred():
            if os.path.lexists(path):
                os.replace(path, earlier)
            os.replace(stage, path)
    finally:
        for p in (stage, earlier):
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)


@contextlib.contextmanager
def folder_lock(path: Path):
    """Hold an exclusive lock on the folder ``path`` (which must exist) while
    the block runs; FolderInUse at once if another holder has it. The lock
    is the kernel's (``flock`` on the folder itself): no lock file is left
    behind, and a killed holder releases it. Where there is no ``flock``
    (Windows), nothing is locked."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover
        yield
        return
    fd = os.open(path, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise FolderInUse(path, "in use by another run (a plan or bench writing it now); wait for that one to "
                                    "end, or choose another folder") from None
        yield
    finally:
        os.close(fd)  # releases the lock


def new_entries(out: Path):
    """What a command may remove if it fails: ``(top, before)``, where ``top`` is
    the first of ``out`` and its parents that does not exist yet (None if ``out``
    exists) and ``before`` what ``out`` holds now."""
    top, p = None, out.absolute()
    while not p.exists():
        top, p = p, p.parent
    return top, (set(out.iterdir()) if top is None and out.is_dir() else set())


def remove_new(out: Path, top, before) -> None:
    """Undo what a failed command wrote: the folders it created, or the entries
    it added to a folder that was there."""
    if top is not None:
        shutil.rmtree(top, ignore_errors=True)
    elif out.is_dir():
        for p in set(out.iterdir()) - before:
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)


def folder_name(text: str) -> str:
    """``text`` with each character that does not belong in a folder name replaced by ``_``."""
    return re.sub(r"[^A-Za-z0-9._=-]", "_", text)


def write_exr(path, channels: dict[str, np.ndarray]) -> None:
    """Write float32 channels to an EXR. Keys: ``"RGB"`` (H,W,3) or single names (H,W).

    OSError when the file cannot be written (OpenEXR raises RuntimeError for a full disk).
    """
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    data = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    with atomic_write(path) as tmp, OpenEXR.File(header, data) as f:
        try:
            f.write(str(tmp))
        except RuntimeError as exc:
            raise OSError(errno.EIO, str(exc).strip()) from None  # atomic_write names the file


def read_exr(path) -> dict[str, np.ndarray]:
    """Read an EXR's channels as float32 arrays, RGB grouped to (H,W,3).

    ValueError, with the library's reason, for a file that OpenEXR cannot
    read whole (a truncated or garbled one).
    """
    return _read_quietly(path, False, lambda f: {k: np.array(v.pixels, dtype=np.float32)
                                                 for k, v in f.channels().items()})


def exr_size(path) -> tuple[int, int]:
    """(width, height) in pixels of an EXR, from its header; ValueError as :func:`read_exr`."""
    lo, hi = _read_quietly(path, True, lambda f: f.header()["dataWindow"])
    return int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)


def _read_quietly(path, header_only: bool, read):
    """``read(f)`` of ``OpenEXR.File(path)``, with what the library prints captured.

    OpenEXR reports a damaged file by printing (on stderr from its C library,
    on stdout from its Python bindings) as well as, or instead of, raising:
    either makes the read a failure, whose reason is the first line printed.
    """
    failure = None
    with _output_captured() as said:
        try:
            with OpenEXR.File(str(path), header_only=header_only) as f:
                result = read(f)
        except Exception as exc:  # noqa: BLE001 (OpenEXR raises RuntimeError, ValueError, among others)
            failure = exc
    reasons = [line.strip().removeprefix(f"{path}: ") for line in said if line.strip()]
    if failure is not None or reasons:
        raise ValueError(reasons[0] if reasons else first_line(failure))
    return result


@contextlib.contextmanager
def _output_captured():
    """Keep what is printed while the block runs off stdout and stderr: in
    Python (``sys.stdout``, where OpenEXR's bindings print) and on file
    descriptors 1 and 2 (where its C and C++ code print). Yields a list of the
    lines, filled when the block ends."""
    for stream in (sys.stdout, sys.stderr):  # Python's pending text still goes where it was meant to
        with contextlib.suppress(Exception):
            stream.flush()
    lines = []
    saved = {}
    python = io.StringIO()
    try:
        for fd in (1, 2):
            with contextlib.suppress(OSError):  # a closed descriptor has nothing to protect
                saved[fd] = os.dup(fd)
        with tempfile.TemporaryFile() as sink:
            for fd in saved:
                os.dup2(sink.fileno(), fd)
            try:
                with contextlib.redirect_stdout(python), contextlib.redirect_stderr(python):
                    yield lines
            finally:
                if _LIBC is not None:
                    _LIBC.fflush(None)  # C's stdout is block-buffered when it is not a terminal
                for fd, copy in saved.items():
                    os.dup2(copy, fd)
                sink.seek(0)
                lines += sink.read().decode(errors="replace").splitlines() + python.getvalue().splitlines()
    finally:
        for copy in saved.values():
            os.close(copy)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """sRGB transfer function, clipped to [0, 1]; float32 in, float32 out."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(np.float32)


def to_uint8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_png(path, img: np.ndarray) -> None:
    """Write an image in [0, 1] ((H,W), (H,W,3) or (H,W,4)) as 8-bit PNG."""
    with atomic_write(path) as tmp:
        iio.imwrite(tmp, to_uint8(img), extension=".png")


def colorize(values: np.ndarray, mask: np.ndarray | None = None, vmin=None, vmax=None, cmap="turbo") -> np.ndarray:
    """Map a scalar image (H,W) to RGB (H,W,3) in [0,1]; pixels outside ``mask`` are black."""
    v = np.asarray(values, dtype=np.float64)
    m = np.isfinite(v) if mask is None else (mask & np.isfinite(v))
    if not m.any():
        return np.zeros(v.shape + (3,), dtype=np.float32)
    lo = np.min(v[m]) if vmin is None else vmin
    hi = np.max(v[m]) if vmax is None else vmax
    t = np.clip((v - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = matplotlib.colormaps[cmap](np.where(m, t, 0))[..., :3].astype(np.float32)
    rgb[~m] = 0.0
    return rgb
