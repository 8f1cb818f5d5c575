"""Pre-captured datasets (NeRF ``transforms*.json``) as view sources.

:class:`DatasetSource` implements the :class:`~mitsuba_active.env.ViewSource`
protocol over posed photographs, so :class:`~mitsuba_active.env.ActiveViewEnv`
and the evaluation protocol run on them unchanged. Two layouts are read:

* nerf-synthetic (Blender): ``transforms_train.json`` + ``transforms_test.json``
  with a global ``camera_angle_x`` (horizontal fov in radians);
* instant-ngp / nerfstudio: one ``transforms.json`` with ``fl_x``, ``fl_y``,
  ``cx``, ``cy``, ``w``, ``h`` (pixels; any of them may also be given per
  frame), split by a per-frame ``split`` key, by nerfstudio's
  ``train_filenames`` / ``test_filenames``, or else every 8th frame held out.

Poses (``transform_matrix``) are camera-to-world in the OpenGL/Blender
convention and become Mitsuba's by a right-multiplication with
:data:`~mitsuba_active.cameras.MITSUBA_TO_OPENGL`. Images are read lazily,
composited on white (or black), area-averaged by an integer factor and
cached in memory. See docs/datasets.md for the conventions and limits.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .cameras import MITSUBA_TO_OPENGL, Camera, rigid_pose
from .checks import is_number, is_whole
from .errors import UserError
from .groundtruth import View
from .imageio_utils import exr_size, linear_to_srgb, read_exr, srgb_to_linear

#: Extensions tried, in order, when a ``file_path`` has none (nerf-synthetic: "./train/r_0").
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".exr", ".PNG", ".JPG", ".JPEG")
#: Per-frame keys that override the file's top-level camera keys (nerfstudio allows this).
CAMERA_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y",
               "k1", "k2", "k3", "k4", "p1", "p2", "camera_model")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
#: Relative difference of fl_x and fl_y accepted as square pixels.
SQUARE_PIXEL_TOL = 1e-3
#: Every how many frames one is held out when a single-file dataset has no split.
HOLDOUT_EVERY = 8
#: Margin of the estimated object box over the radius that fills the views.
BOUNDS_MARGIN = 1.1


@dataclass(frozen=True)
class Frame:
    """One posed image of a dataset.

    Attributes:
        image: path of the image file.
        camera: the camera at the *downscaled* resolution (Mitsuba convention).
        crop: ``(x0, y0, width, height)`` window of the full-resolution image
            that the camera sees, in pixels; width and height are multiples of
            ``downscale`` (the crop also centres an off-centre principal point).
        downscale: integer area-averaging factor.
        full_size: ``(width, height)`` of the image file in pixels.
        depth: optional metric depth map (z along the optical axis), or distance
            map (along each ray, from the optical centre) when ``depth_is_distance``.
        depth_scale: factor from the map's stored values to scene units.
        depth_is_distance: the map already holds distances (``distance_file_path``).
    """

    image: Path
    camera: Camera
    crop: tuple
    downscale: int
    full_size: tuple
    depth: Path | None = None
    depth_scale: float = 1.0
    depth_is_distance: bool = False


class DatasetSource:
    """Views of a pre-captured dataset: training frames are candidates, test frames held out.

    Build it with :meth:`from_path`. Views are looked up, not rendered:
    :meth:`render` returns a stored view when the camera is one of the
    dataset's and raises :class:`UserError` for any other pose.

    Attributes:
        candidates, heldout: lists of :class:`Camera` (one resolution).
        candidate_frames, heldout_frames: the matching :class:`Frame` records.
        candidate_files, heldout_files: their image files, relative to ``root``
            (``"train/r_77.png"``): which of the dataset's frames each view is.
        bbox_min, bbox_max: (3,) float64 scene bounds in scene units.
        name: the dataset folder's name.
        content_hash: hex digest of the dataset's JSON files (None unless
            built by :meth:`from_path`); runs are matched to it.
    """

    def __init__(self, candidate_frames, heldout_frames, bbox_min, bbox_max, name="dataset",
                 white_background=True, root=None):
        self.candidate_frames, self.heldout_frames = list(candidate_frames), list(heldout_frames)
        self.candidates = [f.camera for f in self.candidate_frames]
        self.heldout = [f.camera for f in self.heldout_frames]
        self.root = None if root is None else Path(root)

        def file(frame):  # the name a user finds it by, '/' between folders as in the dataset's JSON
            return Path(os.path.relpath(frame.image, self.root) if self.root else frame.image.name).as_posix()

        self.candidate_files = [file(f) for f in self.candidate_frames]
        self.heldout_files = [file(f) for f in self.heldout_frames]
        self.bbox_min = np.asarray(bbox_min, dtype=np.float64)
        self.bbox_max = np.asarray(bbox_max, dtype=np.float64)
        self.name = name
        if not isinstance(white_background, (bool, np.bool_)):  # bool("false") would be True
            raise UserError(f"white_background must be True or False, got {white_background!r}")
        self.white_background = bool(white_background)
        self._views: dict[int, View] = {}  # keyed by id(frame): frames may repeat across splits
        self.content_hash = None  # set by from_path: a digest of the dataset's JSON files

    @property
    def has_distance(self) -> bool:
        """True when the candidate frames come with depth maps (else views' distances are all 0)."""
        return any(f.depth is not None for f in self.candidate_frames)

    @classmethod
    def from_path(cls, path, downscale: int | None = 1, n_heldout: int | None = None,
                  white_background: bool = True, n_candidates: int | None = None,
                  resolution: int = 64) -> "DatasetSource":
        """Read a dataset.

        Args:
            path: ``transforms_train.json``, ``transforms.json`` (or any other
                single-file ``.json``), or a folder that holds one of them.
            downscale: integer factor by which images shrink (area averaging);
                ``None`` picks ``max(1, round(width / resolution))``.
            n_heldout: keep at most this many held-out frames, evenly spaced.
            white_background: composite RGBA images on white (else black).
            n_candidates: keep at most this many candidate frames, evenly spaced.
            resolution: target width in pixels when ``downscale`` is None.
        """
        for key, count in (("n_candidates", n_candidates), ("n_heldout", n_heldout)):
            if count is not None and (not is_whole(count) or count < 0):
                raise UserError(f"{key} must be a whole number >= 0 (or None: all frames), got {count!r}")
        if n_candidates == 0:
            raise UserError("at least one candidate view is needed, got n_candidates=0")
        if downscale is None and (not is_whole(resolution) or resolution < 1):
            raise UserError(f"image resolution must be a positive whole number, got {resolution!r}")
        files, name, root = _locate(path)
        metas = [(f, _read_json(f)) for f in files]
        train, test = _split(metas, files)
        if not train and not test:
            raise UserError(f"{files[0]}: the dataset has no frames")
        bounds = _bounds_from_keys(metas)

        # Parse everything first (errors name the frame), then drop missing images.
        train = [_parse_frame(*t) for t in train]
        test = [_parse_frame(*t) for t in test]
        missing = [t[0] for t in train + test if not t[0].is_file()]
        n_frames = len(train) + len(test)
        train = [t for t in train if t[0].is_file()]
        test = [t for t in test if t[0].is_file()]
        # Refused before the warning about skipped frames: one line says it all.
        if not train and not test:
            raise UserError(f"{files[0]}: none of the dataset's image files exist (e.g. {missing[0]})")
        if not train:
            raise UserError(f"{root}: no training frame has an image file")
        if missing:
            warnings.warn(f"{name}: skipped {len(missing)} of {n_frames} frames whose image "
                          f"file is missing (e.g. {missing[0]})", stacklevel=2)

        if downscale is None:
            width = _full_size(train[0])[0]
            downscale = max(1, round(width / resolution))
        if not is_number(downscale, finite=True) or int(downscale) != downscale or int(downscale) < 1:
            raise UserError(f"downscale must be a positive integer, got {downscale!r}")
        downscale = int(downscale)
        # One window size for every frame (views share one resolution): the
        # smallest frame's, so that per-frame principal points a fraction of
        # a pixel apart do not give crops a pixel apart.
        train = [(t, _full_size(t)) for t in train]
        test = [(t, _full_size(t)) for t in test]
        windows = [_window(t, full, downscale) for t, full in train + test]
        size = (min(w[2] for w in windows), min(w[3] for w in windows))
        train = _subsample([_make_frame(t, full, downscale, size) for t, full in train], n_candidates)
        test = _subsample([_make_frame(t, full, downscale, size) for t, full in test], n_heldout)
        if not test:
            raise UserError(f"{root}: no held-out frames to evaluate on (no test or val split, or "
                            "a held-out count of 0); tag some frames \"split\": \"test\"")
        if bounds is None:
            bounds = estimate_bounds([f.camera for f in train + test])
        src = cls(train, test, bounds[0], bounds[1], name=name, white_background=white_background, root=root)
        # What the frames are (poses, image and depth file names), wherever
        # the dataset lies and whichever of its names it was opened by.
        digest = hashlib.sha256()
        for f in files:
            digest.update(f.read_bytes())
        src.content_hash = digest.hexdigest()
        return src

    # -- ViewSource ----------------------------------------------------------
    def candidate_view(self, index: int) -> View:
        return self._view(self.candidate_frames[index])

    def heldout_view(self, index: int) -> View:
        return self._view(self.heldout_frames[index])

    def render(self, camera: Camera) -> View:
        """The stored view when ``camera`` is one of the dataset's cameras; otherwise UserError."""
        for frame in self.candidate_frames + self.heldout_frames:
            c = frame.camera
            if ((c.width, c.height) == (camera.width, camera.height) and abs(c.fov - camera.fov) < 1e-6
                    and np.allclose(c.to_world, camera.to_world, atol=1e-6)):
                return self._view(frame)
        raise UserError(f"{self.name}: a pre-captured dataset cannot render new poses")

    def _view(self, frame: Frame) -> View:
        """The frame's view, read once; each call gets arrays of its own, as a scene's renders
        are, so that a caller's edits (an augmentation in place) reach no other view."""
        key = id(frame)
        if key not in self._views:
            self._views[key] = load_view(frame, self.white_background)
        view = self._views[key]
        return View(view.rgb.copy(), view.distance.copy(), view.mask.copy(), view.camera, view.known_empty.copy(),
                    view.background)

    def __repr__(self):
        c = self.candidates[0]
        return (f"DatasetSource({self.name!r}, {len(self.candidates)} candidates, {len(self.heldout)} held out, "
                f"{c.width}x{c.height}, fov {c.fov:.2f})")


# ---------------------------------------------------------------------------
# Views
# ---------------------------------------------------------------------------

def load_view(frame: Frame, white_background: bool = True) -> View:
    """Read, composite, crop and downscale one frame's image (and depth map if any)."""
    cam, f = frame.camera, frame.downscale
    rgb, alpha = _read_rgb(frame.image, white_background)
    if rgb.shape[1::-1] != tuple(frame.full_size):
        w, h = frame.full_size
        raise UserError(f"{frame.image} is {rgb.shape[1]}x{rgb.shape[0]} pixels, the dataset says {w}x{h}")
    rgb = _crop(rgb, frame.crop, frame.image)
    # Average in linear light, as a camera pixel (and Mitsuba's box filter) does.
    rgb = linear_to_srgb(area_downscale(srgb_to_linear(rgb), f))
    # Known empty: every full-resolution pixel under a downscaled one is transparent.
    empty = (np.zeros(rgb.shape[:2], bool) if alpha is None
             else area_downscale(_crop(alpha, frame.crop, frame.image), f) <= 0.0)
    distance = np.zeros((cam.height, cam.width), np.float32)
    if frame.depth is not None:
        entry = "distance_file_path" if frame.depth_is_distance else "depth_file_path"
        depth = _crop(_read_depth(frame.depth, entry), frame.crop, frame.depth) * frame.depth_scale
        # Depth at the full-resolution pixel nearest each downscaled pixel centre:
        # averaging across a silhouette would invent depths that lie on no surface.
        z = depth[f // 2::f, f // 2::f][: cam.height, : cam.width]
        z = np.where(np.isfinite(z) & (z > 0), z, 0.0)
        distance = (z if frame.depth_is_distance else z * depth_to_distance_factor(cam)).astype(np.float32)
    background = None if alpha is None else (1.0,) * 3 if white_background else (0.0,) * 3
    return View(rgb.astype(np.float32), distance, distance > 0, cam, empty, background)


def depth_to_distance_factor(camera: Camera) -> np.ndarray:
    """(H, W) factor turning depth along the optical axis into distance along pixel-centre rays."""
    k = camera.intrinsics()
    x = (np.arange(camera.width) + 0.5 - k[0, 2]) / k[0, 0]
    y = (np.arange(camera.height) + 0.5 - k[1, 2]) / k[1, 1]
    return np.sqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2)


def area_downscale(img: np.ndarray, f: int) -> np.ndarray:
    """Mean over ``f x f`` blocks; (H, W, ...) -> (H // f, W // f, ...); H, W must be multiples of f."""
    if f == 1:
        return img
    h, w = img.shape[:2]
    return img.reshape(h // f, f, w // f, f, *img.shape[2:]).mean(axis=(1, 3))


def _read_exr(path: Path, what: str) -> dict:
    """:func:`~mitsuba_active.imageio_utils.read_exr`, with a file it cannot read as a UserError."""
    try:
        return read_exr(path)
    except ValueError as exc:
        raise UserError(f"cannot read {what} {path}: {exc}") from None


def _exr_colour(path: Path, white_background: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """(H, W, 3) float32 sRGB of an EXR image: RGB, RGBA or grey (Y); its
    alpha is premultiplied (EXR's convention), so composited in linear light;
    and its (H, W) alpha, or None."""
    ch = _read_exr(path, "image")
    if "RGBA" in ch:  # OpenEXR groups R, G, B and A
        rgb, alpha = ch["RGBA"][..., :3], ch["RGBA"][..., 3]
    elif "RGB" in ch or "Y" in ch:
        rgb = ch["RGB"] if "RGB" in ch else np.repeat(ch["Y"][..., None], 3, axis=-1)
        alpha = ch.get("A")
    else:
        raise UserError(f"{path} has no colour channels (RGB, RGBA or Y), only {', '.join(sorted(ch))}")
    if alpha is not None:
        rgb = rgb + (1.0 - alpha[..., None]) * (1.0 if white_background else 0.0)
    return linear_to_srgb(rgb), alpha


def _read_rgb(path: Path, white_background: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """(H, W, 3) float32 sRGB in [0, 1], alpha composited (in sRGB for PNG and JPEG, the
    nerf-synthetic convention; in linear light for EXR); and the (H, W) float32 alpha in
    [0, 1], or None for an image without one."""
    if path.suffix.lower() == ".exr":
        rgb, alpha = _exr_colour(path, white_background)
        alpha = None if alpha is None else np.clip(alpha, 0.0, 1.0).astype(np.float32)
        return np.clip(rgb, 0.0, 1.0).astype(np.float32), alpha
    import imageio.v3 as iio
    from PIL import Image

    try:
        with Image.open(path) as im:
            cmyk = im.mode == "CMYK"  # 4 channels that are no alpha: as RGB
        raw = iio.imread(path, mode="RGB") if cmyk else iio.imread(path)
    except Exception as exc:
        raise UserError(f"cannot read image {path}: {exc}") from None
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(raw.dtype, 1.0)
    img = raw.astype(np.float32) / scale
    if img.ndim == 2:
        img = img[..., None]
    alpha = None
    if img.shape[-1] in (2, 4):  # grey + alpha, RGB + alpha
        alpha = np.clip(img[..., -1], 0.0, 1.0)
        bg = 1.0 if white_background else 0.0
        img = img[..., :-1] * alpha[..., None] + bg * (1.0 - alpha[..., None])
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    return np.clip(img, 0.0, 1.0).astype(np.float32), alpha


def _read_depth(path: Path, entry: str) -> np.ndarray:
    """(H, W) float32 stored depth values (unscaled); ``entry``: the frame's key naming the file."""
    if path.suffix.lower() == ".exr":
        ch = _read_exr(path, "depth map")
        key = next((k for k in ("Z", "Y", "R", "depth") if k in ch), next(iter(ch)))
        d = ch[key]
        return d[..., 0] if d.ndim == 3 else d
    if path.suffix.lower() == ".npy":
        try:
            d = np.load(path)
        except (OSError, ValueError) as exc:
            raise UserError(f"cannot read depth map {path}: {exc}") from None
        if d.ndim != 2 or not np.issubdtype(d.dtype, np.number):
            raise UserError(f"depth map {path} must be a 2-D array of numbers, got {d.dtype} {d.shape}")
        return d.astype(np.float32)
    import imageio.v3 as iio

    try:
        d = iio.imread(path)
    except Exception as exc:
        raise UserError(f"cannot read depth map {path}: {exc}") from None
    if d.dtype == np.uint8 and _png_bit_depth(path) == 16:  # Pillow reads 16-bit colour PNGs as 8-bit
        raise UserError(f"depth map {path} is a 16-bit colour PNG, which is read as 8-bit; store depth as a "
                        "16-bit grey PNG, an EXR or a .npy")
    if d.dtype == np.uint8:
        # 8-bit maps (e.g. nerf-synthetic's r_N_depth_0186.png) are normalised, not metric.
        raise UserError(f"depth map {path} is 8-bit and therefore not metric; remove the frame's {entry}")
    return (d[..., 0] if d.ndim == 3 else d).astype(np.float32)


def _png_bit_depth(path: Path) -> int | None:
    """Bits per channel a PNG file's header gives (None for another kind of file)."""
    with open(path, "rb") as fh:
        head = fh.read(25)
    return head[24] if len(head) == 25 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" else None


def _crop(img: np.ndarray, crop, path) -> np.ndarray:
    x0, y0, w, h = crop
    if img.shape[0] < y0 + h or img.shape[1] < x0 + w:
        raise UserError(f"{path} is {img.shape[1]}x{img.shape[0]} pixels, smaller than the dataset says")
    return img[y0:y0 + h, x0:x0 + w]


# ---------------------------------------------------------------------------
# Files and frames
# ---------------------------------------------------------------------------

def _locate(path):
    """The JSON files of a dataset ``(files, name, root)``; files[0] is the train (or only) file."""
    p = Path(path)
    if not p.exists():
        raise UserError(f"dataset not found: {p}")
    if p.is_dir():
        for candidate in ("transforms_train.json", "transforms.json"):
            if (p / candidate).is_file():
                p = p / candidate
                break
        else:
            raise UserError(f"{p} holds neither transforms_train.json nor transforms.json")
    if p.suffix.lower() != ".json":
        raise UserError(f"{p}: a dataset is a transforms .json file or a folder holding one")
    root = p.parent
    name = root.resolve().name
    if p.name == "transforms_train.json":
        test = root / "transforms_test.json"
        return ([p, test] if test.is_file() else [p]), name, root
    return [p], name, root


def _read_json(path: Path) -> dict:
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


def _split(metas, files):
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


def _parse_frame(frame: dict, meta: dict, json_path: Path, index: int):
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


def _full_size(parsed) -> tuple[int, int]:
    """Full-resolution (width, height) of a parsed frame: the JSON's ``w``/``h``, else the image header."""
    image, _, keys, _, where = parsed
    for name in ("w", "h"):
        value = keys[name]
        if value is not None and not (is_number(value, finite=True) and float(value).is_integer() and value > 0):
            raise UserError(f"{where}: {name} must be a whole number of pixels, got {value!r}")
    if keys["w"] is not None and keys["h"] is not None:
        return int(keys["w"]), int(keys["h"])
    if image.suffix.lower() == ".exr":
        try:
            return exr_size(image)
        except ValueError as exc:
            raise UserError(f"cannot read image {image}: {exc}") from None
    from PIL import Image

    try:
        with Image.open(image) as im:
            return im.size
    except Exception as exc:
        raise UserError(f"cannot read image {image}: {exc}") from None


def _window(parsed, full_size, downscale: int, size=None) -> tuple:
    """``(x0, y0, width, height)``: the crop window in full-resolution pixels of a
    frame whose image is ``full_size`` (width, height).

    Our camera model has its principal point at the image centre: the window
    is the largest one centred on (cx, cy), at most ``size`` (width, height),
    trimmed to multiples of the factor."""
    _, _, keys, _, where = parsed
    w, h = full_size
    _, _, cx, cy = _intrinsics(keys, w, h, where)
    x0, wc = _centred_window(cx, w, downscale, size and size[0])
    y0, hc = _centred_window(cy, h, downscale, size and size[1])
    if wc < downscale or hc < downscale:
        raise UserError(f"{where}: the image ({w}x{h}) is too small for downscale {downscale}")
    return x0, y0, wc, hc


def _make_frame(parsed, full_size, downscale: int, size=None) -> Frame:
    """Camera and crop window (at most ``size``) of one frame, at ``1 / downscale`` resolution."""
    image, to_world, keys, depth, where = parsed
    w, h = full_size
    fx, _, _, _ = _intrinsics(keys, w, h, where)
    x0, y0, wc, hc = _window(parsed, full_size, downscale, size)
    fov = math.degrees(2.0 * math.atan(0.5 * wc / fx))
    cam = Camera(to_world, fov, wc // downscale, hc // downscale)
    return Frame(image, cam, (x0, y0, wc, hc), downscale, (w, h), *depth)


def _centred_window(c: float, size: int, f: int, most: int | None = None) -> tuple[int, int]:
    """``(start, length)``: the widest pixel window centred on ``c`` (to half a pixel), length a multiple
    of ``f`` and at most ``most``."""
    centre = int(round(c * 2)) / 2  # centres fall on pixel edges or centres only
    half = min(centre, size - centre)
    length = min(int(2 * half), most or size) // f * f
    start = int(round(centre - length / 2))
    return max(start, 0), length


def _focal_from_angle(keys: dict, name: str, size: int, where: str) -> float:
    """Focal length in pixels from a field-of-view key (radians) across ``size`` pixels."""
    angle = float(keys[name])
    if not 0 < angle < math.pi:
        raise UserError(f"{where}: {name} must be in (0, pi) radians, got {keys[name]}")
    return 0.5 * size / math.tan(0.5 * angle)


def _intrinsics(keys: dict, w: int, h: int, where: str):
    """``(fx, fy, cx, cy)`` in full-resolution pixels; UserError for what a centred pinhole cannot model."""
    for name in ("fl_x", "fl_y", "cx", "cy", "camera_angle_x", "camera_angle_y"):
        value = keys[name]
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise UserError(f"{where}: {name} must be a number, got {value!r}")
    model = keys["camera_model"]
    if model is not None and str(model).upper() not in PINHOLE_MODELS:
        raise UserError(f"{where}: camera_model {model} is not supported; only pinhole cameras are")
    bent = {k: keys[k] for k in DISTORTION_KEYS if keys[k] not in (None, 0, 0.0)}
    if bent:
        raise UserError(f"{where}: lens distortion ({', '.join(bent)}) is not supported; "
                        "undistort the images first")
    if keys["fl_x"] is not None:
        fx = float(keys["fl_x"])
    elif keys["camera_angle_x"] is not None:
        fx = _focal_from_angle(keys, "camera_angle_x", w, where)
    else:
        raise UserError(f"{where}: no focal length (needs camera_angle_x or fl_x)")
    if keys["fl_y"] is not None:
        fy = float(keys["fl_y"])
    elif keys["camera_angle_y"] is not None and keys["fl_x"] is None:
        fy = _focal_from_angle(keys, "camera_angle_y", h, where)
    else:
        fy = fx
    if not (fx > 0 and fy > 0 and math.isfinite(fx) and math.isfinite(fy)):
        raise UserError(f"{where}: focal length must be positive, got fl_x={fx}, fl_y={fy}")
    if abs(fx - fy) > SQUARE_PIXEL_TOL * fx:
        raise UserError(f"{where}: non-square pixels (fl_x={fx:.6g}, fl_y={fy:.6g}) are not supported")
    cx = float(keys["cx"]) if keys["cx"] is not None else 0.5 * w
    cy = float(keys["cy"]) if keys["cy"] is not None else 0.5 * h
    if not (0 < cx < w and 0 < cy < h):
        raise UserError(f"{where}: principal point ({cx}, {cy}) lies outside the {w}x{h} image")
    return fx, fy, cx, cy


def _subsample(frames: list, n: int | None) -> list:
    """At most ``n`` frames, evenly spaced over the list (all when ``n`` is None)."""
    if n is None or n >= len(frames):
        return frames
    if n <= 0:
        return []
    idx = np.unique(np.round(np.linspace(0, len(frames) - 1, int(n))).astype(int))
    return [frames[i] for i in idx]


# ---------------------------------------------------------------------------
# Scene bounds
# ---------------------------------------------------------------------------

def _bounds_from_keys(metas):
    """``(min, max)`` from an ``aabb`` or ``scene_box`` key ([[x,y,z],[x,y,z]]), else None."""
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
    return None


def estimate_bounds(cameras, margin: float = BOUNDS_MARGIN):
    """Object-centred box ``(min, max)`` seen by inward-looking cameras.

    The centre is the point closest (least squares) to all optical axes; the
    half size is ``margin`` times the median over cameras of
    ``distance to centre * sin(half the narrower fov)``, the radius of a
    sphere that just fills each view. When the axes do not converge in
    front of the cameras (forward-facing captures), the box of the camera
    positions grown by its own size is returned instead.
    """
    pos = np.stack([c.position for c in cameras])
    fwd = np.stack([c.forward for c in cameras])
    proj = np.eye(3)[None] - fwd[:, :, None] * fwd[:, None, :]  # (N,3,3) projections off each axis
    a, b = proj.sum(0), np.einsum("nij,nj->i", proj, pos)
    centre = None
    if np.linalg.cond(a) < 1e6:
        centre = np.linalg.solve(a, b)
        if np.median(np.einsum("ni,ni->n", centre - pos, fwd)) <= 0:
            centre = None  # behind the cameras
    if centre is None:
        lo, hi = pos.min(0), pos.max(0)
        pad = np.maximum(hi - lo, 1.0).max()
        return lo - pad, hi + pad
    tan_x = np.array([math.tan(math.radians(c.fov) / 2) for c in cameras])
    aspect = np.array([c.height / c.width for c in cameras])
    half_fov = np.arctan(tan_x * np.minimum(aspect, 1.0))  # half the narrower field of view
    radius = margin * float(np.median(np.linalg.norm(pos - centre, axis=1) * np.sin(half_fov)))
    return centre - radius, centre + radius


# ---------------------------------------------------------------------------
# Scenes or datasets, from one path
# ---------------------------------------------------------------------------

def open_source(path, *, rig="auto", n_candidates=100, n_heldout=20, resolution=64, fov=None, spp=64,
                downscale=None, cache_dir=None):
    """A view source for ``path``: a Mitsuba scene ``.xml`` or a dataset (``.json`` or folder).

    Scenes give :meth:`SceneSource.from_xml(...) <mitsuba_active.env.SceneSource.from_xml>`;
    datasets give :meth:`DatasetSource.from_path`, keeping at most
    ``n_candidates`` / ``n_heldout`` frames (evenly spaced) and shrinking
    images by ``downscale`` (``None``: ``max(1, round(width / resolution))``).
    A dataset's poses and fov are fixed, so ``rig`` must be ``"auto"`` and
    ``fov`` None; ``spp`` and ``cache_dir`` only concern scenes.
    """
    from .env import SceneSource

    p = Path(path)
    if not p.exists():
        raise UserError(f"no such scene or dataset: {p}")
    if p.is_file() and p.suffix.lower() == ".xml":
        return SceneSource.from_xml(p, rig=rig, n_candidates=n_candidates, n_heldout=n_heldout,
                                    resolution=resolution, fov=fov, spp=spp, cache_dir=cache_dir)
    if p.is_dir() or p.suffix.lower() == ".json":
        if rig != "auto":
            raise UserError(f"{p}: a dataset's cameras are fixed; the rig option ('{rig}') does not apply")
        if fov is not None:
            raise UserError(f"{p}: a dataset's field of view is fixed; the fov option does not apply")
        return DatasetSource.from_path(p, downscale=downscale, n_heldout=n_heldout,
                                       n_candidates=n_candidates, resolution=resolution)
    raise UserError(f"{p}: expected a Mitsuba scene (.xml), a transforms .json, or a dataset folder "
                    "(for a mesh, 'mitsuba-active plan' and 'mitsuba-active scene' author a scene around it)")
