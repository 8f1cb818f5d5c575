"""Reading a dataset's image files: colour with alpha, depth maps, orientation and size.

PNG (8 or 16 bits), JPEG (CMYK too) and EXR colour come back as sRGB in
[0, 1] composited on the background, with their alpha; JPEGs are turned
upright by their EXIF orientation (see :func:`read_rgb`). Unreadable files
raise :class:`~mitsuba_active.errors.UserError` naming the file.
"""

from __future__ import annotations

import functools
from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np
from PIL import Image

from .errors import UserError
from .imageio_utils import exr_size, linear_to_srgb, read_exr, srgb_to_linear

#: EXIF orientation (tag 274) -> (transpose first, then rotate by 90 degrees this many times counter-clockwise,
#: then flip left-right): the operations that turn the stored pixels upright.
EXIF_ORIENTATION = 0x0112
_UPRIGHT = {2: (False, 0, True), 3: (False, 2, False), 4: (False, 2, True), 5: (True, 0, False),
            6: (False, 3, False), 7: (True, 2, False), 8: (False, 1, False)}


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


def read_rgb(path: Path, white_background: bool, size=None) -> tuple[np.ndarray, np.ndarray | None]:
    """(H, W, 3) float32 sRGB in [0, 1], alpha composited (in sRGB for PNG and JPEG, the
    nerf-synthetic convention; in linear light for EXR); and the (H, W) float32 alpha in
    [0, 1], or None for an image without one.

    An image with an EXIF orientation is turned upright, unless ``size``
    (width, height: what the dataset says) is the stored pixels' size and
    not the upright one (the poses were then found on the stored pixels)."""
    if path.suffix.lower() == ".exr":
        rgb, alpha = _exr_colour(path, white_background)
        alpha = None if alpha is None else np.clip(alpha, 0.0, 1.0).astype(np.float32)
        return np.clip(rgb, 0.0, 1.0).astype(np.float32), alpha
    return _composited(_pixels(path, size), white_background)


def read_linear_rgb(path: Path, white_background: bool, size=None) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`read_rgb`'s colour in linear light (float32) and its alpha. An 8- or
    16-bit image without alpha (a photograph) is converted through a table of
    its 256 or 65,536 levels: the same values, several times faster than the
    transfer function on every pixel of a phone-sized frame."""
    if path.suffix.lower() == ".exr":
        rgb, alpha = read_rgb(path, white_background, size)
        return srgb_to_linear(rgb), alpha
    img = _pixels(path, size)
    if img.dtype in (np.uint8, np.uint16) and (img.ndim == 2 or img.shape[-1] in (1, 3)):
        lin = _linear_levels(img.dtype)[img]
        lin = lin.reshape(*img.shape[:2], -1)
        return (np.repeat(lin, 3, axis=-1) if lin.shape[-1] == 1 else lin), None
    rgb, alpha = _composited(img, white_background)
    return srgb_to_linear(rgb), alpha


@functools.cache
def _linear_levels(dtype) -> np.ndarray:
    """(levels,) float32: the linear light of every level of an unsigned ``dtype``, as
    :func:`read_rgb` then :func:`~mitsuba_active.imageio_utils.srgb_to_linear` give it."""
    top = np.iinfo(dtype).max
    return srgb_to_linear(np.arange(top + 1, dtype=np.float32) / np.float32(top))


def _pixels(path: Path, size=None) -> np.ndarray:
    """The stored pixels of a PNG or JPEG (H, W[, C]), turned upright by their EXIF
    orientation unless ``size`` (width, height) is the stored pixels' size and not the upright one."""
    raw, orientation = _read_pixels(path)
    img = _upright(raw, orientation)
    if size is not None and img.shape[1::-1] != tuple(size) and raw.shape[1::-1] == tuple(size):
        img = raw
    return img


def _composited(img: np.ndarray, white_background: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """Stored pixels (H, W[, C]) as (H, W, 3) float32 sRGB in [0, 1], alpha composited, and the alpha or None."""
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(img.dtype, 1.0)
    img = img.astype(np.float32) / scale
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


def _read_pixels(path: Path) -> tuple[np.ndarray, int]:
    """The stored pixels (H, W[, C]) uint8 or uint16, RGB(A) order, and the EXIF orientation (1: upright)."""
    try:
        with Image.open(path) as im:
            cmyk = im.mode == "CMYK"  # 4 channels that are no alpha: as RGB
            orientation = int(im.getexif().get(EXIF_ORIENTATION, 1) or 1)
        if _png_bit_depth(path) == 16:  # Pillow reads 16-bit colour PNGs as 8-bit

            raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if raw is None:
                raise ValueError("OpenCV cannot decode it")
            if raw.ndim == 3:
                raw = raw[..., [2, 1, 0, 3][: raw.shape[-1]]] if raw.shape[-1] == 4 else raw[..., ::-1]
        else:
            raw = iio.imread(path, mode="RGB") if cmyk else iio.imread(path)
    except Exception as exc:  # noqa: BLE001 (image readers raise many kinds)
        raise UserError(f"cannot read image {path}: {exc}") from None
    return np.ascontiguousarray(raw), orientation


def _upright(img: np.ndarray, orientation: int) -> np.ndarray:
    """``img`` (H, W[, C]) turned upright by its EXIF ``orientation``."""
    if orientation not in _UPRIGHT:
        return img
    transpose, turns, flip = _UPRIGHT[orientation]
    if transpose:
        img = np.swapaxes(img, 0, 1)
    img = np.rot90(img, turns)
    return np.ascontiguousarray(img[:, ::-1] if flip else img)


def image_size(path: Path, upright: bool = True) -> tuple[int, int]:
    """(width, height) of an image file, from its header; ``upright``: as its EXIF orientation shows it."""
    if path.suffix.lower() == ".exr":
        try:
            return exr_size(path)
        except ValueError as exc:
            raise UserError(f"cannot read image {path}: {exc}") from None

    try:
        with Image.open(path) as im:
            w, h = im.size
            orientation = int(im.getexif().get(EXIF_ORIENTATION, 1) or 1)
    except Exception as exc:  # noqa: BLE001
        raise UserError(f"cannot read image {path}: {exc}") from None
    return (h, w) if upright and orientation in (5, 6, 7, 8) else (w, h)


def read_depth(path: Path, entry: str) -> np.ndarray:
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


def crop(img: np.ndarray, window, path) -> np.ndarray:
    """``img`` cut to ``window`` = (x0, y0, width, height); UserError when it is smaller."""
    x0, y0, w, h = window
    if img.shape[0] < y0 + h or img.shape[1] < x0 + w:
        raise UserError(f"{path} is {img.shape[1]}x{img.shape[0]} pixels, smaller than the dataset says")
    return img[y0:y0 + h, x0:x0 + w]
