"""COLMAP projects as view sources (``sparse/0`` and ``images/``, read with pycolmap).

A project folder holds the sparse model ``sparse/0/{cameras,images,points3D}``
(``.bin`` or ``.txt``) and the photographs in ``images/``. Each registered
image becomes a frame of a :class:`~mitsuba_active.datasets.DatasetSource`:
its pose is COLMAP's world-to-camera in OpenCV axes (+X right, +Y down, +Z
forward) turned into Mitsuba's camera-to-world, its camera model into the
transforms.json keys the dataset reader undistorts by. The held-out frames
are spread evenly over the images sorted by name; the scene's bounds are
robust percentiles of the sparse points.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from .cameras import MITSUBA_TO_OPENCV, rigid_pose
from .checks import is_whole
from .errors import UserError
from .transforms import CAMERA_KEYS

#: The sparse model's folder in a project, and the files it must hold (``.bin`` or ``.txt``).
SPARSE = Path("sparse") / "0"
MODEL_FILES = ("cameras", "images", "points3D")
#: COLMAP camera model -> (transforms.json camera_model, names of its parameters in order).
CAMERA_MODELS = {
    "SIMPLE_PINHOLE": ("PINHOLE", ("f", "cx", "cy")),
    "PINHOLE": ("PINHOLE", ("fl_x", "fl_y", "cx", "cy")),
    "SIMPLE_RADIAL": ("OPENCV", ("f", "cx", "cy", "k1")),
    "RADIAL": ("OPENCV", ("f", "cx", "cy", "k1", "k2")),
    "OPENCV": ("OPENCV", ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "p1", "p2")),
    "OPENCV_FISHEYE": ("OPENCV_FISHEYE", ("fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "k4")),
}
#: Percentiles of the sparse points, per axis, that bound the scene (outliers lie beyond).
BOUNDS_PERCENTILES = (1.0, 99.0)
#: Every how many images one is held out when no count is given.
HOLDOUT_EVERY = 8


def is_colmap_project(path) -> bool:
    """True when ``path`` is a folder holding a ``sparse/0`` folder."""
    return (Path(path) / SPARSE).is_dir()


def colmap_source(path, *, n_heldout=None, **options):
    """The :class:`~mitsuba_active.datasets.DatasetSource` of a COLMAP project folder.

    ``n_heldout`` images (evenly spaced over the names; ``None``: every
    8th) are held out; ``options`` are those of
    :meth:`DatasetSource.from_parsed <mitsuba_active.datasets.DatasetSource.from_parsed>`.
    """
    from .datasets import DatasetSource

    root = Path(path)
    sparse = root / SPARSE
    if n_heldout is not None and (not is_whole(n_heldout) or n_heldout < 0):
        raise UserError(f"n_heldout must be a whole number >= 0 (or None: every {HOLDOUT_EVERY}th image), "
                        f"got {n_heldout!r}")
    files = []
    for stem in MODEL_FILES:
        found = [sparse / f"{stem}{ext}" for ext in (".bin", ".txt") if (sparse / f"{stem}{ext}").is_file()]
        if not found:
            raise UserError(f"{sparse} has no {stem}.bin or {stem}.txt: not a COLMAP sparse model")
        files.append(found[0])
    rec = _read_model(sparse)
    frames, points = frames_from_reconstruction(rec, root / "images", str(sparse))
    if not frames:
        raise UserError(f"{sparse}: the model has no registered images")
    held = set(_heldout_indices(len(frames), n_heldout))
    train = [f for i, f in enumerate(frames) if i not in held]
    test = [f for i, f in enumerate(frames) if i in held]
    src = DatasetSource.from_parsed(train, test, points_bounds(points), root.resolve().name, root,
                                    n_heldout=n_heldout, where=sparse, **options)
    digest = hashlib.sha256()
    for f in files:
        digest.update(f.read_bytes())
    src.content_hash = digest.hexdigest()
    return src


def _read_model(sparse: Path):
    """The pycolmap Reconstruction in ``sparse``; UserError when pycolmap is missing or cannot read it."""
    try:
        import pycolmap
    except ImportError:
        raise UserError("reading COLMAP projects needs pycolmap: pip install 'mitsuba-active[colmap]'") from None
    try:
        return pycolmap.Reconstruction(str(sparse))
    except Exception as exc:  # noqa: BLE001 (pycolmap raises its own kinds)
        text = str(exc).strip().splitlines()
        raise UserError(f"{sparse}: cannot read the COLMAP model ({text[-1] if text else type(exc).__name__})") \
            from None


def frames_from_reconstruction(rec, images: Path, where: str):
    """``(frames, points)``: the parsed frames (see ``DatasetSource.from_parsed``) of a pycolmap
    Reconstruction's registered images, sorted by name, and its (N, 3) float64 sparse points."""
    frames = []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        camera = rec.cameras[image.camera_id]
        name = f"{where}: image {image.name}"
        keys = camera_keys(camera.model.name, list(camera.params), camera.width, camera.height, name)
        pose = image.cam_from_world()
        world_to_cam = np.vstack([np.asarray(pose.matrix(), dtype=np.float64), [0.0, 0.0, 0.0, 1.0]])
        to_world = rigid_pose(np.linalg.inv(world_to_cam), f"{name}: pose") @ MITSUBA_TO_OPENCV
        frames.append((images / image.name, to_world, keys, (None, 1.0, False), name))
    points = np.array([p.xyz for p in rec.points3D.values()], dtype=np.float64).reshape(-1, 3)
    return frames, points


def camera_keys(model: str, params: list, width: int, height: int, where: str) -> dict:
    """The transforms.json camera keys (``fl_x``, ``cx``, ``k1``, ``camera_model``, ...) of a COLMAP camera."""
    if model not in CAMERA_MODELS:
        raise UserError(f"{where}: COLMAP camera model {model} is not supported "
                        f"(supported: {', '.join(CAMERA_MODELS)})")
    camera_model, names = CAMERA_MODELS[model]
    if len(params) != len(names):
        raise UserError(f"{where}: a {model} camera has {len(names)} parameters, got {len(params)}")
    keys = dict.fromkeys(CAMERA_KEYS)
    values = dict(zip(names, (float(p) for p in params)))
    if "f" in values:
        values["fl_x"] = values["fl_y"] = values.pop("f")
    keys.update(values, w=int(width), h=int(height), camera_model=camera_model)
    return keys


def points_bounds(points: np.ndarray):
    """``(min, max)`` (3,) float64: the :data:`BOUNDS_PERCENTILES` of (N, 3) points per axis, or None
    for fewer than 4 points (the bounds are then estimated from the cameras)."""
    if len(points) < 4:
        return None
    lo, hi = np.percentile(points, BOUNDS_PERCENTILES, axis=0)
    return lo, hi


def _heldout_indices(n: int, count) -> list[int]:
    """Indices of ``count`` frames spread evenly over ``n`` (``None``: every :data:`HOLDOUT_EVERY`-th),
    leaving at least one for training."""
    if count is None:
        return list(range(0, n, HOLDOUT_EVERY)) if n > 1 else []
    count = min(int(count), n - 1)
    if count <= 0:
        return []
    # Centred in their stretches, so that neither end is favoured.
    return sorted({int((k + 0.5) * n / count) for k in range(count)})
