"""Reading NeRF ``transforms*.json`` files: which files, their split, each frame's keys.

The files of a dataset folder (nerf-synthetic's ``transforms_train.json``
and ``transforms_test.json``, or one ``transforms.json``), their split into
training and held-out frames, each frame validated into its image, pose
(Mitsuba's camera-to-world), camera keys and depth map, and the scene's box
from the file's keys. :mod:`.datasets` makes views of the frames; see
docs/datasets.md for the conventions.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np

from .cameras import MITSUBA_TO_OPENGL, rigid_pose
from .checks import is_number
from .errors import UserError

#: The files a dataset folder is read from, in order of preference.
TRANSFORMS_FILES = ("transforms_train.json", "transforms.json")
#: Extensions tried, in order, when a ``file_path`` has none (nerf-synthetic: "./train/r_0").
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr", ".PNG", ".JPG", ".JPEG")
#: Per-frame keys that override the file's top-level camera keys (nerfstudio allows this).
CAMERA_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
               "k1", "k2", "k3", "k4", "p1", "p2", "camera_model")
#: Every how many frames one is held out when a single-file dataset has no split.
HOLDOUT_EVERY = 8
#: instant-ngp's defaults for the map from scene to its unit cube (``pos * scale + offset``).
NGP_SCALE, NGP_OFFSET = 0.33, [0.5, 0.5, 0.5]


def locate_files(path):
    """The JSON files of a dataset ``(files, name, root)``; files[0] is the train (or only) file."""
    p = Path(path)
    if not p.exists():
        raise UserError(f"dataset not found: {p}")
    if p.is_dir():
        for candidate in TRANSFORMS_FILES:
            if (p / candidate).is_file():
                p = p / candidate
                break
        else:
            raise UserError(f"{p} holds neither transforms_train.json nor transforms.json (nor a COLMAP sparse/0)")
    if p.suffix.lower() != ".json":
        raise UserError(f"{p}: a dataset is a transforms .json file or a folder holding one")
    root = p.parent
    name = root.resolve().name
    if p.name == "transforms_train.json":
        test = root / "transforms_test.json"
        return ([p, test] if test.is_file() else [p]), name, root
    return [p], name, root


def read_transforms(path: Path) -> dict:
    try:
        with open(path, encoding="utf-8") as fh:
            meta = json.load(fh)
    except json.JSONDecodeError as exc:
        raise UserError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except UnicodeDecodeError:
        raise UserError(f"{path}: not valid JSON (not UTF-8 text)") from None
    except RecursionError:
        raise UserError(f"{path}: not a dataset's JSON (nested too deeply to read)") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read ({exc.strerror})") from None
    if not isinstance(meta, dict):
        raise UserError(f"{path}: expected a JSON object with 'frames'")
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise UserError(f"{path}: the dataset has no frames")
    if not all(isinstance(f, dict) for f in frames):
        raise UserError(f"{path}: every entry of 'frames' must be an object")
    return meta


def split_frames(metas, files):
    """``(train, test)`` lists of ``(frame dict, file meta, json path, index in the file's frames)``."""
    if len(metas) == 2:  # nerf-synthetic: the files are the split
        (ftr, mtr), (fte, mte) = metas
        return ([(fr, mtr, ftr, i) for i, fr in enumerate(mtr["frames"])],
                [(fr, mte, fte, i) for i, fr in enumerate(mte["frames"])])
    jf, meta = metas[0]
    frames = meta["frames"]
    tagged = [(fr, meta, jf, i) for i, fr in enumerate(frames)]
    if any("split" in fr for fr in frames):
        test = [t for t in tagged if t[0].get("split") == "test"]
        if not test:
            test = [t for t in tagged if t[0].get("split") == "val"]
        return [t for t in tagged if t[0].get("split", "train") == "train"], test
    if "test_filenames" in meta or "val_filenames" in meta or "train_filenames" in meta:
        def names(key):
            listed = meta.get(key, [])
            if not isinstance(listed, list) or not all(isinstance(n, str) for n in listed):
                raise UserError(f"{jf}: '{key}' must be a list of file names, got {listed!r}")
            return {os.path.normpath(n) for n in listed}

        held = names("test_filenames") or names("val_filenames")
        train_names = names("train_filenames")
        norm = lambda t: os.path.normpath(str(t[0].get("file_path", "")))  # noqa: E731
        test = [t for t in tagged if norm(t) in held]
        train = [t for t in tagged if (norm(t) in train_names if train_names else norm(t) not in held)]
        return train, test
    if len(frames) < 2:
        return tagged, []
    return ([t for i, t in enumerate(tagged) if i % HOLDOUT_EVERY != 0],
            [t for i, t in enumerate(tagged) if i % HOLDOUT_EVERY == 0])


def _image_path(frame: dict, json_path: Path, index: int):
    """Resolve ``file_path`` (relative to the JSON's folder), trying extensions when the file is absent."""
    fp = frame.get("file_path")
    if fp is not None and not isinstance(fp, str):
        raise UserError(f"{json_path}: frame {index}'s file_path must be a file name, got {fp!r}")
    if not fp:
        raise UserError(f"{json_path}: frame {index} has no 'file_path'")
    p = json_path.parent / fp
    if p.is_file():
        return p
    for ext in IMAGE_EXTENSIONS:
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    return p


def parse_frame(frame: dict, meta: dict, json_path: Path, index: int):
    """Validate one frame (``index``: its place in the file's ``frames``); ``(image, to_world (Mitsuba),
    camera keys, (map, scale, is distance), where)``."""
    image = _image_path(frame, json_path, index)
    where = f"{json_path}: frame {index} ({frame.get('file_path')})"
    if "transform_matrix" not in frame:
        raise UserError(f"{where} has no 'transform_matrix'")
    to_world = opengl_to_mitsuba(frame["transform_matrix"], f"{where}: transform_matrix")
    keys = {k: frame.get(k, meta.get(k)) for k in CAMERA_KEYS}
    depth, scale = None, 1.0
    # distance_file_path: our own export (EXR channel Z, distance from the optical centre).
    for key in ("distance_file_path", "depth_file_path"):
        if frame.get(key) is not None and not isinstance(frame[key], str):
            raise UserError(f"{where}: {key} must be a file name, got {frame[key]!r}")
    is_distance = bool(frame.get("distance_file_path"))
    map_path = frame.get("distance_file_path") or frame.get("depth_file_path")
    if map_path:
        depth = json_path.parent / map_path
        if not depth.is_file():
            warnings.warn(f"{where}: depth map {depth} is missing; its distances are unknown", stacklevel=3)
            depth = None
        else:
            # nerfstudio's default: 16-bit PNG depth in millimetres; float files are in scene units.
            default = 1.0 if depth.suffix.lower() in (".exr", ".npy") else 1e-3
            scale = meta.get("depth_unit_scale_factor", default)
            if not (is_number(scale, finite=True) and scale > 0):
                raise UserError(f"{json_path}: depth_unit_scale_factor must be a positive number, got {scale!r}")
            scale = float(scale)
    return image, to_world, keys, (depth, scale, is_distance), where


def opengl_to_mitsuba(matrix, what="transform_matrix") -> np.ndarray:
    """OpenGL/Blender camera-to-world (looks along -Z) -> Mitsuba camera-to-world (looks along +Z).

    The matrix is checked and its rotation re-orthonormalised by
    :func:`~mitsuba_active.cameras.rigid_pose` (dataset files store ~1e-7
    errors); ``what`` names it in the :class:`UserError` of a bad one.
    """
    return rigid_pose(matrix, what) @ MITSUBA_TO_OPENGL


def mitsuba_to_opengl(to_world) -> np.ndarray:
    """Mitsuba camera-to-world -> OpenGL/Blender ``transform_matrix`` (the inverse of :func:`opengl_to_mitsuba`)."""
    return np.asarray(to_world, dtype=np.float64) @ MITSUBA_TO_OPENGL


def bounds_from_keys(metas):
    """``(min, max)`` from an ``aabb`` or ``scene_box`` key ([[x,y,z],[x,y,z]]), else instant-ngp's
    ``aabb_scale`` unit cube, else None."""
    for jf, meta in metas:
        for key in ("aabb", "scene_box"):
            box = meta.get(key)
            if isinstance(box, dict):
                box = box.get("aabb")
            if box is None:
                continue
            try:
                b = np.asarray(box, dtype=np.float64)
            except (TypeError, ValueError):
                b = np.zeros(0)
            # A flat box (a planar scene's, as a run records it) is a box: the fields give it depth.
            if not (b.shape == (2, 3) and np.all(np.isfinite(b)) and np.all(b[1] >= b[0]) and np.any(b[1] > b[0])):
                raise UserError(f"{jf}: '{key}' must be [[xmin,ymin,zmin],[xmax,ymax,zmax]], got {box}")
            return b[0], b[1]
    for jf, meta in metas:
        if "aabb_scale" in meta:
            return _ngp_box(jf, meta)
    return None


def _ngp_box(jf: Path, meta: dict):
    """instant-ngp's box: the unit cube of its space (``pos * scale + offset``), in the file's coordinates
    (an ``aabb_scale`` over 1 says the scene reaches past it: the fields then contract it, see
    :meth:`~mitsuba_active.datasets.DatasetSource.field_options`)."""
    scale, offset, k = meta.get("scale", NGP_SCALE), meta.get("offset", NGP_OFFSET), meta["aabb_scale"]
    o = np.asarray(offset, dtype=np.float64) if isinstance(offset, list) else np.zeros(0)
    if not (is_number(scale, finite=True) and scale > 0 and o.shape == (3,) and np.all(np.isfinite(o))
            and is_number(k, finite=True) and k >= 1):
        raise UserError(f"{jf}: aabb_scale (>= 1), scale (> 0) and offset ([x, y, z]) must be numbers, "
                        f"got {k!r}, {scale!r}, {offset!r}")
    if np.ptp(o) > 0:  # instant-ngp cycles the axes before it offsets them
        raise UserError(f"{jf}: an offset unlike on every axis ({offset}) is not read; give the box as 'aabb'")
    return (0.0 - o) / scale, (1.0 - o) / scale


def aabb_scale_from_keys(metas) -> float | None:
    """instant-ngp's ``aabb_scale`` (how many times the box the scene reaches; checked by
    :func:`bounds_from_keys`), or None where no file gives one."""
    for _, meta in metas:
        if is_number(meta.get("aabb_scale"), finite=True):
            return float(meta["aabb_scale"])
    return None
