"""COLMAP projects read: the frames and bounds of a sparse model (``sparse/0`` and ``images/``, with pycolmap).

A project folder holds the sparse model ``sparse/0/{cameras,images,points3D}``
(``.bin`` or ``.txt``) and the photographs in ``images/``. Each registered
image becomes a frame of a :class:`~mitsuba_active.datasets.DatasetSource`:
its pose is COLMAP's world-to-camera in OpenCV axes (+X right, +Y down, +Z
forward) turned into Mitsuba's camera-to-world, its camera model into the
transforms.json keys the dataset reader undistorts by. The held-out frames
are spread evenly over the images sorted by name; the scene's bounds are
robust percentiles of the sparse points. :func:`~mitsuba_active.datasets.colmap_source`
makes the dataset source of a project.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .cameras import MITSUBA_TO_OPENCV, rigid_pose
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


def read_model(sparse: Path):
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


def heldout_indices(n: int, count) -> list[int]:
    """Indices of ``count`` frames spread evenly over ``n`` (``None``: every :data:`HOLDOUT_EVERY`-th),
    leaving at least one for training."""
    if count is None:
        return list(range(0, n, HOLDOUT_EVERY)) if n > 1 else []
    count = min(int(count), n - 1)
    if count <= 0:
        return []
    # Centred in their stretches, so that neither end is favoured.
    return sorted({int((k + 0.5) * n / count) for k in range(count)})
