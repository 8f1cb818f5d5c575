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
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .cameras import Camera, camera_rays
from .checks import is_number, is_whole
from .colmap import (HOLDOUT_EVERY, MODEL_FILES, SPARSE, frames_from_reconstruction, heldout_indices,
                     is_colmap_project, points_bounds, read_model)
from .errors import UserError
from .field.config import CAPTURE_SKY_RESOLUTION, MAX_CONTRACTION
from .groundtruth import View, default_cache_dir
from .images import crop, image_size, read_depth, read_linear_rgb
from .imageio_utils import linear_to_srgb
from .lens import Lens, lens_from_keys
from .sources import SceneSource
from .transforms import (TRANSFORMS_FILES, aabb_scale_from_keys, bounds_from_keys, locate_files,  # noqa: F401
                         mitsuba_to_opengl, opengl_to_mitsuba, parse_frame, read_transforms, split_frames)
from .viewcache import cached

#: Relative difference of fl_x and fl_y accepted as square pixels (larger ones make a lens camera).
SQUARE_PIXEL_TOL = 1e-3
#: Margin of the estimated object box over the radius that fills the views.
BOUNDS_MARGIN = 1.1
#: How far (in half box sizes) the fields reach for a capture whose
#: background is neither plain nor transparent and that gives no ``aabb_scale``.
FAR_CONTRACTION = 32.0
#: A backdrop counts as plain (a white or black studio, a composited image)
#: where this fraction of the first view's border pixels lie within
#: ``PLAIN_TOLERANCE`` of white or of black.
PLAIN_FRACTION, PLAIN_TOLERANCE = 0.9, 0.03


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
        lens: the full-resolution image's lens when the camera follows one
            (distortion, or ``fl_y`` unlike ``fl_x``; the camera holds it
            cropped and downscaled), else None.
    """

    image: Path
    camera: Camera
    crop: tuple
    downscale: int
    full_size: tuple
    depth: Path | None = None
    depth_scale: float = 1.0
    depth_is_distance: bool = False
    lens: Lens | None = None


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
        cache_dir: folder where large images' views are kept once loaded
            (:mod:`~mitsuba_active.viewcache`), or None.
        aabb_scale: instant-ngp's ``aabb_scale`` of the capture, or None.
    """

    def __init__(self, candidate_frames, heldout_frames, bbox_min, bbox_max, name="dataset",
                 white_background=True, root=None, cache_dir=None, aabb_scale=None):
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
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self.aabb_scale = None if aabb_scale is None else float(aabb_scale)

    def field_options(self, config=None, planner: bool = False) -> dict:
        """:class:`~mitsuba_active.field.FieldConfig` options the capture needs (over any ``config``,
        for either field):
        where its background lies beyond its box (:meth:`suggested_contraction` is not 0), a
        directional background (``background_resolution``), which lets the volume around the object
        stay empty; else none. The contraction itself is not chosen: from 20 views it filled the
        space before the cameras (``benchmarks/unbounded_quality.py``)."""
        return {"background_resolution": CAPTURE_SKY_RESOLUTION} if self.suggested_contraction() else {}

    def suggested_contraction(self) -> float:
        """The ``contraction`` a capture whose background lies beyond its box would take: its
        ``aabb_scale`` where over 1, else :data:`FAR_CONTRACTION` where its first view's backdrop is
        neither transparent nor plain (:func:`plain_backdrop`); else 0 (the box alone)."""
        if self.aabb_scale is not None and self.aabb_scale > 1:
            return float(min(self.aabb_scale, MAX_CONTRACTION))
        view = self.candidate_view(0)
        if view.background is not None or plain_backdrop(view.rgb):
            return 0.0
        return float(FAR_CONTRACTION)

    @property
    def has_distance(self) -> bool:
        """True when the candidate frames come with depth maps (else views' distances are all 0)."""
        return any(f.depth is not None for f in self.candidate_frames)

    @classmethod
    def from_path(cls, path, downscale: int | None = 1, n_heldout: int | None = None,
                  white_background: bool = True, n_candidates: int | None = None,
                  resolution: int = 64, cache_dir=False) -> "DatasetSource":
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
            cache_dir: where large images' loaded views are kept (``None``:
                :func:`~mitsuba_active.groundtruth.default_cache_dir`; ``False``: nowhere).
        """
        files, name, root = locate_files(path)
        metas = [(f, read_transforms(f)) for f in files]
        train, test = split_frames(metas, files)
        if not train and not test:
            raise UserError(f"{files[0]}: the dataset has no frames")
        # Parse everything first (errors name the frame), then drop missing images.
        train = [parse_frame(*t) for t in train]
        test = [parse_frame(*t) for t in test]
        src = cls.from_parsed(train, test, bounds_from_keys(metas), name, root, downscale=downscale,
                              n_heldout=n_heldout, white_background=white_background, n_candidates=n_candidates,
                              resolution=resolution, cache_dir=cache_dir, where=files[0],
                              aabb_scale=aabb_scale_from_keys(metas))
        # What the frames are (poses, image and depth file names), wherever
        # the dataset lies and whichever of its names it was opened by.
        digest = hashlib.sha256()
        for f in files:
            digest.update(f.read_bytes())
        src.content_hash = digest.hexdigest()
        return src

    @classmethod
    def from_parsed(cls, train, test, bounds, name, root, *, downscale=1, n_heldout=None, white_background=True,
                    n_candidates=None, resolution=64, cache_dir=False, where=None, aabb_scale=None) -> "DatasetSource":
        """A source of parsed frames ``(image, to_world (Mitsuba), camera keys, (depth map, scale, is
        distance), where)`` as :meth:`from_path` reads them (``bounds``: ``(min, max)`` or None:
        estimated); the options are :meth:`from_path`'s, ``where`` names the dataset in messages,
        ``aabb_scale`` is the capture's (or None)."""
        for key, count in (("n_candidates", n_candidates), ("n_heldout", n_heldout)):
            if count is not None and (not is_whole(count) or count < 0):
                raise UserError(f"{key} must be a whole number >= 0 (or None: all frames), got {count!r}")
        if n_candidates == 0:
            raise UserError("at least one candidate view is needed, got n_candidates=0")
        if downscale is None and (not is_whole(resolution) or resolution < 1):
            raise UserError(f"image resolution must be a positive whole number, got {resolution!r}")
        where = where or root
        missing = [t[0] for t in train + test if not t[0].is_file()]
        n_frames = len(train) + len(test)
        train = [t for t in train if t[0].is_file()]
        test = [t for t in test if t[0].is_file()]
        # Refused before the warning about skipped frames: one line says it all.
        if not train and not test:
            raise UserError(f"{where}: none of the dataset's image files exist (e.g. {missing[0]})")
        if not train:
            raise UserError(f"{root}: no training frame has an image file")
        if missing:
            warnings.warn(f"{name}: skipped {len(missing)} of {n_frames} frames whose image "
                          f"file is missing (e.g. {missing[0]})", stacklevel=3)

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
        cache = None if cache_dir is False else Path(cache_dir or default_cache_dir())
        return cls(train, test, bounds[0], bounds[1], name=name, white_background=white_background, root=root,
                   cache_dir=cache, aabb_scale=aabb_scale)

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
            def load():
                v = load_view(frame, self.white_background)
                return {"rgb": v.rgb, "distance": v.distance, "empty": v.known_empty,
                        "alpha": np.array(v.background is not None)}

            a = cached(self.cache_dir, frame, self.white_background, load)
            background = (None if not a["alpha"] else (1.0,) * 3 if self.white_background else (0.0,) * 3)
            self._views[key] = View(a["rgb"], a["distance"], a["distance"] > 0, frame.camera, a["empty"], background)
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
    cam, f, lens = frame.camera, frame.downscale, frame.lens
    rgb, alpha = read_linear_rgb(frame.image, white_background, frame.full_size)
    if rgb.shape[1::-1] != tuple(frame.full_size):
        w, h = frame.full_size
        raise UserError(f"{frame.image} is {rgb.shape[1]}x{rgb.shape[0]} pixels, the dataset says {w}x{h}")
    # Averaged in linear light, as a camera pixel (and Mitsuba's box filter) does; a lens camera's
    # rays follow the lens through the pixels as captured, so nothing is resampled.
    rgb = linear_to_srgb(area_downscale(crop(rgb, frame.crop, frame.image), f))
    # Known empty: every full-resolution pixel under a downscaled one is transparent.
    empty = (np.zeros(rgb.shape[:2], bool) if alpha is None
             else area_downscale(crop(alpha, frame.crop, frame.image), f) <= 0.0)
    distance = np.zeros((cam.height, cam.width), np.float32)
    if frame.depth is not None:
        entry = "distance_file_path" if frame.depth_is_distance else "depth_file_path"
        depth = read_depth(frame.depth, entry)
        if lens is not None and depth.shape[1::-1] != lens.size:
            raise UserError(f"{frame.depth} is {depth.shape[1]}x{depth.shape[0]} pixels, its image "
                            f"{lens.size[0]}x{lens.size[1]}")
        depth = crop(depth, frame.crop, frame.depth) * frame.depth_scale
        # Depth at the full-resolution pixel nearest each downscaled pixel centre:
        # averaging across a silhouette would invent depths that lie on no surface.
        z = depth[f // 2::f, f // 2::f][: cam.height, : cam.width]
        z = np.where(np.isfinite(z) & (z > 0), z, 0.0)
        distance = (z if frame.depth_is_distance else z * depth_to_distance_factor(cam)).astype(np.float32)
    background = None if alpha is None else (1.0,) * 3 if white_background else (0.0,) * 3
    return View(rgb.astype(np.float32), distance, distance > 0, cam, empty, background)


def plain_backdrop(rgb: np.ndarray) -> bool:
    """Whether an (H, W, 3) image's border is a plain white or black backdrop
    (:data:`PLAIN_FRACTION` of its pixels within :data:`PLAIN_TOLERANCE`)."""
    a = np.asarray(rgb, np.float32)
    border = np.concatenate([a[0], a[-1], a[:, 0], a[:, -1]])
    near = (np.abs(border - 1.0).max(axis=1) <= PLAIN_TOLERANCE) | (border.max(axis=1) <= PLAIN_TOLERANCE)
    return bool(near.mean() >= PLAIN_FRACTION)


def depth_to_distance_factor(camera: Camera) -> np.ndarray:
    """(H, W) factor turning depth along the optical axis into distance along pixel-centre rays."""
    if camera.lens is not None:  # the rays the lens bends: 1 / their cosine to the optical axis
        _, d = camera_rays(camera)
        return (1.0 / (d.astype(np.float64) @ camera.forward)).reshape(camera.height, camera.width)
    k = camera.intrinsics()
    x = (np.arange(camera.width) + 0.5 - k[0, 2]) / k[0, 0]
    y = (np.arange(camera.height) + 0.5 - k[1, 2]) / k[1, 1]
    return np.sqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2)


def area_downscale(img: np.ndarray, f: int) -> np.ndarray:
    """Mean over ``f x f`` blocks; (H, W, ...) -> (H // f, W // f, ...); H, W must be multiples of f."""
    if f == 1:
        return img
    h, w = img.shape[:2]
    if img.dtype == np.float32 and img.ndim in (2, 3) and (img.ndim == 2 or img.shape[2] <= 4):
        # OpenCV's area filter at a whole factor is this mean, an order of magnitude faster on large frames.
        out = cv2.resize(img, (w // f, h // f), interpolation=cv2.INTER_AREA)
        return out.reshape(h // f, w // f, *img.shape[2:])
    return img.reshape(h // f, f, w // f, f, *img.shape[2:]).mean(axis=(1, 3))


# ---------------------------------------------------------------------------
# Frames: cameras and windows
# ---------------------------------------------------------------------------

def _full_size(parsed) -> tuple[int, int]:
    """Full-resolution (width, height) of a parsed frame: the JSON's ``w``/``h``, else the image header."""
    image, _, keys, _, where = parsed
    for name in ("w", "h"):
        value = keys[name]
        if value is not None and not (is_number(value, finite=True) and float(value).is_integer() and value > 0):
            raise UserError(f"{where}: {name} must be a whole number of pixels, got {value!r}")
    if keys["w"] is not None and keys["h"] is not None:
        return int(keys["w"]), int(keys["h"])
    return image_size(image)


def _window(parsed, full_size, downscale: int, size=None) -> tuple:
    """``(x0, y0, width, height)``: the crop window in full-resolution pixels of a
    frame whose image is ``full_size`` (width, height).

    A pinhole camera has its principal point at the image centre: the window
    is the largest one centred on (cx, cy), at most ``size`` (width, height),
    trimmed to multiples of the factor. A lens camera carries its principal
    point: the window is centred on the image's centre."""
    _, _, keys, _, where = parsed
    w, h = full_size
    _, _, cx, cy = _intrinsics(keys, w, h, where)
    if _lens(parsed, full_size) is not None:
        cx, cy = 0.5 * w, 0.5 * h
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
    lens = _lens(parsed, full_size)
    cam = Camera(to_world, fov, wc // downscale, hc // downscale,
                 lens=None if lens is None else lens.cropped(x0, y0, wc, hc, downscale))
    return Frame(image, cam, (x0, y0, wc, hc), downscale, (w, h), *depth, lens=lens)


def _lens(parsed, full_size) -> Lens | None:
    """The frame's :class:`~mitsuba_active.lens.Lens` when its camera must follow one (distortion,
    or non-square pixels), else None (a pinhole)."""
    _, _, keys, _, where = parsed
    fx, fy, cx, cy = _intrinsics(keys, *full_size, where)
    lens = lens_from_keys(keys, fx, fy, cx, cy, full_size, where)
    return lens if lens.distorted or abs(fx - fy) > SQUARE_PIXEL_TOL * fx else None


def _centred_window(c: float, size: int, f: int, most: int | None = None) -> tuple[int, int]:
    """``(start, length)``: the widest pixel window centred on ``c`` (to half a pixel), length a multiple
    of ``f``, at most ``most``."""
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
    """``(fx, fy, cx, cy)`` in full-resolution pixels; UserError for what no camera can be."""
    for name in ("fl_x", "fl_y", "cx", "cy", "camera_angle_x", "camera_angle_y"):
        value = keys[name]
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise UserError(f"{where}: {name} must be a number, got {value!r}")
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


def colmap_source(path, *, n_heldout=None, **options):
    """The :class:`~mitsuba_active.datasets.DatasetSource` of a COLMAP project folder.

    ``n_heldout`` images (evenly spaced over the names; ``None``: every
    8th) are held out; ``options`` are those of
    :meth:`DatasetSource.from_parsed <mitsuba_active.datasets.DatasetSource.from_parsed>`.
    """
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
    rec = read_model(sparse)
    frames, points = frames_from_reconstruction(rec, root / "images", str(sparse))
    if not frames:
        raise UserError(f"{sparse}: the model has no registered images")
    held = set(heldout_indices(len(frames), n_heldout))
    train = [f for i, f in enumerate(frames) if i not in held]
    test = [f for i, f in enumerate(frames) if i in held]
    src = DatasetSource.from_parsed(train, test, points_bounds(points), root.resolve().name, root,
                                    n_heldout=n_heldout, where=sparse, **options)
    digest = hashlib.sha256()
    for f in files:
        digest.update(f.read_bytes())
    src.content_hash = digest.hexdigest()
    return src


# ---------------------------------------------------------------------------
# Scenes or datasets, from one path
# ---------------------------------------------------------------------------

def open_source(path, *, rig="auto", n_candidates=100, n_heldout=20, resolution=64, fov=None, spp=64,
                downscale=None, cache_dir=None):
    """A view source for ``path``: a Mitsuba scene ``.xml`` or a dataset (``.json`` or folder).

    Scenes give :meth:`SceneSource.from_xml(...) <mitsuba_active.env.SceneSource.from_xml>`;
    datasets (a transforms ``.json`` or a folder holding one; a COLMAP project
    folder with ``sparse/0``: :func:`colmap_source`)
    give :meth:`DatasetSource.from_path`, keeping at most
    ``n_candidates`` / ``n_heldout`` frames (evenly spaced) and shrinking
    images by ``downscale`` (``None``: ``max(1, round(width / resolution))``).
    A dataset's poses and fov are fixed, so ``rig`` must be ``"auto"`` and
    ``fov`` None; ``spp`` only concerns scenes, and ``cache_dir`` also keeps
    large images' loaded views.
    """
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
        if p.is_dir() and is_colmap_project(p) and not any((p / n).is_file() for n in TRANSFORMS_FILES):
            return colmap_source(p, downscale=downscale, n_heldout=n_heldout, n_candidates=n_candidates,
                                 resolution=resolution, cache_dir=cache_dir)
        return DatasetSource.from_path(p, downscale=downscale, n_heldout=n_heldout,
                                       n_candidates=n_candidates, resolution=resolution, cache_dir=cache_dir)
    raise UserError(f"{p}: expected a Mitsuba scene (.xml), a transforms .json, or a dataset folder "
                    "(for a mesh, 'mitsuba-active plan' and 'mitsuba-active scene' author a scene around it)")
