"""On-disk cache of a dataset's loaded views (large images decoded and shrunk once).

A view is stored as ``.npz`` under a digest of everything it is made from:
the image (and depth map) file's path, size and modification time, the
crop, the downscale factor, the lens, the camera and the background. A
changed file or setting gives a new key, so a stale entry is never read.
Views of a lens camera are kept as captured (once they were resampled to a
pinhole, under keys without ``rays``): their keys name that, pinholes' keys
stay as they were.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np

from .imageio_utils import atomic_write

CACHE_VERSION = "1"
#: Frames at most this many full-resolution pixels are read again rather than cached.
MIN_CACHED_PIXELS = 512 * 512


def _stamp(path: Path | None):
    """What identifies a file's content cheaply: its resolved path, size and modification time."""
    if path is None:
        return None
    st = path.stat()
    return [str(path.resolve()), st.st_size, st.st_mtime_ns]


def view_key(frame, white_background: bool) -> str:
    """Hex digest naming the cached view of ``frame`` (a :class:`~mitsuba_active.datasets.Frame`)."""
    parts = {"v": CACHE_VERSION, "image": _stamp(frame.image), "depth": _stamp(frame.depth),
             "scale": frame.depth_scale, "is_distance": frame.depth_is_distance, "crop": list(frame.crop),
             "downscale": frame.downscale, "size": list(frame.full_size), "white": bool(white_background),
             "lens": None if frame.lens is None else dataclasses.asdict(frame.lens),
             "camera": [frame.camera.width, frame.camera.height, frame.camera.fov]}
    if frame.camera.lens is not None:
        parts["rays"] = dataclasses.asdict(frame.camera.lens)
    return hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()


def cached(cache_dir: Path | None, frame, white_background: bool, load) -> dict:
    """``load()``'s arrays (a dict of name -> ndarray) for ``frame``, from the cache when stored there;
    ``cache_dir`` None, or a small image, reads every time."""
    w, h = frame.full_size
    if cache_dir is None or w * h <= MIN_CACHED_PIXELS:
        return load()
    path = Path(cache_dir) / "views" / f"{view_key(frame, white_background)}.npz"
    if path.is_file():
        try:
            with np.load(path) as data:
                return {k: data[k] for k in data.files}
        except (OSError, ValueError, EOFError):
            pass  # a damaged entry is made again
    arrays = load()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path, suffix=".npz") as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    except OSError:
        pass  # a cache that cannot be written only costs time
    return arrays
