"""Lens distortion of captured images: the rays through their pixels (OpenCV camera models).

Real captures (phones, COLMAP, nerfstudio's ``ns-process-data``) come with
a distortion model. :class:`Lens` holds one frame's intrinsics and model;
:func:`pixel_rays` gives the ray through every pixel centre of the image as
captured (the inverse of :func:`distort`, per pixel), which a dataset's
cameras train and score along. Resampling the images to a pinhole instead
crops the periphery the lens sees (``benchmarks/distortion_quality.py``
measures both routes).

Models, on normalised image coordinates ``(x, y)``, ``r^2 = x^2 + y^2``:

* ``OPENCV`` (radial-tangential, as nerfstudio and instant-ngp apply it):
  ``x' = x d + 2 p1 x y + p2 (r^2 + 2 x^2)``, ``y' = y d + p1 (r^2 + 2 y^2) + 2 p2 x y``
  with ``d = 1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8``;
* ``OPENCV_FISHEYE`` (equidistant): ``theta = atan r``,
  ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``,
  ``(x', y') = (x, y) theta_d / r``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from .errors import UserError

#: Radial-tangential and fisheye model names, as transforms.json and COLMAP spell them.
RADTAN, FISHEYE = "OPENCV", "OPENCV_FISHEYE"
#: ``camera_model`` values of a transforms.json, and the model each one means.
TRANSFORMS_MODELS = {"PINHOLE": RADTAN, "SIMPLE_PINHOLE": RADTAN, "OPENCV": RADTAN, "FULL_OPENCV": RADTAN,
                     "OPENCV_FISHEYE": FISHEYE, "FISHEYE": FISHEYE, "EQUIRECTANGULAR": None}
#: Coefficient names, in the order :attr:`Lens.coeffs` holds them.
COEFF_NAMES = ("k1", "k2", "k3", "k4", "p1", "p2")
#: Radius steps searched for where the radial model stops growing.
FOLD_SAMPLES = 4096
#: Newton steps of the inverse distortion, and the round trip (pixels) a pixel's ray must meet.
INVERSE_STEPS, INVERSE_TOL_PX = 50, 1e-3


@dataclass(frozen=True)
class Lens:
    """One frame's intrinsics and distortion, at the image file's resolution.

    Attributes:
        model: :data:`RADTAN` or :data:`FISHEYE`.
        fx, fy, cx, cy: focal lengths and principal point in pixels.
        coeffs: ``(k1, k2, k3, k4, p1, p2)`` (p1, p2 are 0 for the fisheye).
        size: ``(width, height)`` of the image in pixels.
    """

    model: str
    fx: float
    fy: float
    cx: float
    cy: float
    coeffs: tuple
    size: tuple

    @property
    def distorted(self) -> bool:
        """True when the model bends rays (any coefficient non-zero, or a fisheye)."""
        return self.model == FISHEYE or any(c != 0.0 for c in self.coeffs)

    def to_keys(self) -> dict:
        """The lens as transforms.json keys (``camera_model`` and the coefficients)."""
        return {"camera_model": self.model, **dict(zip(COEFF_NAMES, self.coeffs))}

    def cropped(self, x0: int, y0: int, width: int, height: int, downscale: int = 1) -> "Lens":
        """The lens of the window ``(x0, y0, width, height)`` of the image, shrunk ``downscale`` times
        (its pixel ``(i, j)`` covers the window's ``downscale`` x ``downscale`` block ``(i, j)``)."""
        f = float(downscale)
        return Lens(self.model, self.fx / f, self.fy / f, (self.cx - x0) / f, (self.cy - y0) / f, self.coeffs,
                    (int(width) // int(downscale), int(height) // int(downscale)))

    def scaled(self, width: int, height: int) -> "Lens":
        """The lens of the image resized to ``width`` x ``height`` pixels."""
        sx, sy = width / self.size[0], height / self.size[1]
        return Lens(self.model, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, self.coeffs,
                    (int(width), int(height)))


def lens_to_dict(lens: Lens) -> dict:
    """The lens as JSON-ready values (:func:`lens_from_dict` reads them back)."""
    return {"model": lens.model, "fx": lens.fx, "fy": lens.fy, "cx": lens.cx, "cy": lens.cy,
            "coeffs": list(lens.coeffs), "size": list(lens.size)}


def lens_from_dict(d) -> Lens:
    """The :class:`Lens` :func:`lens_to_dict` wrote; UserError when ``d`` is not one."""
    try:
        lens = Lens(str(d["model"]), *(float(d[k]) for k in ("fx", "fy", "cx", "cy")),
                    tuple(float(c) for c in d["coeffs"]), tuple(int(s) for s in d["size"]))
    except (TypeError, ValueError, KeyError):
        raise UserError("a camera's lens is a table with model, fx, fy, cx, cy, coeffs and size") from None
    numbers = (lens.fx, lens.fy, lens.cx, lens.cy) + lens.coeffs
    if (lens.model not in (RADTAN, FISHEYE) or len(lens.coeffs) != len(COEFF_NAMES) or len(lens.size) != 2
            or not all(math.isfinite(v) for v in numbers) or min(lens.fx, lens.fy, *lens.size) <= 0):
        raise UserError(f"a camera's lens must have model {RADTAN} or {FISHEYE}, positive finite focal lengths, "
                        f"{len(COEFF_NAMES)} finite coefficients and a positive size, got {d!r}")
    return lens


def lens_from_keys(keys: dict, fx: float, fy: float, cx: float, cy: float, size, where: str) -> Lens:
    """The :class:`Lens` of a transforms.json frame's ``camera_model`` and ``k1``..``k4``, ``p1``, ``p2``."""
    name = keys.get("camera_model")
    if name is not None and (not isinstance(name, str) or name.upper() not in TRANSFORMS_MODELS):
        known = ", ".join(m for m, v in TRANSFORMS_MODELS.items() if v)
        raise UserError(f"{where}: camera_model {name!r} is not supported (known: {known})")
    model = TRANSFORMS_MODELS[name.upper()] if name else RADTAN
    if model is None:
        raise UserError(f"{where}: camera_model {name} (a panorama) is not supported; only perspective and "
                        "fisheye cameras are")
    coeffs = []
    for key in COEFF_NAMES:
        value = keys.get(key)
        if value is None:
            value = 0.0
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise UserError(f"{where}: {key} must be a number, got {value!r}")
        coeffs.append(float(value))
    if model == FISHEYE and (coeffs[4] or coeffs[5]):
        raise UserError(f"{where}: a fisheye lens ({name}) has no tangential terms; p1 and p2 must be 0")
    return Lens(model, float(fx), float(fy), float(cx), float(cy), tuple(coeffs), tuple(int(s) for s in size))


def distort(lens: Lens, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distorted normalised coordinates of undistorted ones (float64 arrays of one shape)."""
    k1, k2, k3, k4, p1, p2 = lens.coeffs
    r2 = x * x + y * y
    if lens.model == FISHEYE:
        r = np.sqrt(r2)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
        return x * scale, y * scale
    d = 1 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    return (x * d + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * d + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


def undistort(lens: Lens, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates of distorted ones (float64 arrays of one shape), and a bool
    array of those found: Newton's method (:data:`INVERSE_STEPS`) whose :func:`distort` round trip
    lands within :data:`INVERSE_TOL_PX` pixels, before the model folds back (and, for a fisheye, in
    front of the camera). Points not found get their distorted coordinates, finite."""
    k1, k2, k3, k4, p1, p2 = lens.coeffs
    with np.errstate(all="ignore"):
        if lens.model == FISHEYE:  # radial: solve theta_d(theta) = |(xd, yd)|
            rd = np.hypot(xd, yd)
            theta = np.minimum(rd, 1.5)
            for _ in range(INVERSE_STEPS):
                t2 = theta * theta
                g = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - rd
                dg = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
                theta = np.clip(theta - g / dg, 0.0, math.pi / 2)
            scale = np.where(rd > 1e-12, np.tan(theta) / np.maximum(rd, 1e-12), 1.0)
            x, y = xd * scale, yd * scale
            found = theta < math.pi / 2 - 1e-6
        else:
            x, y = xd.copy(), yd.copy()
            for _ in range(INVERSE_STEPS):
                r2 = x * x + y * y
                d = 1 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
                dp = k1 + r2 * (2 * k2 + r2 * (3 * k3 + r2 * 4 * k4))  # d(d)/d(r^2)
                fx, fy = distort(lens, x, y)
                ex, ey = fx - xd, fy - yd
                a = d + 2 * x * x * dp + 2 * p1 * y + 6 * p2 * x
                b = 2 * x * y * dp + 2 * p1 * x + 2 * p2 * y
                c = d + 2 * y * y * dp + 6 * p1 * y + 2 * p2 * x
                det = a * c - b * b
                x, y = x - (c * ex - b * ey) / det, y - (a * ey - b * ex) / det
            found = np.ones(x.shape, bool)
        bx, by = distort(lens, x, y)
        miss = np.hypot((bx - xd) * lens.fx, (by - yd) * lens.fy)
        found &= np.isfinite(x) & np.isfinite(y) & (miss < INVERSE_TOL_PX)
        r = np.hypot(x, y)
        if found.any():  # the other preimage of a folding model shows what lies elsewhere
            found &= r < fold_radius(lens, float(r[found].max()) * 1.01)
    return np.where(found, x, xd), np.where(found, y, yd), found


@lru_cache(maxsize=2)  # frames share a lens; a 4096x4096 image's rays take 400 MB
def pixel_rays(lens: Lens) -> tuple[np.ndarray, np.ndarray]:
    """The rays through the pixel centres of an image of ``lens``, row-major: ``(local, valid)``,
    (H*W, 3) float64 directions ``(x, y, 1)`` in OpenCV's camera frame (x right, y down, z forward;
    not unit length) and (H*W,) bool, the pixels whose ray :func:`undistort` finds. Read-only."""
    w, h = lens.size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64) + 0.5, np.arange(h, dtype=np.float64) + 0.5)
    xd, yd = ((u - lens.cx) / lens.fx).ravel(), ((v - lens.cy) / lens.fy).ravel()
    if lens.distorted:
        x, y, valid = undistort(lens, xd, yd)
    else:
        x, y, valid = xd, yd, np.ones(xd.shape, bool)
    local = np.stack([x, y, np.ones_like(x)], axis=1)
    local.flags.writeable = valid.flags.writeable = False
    return local, valid


def fold_radius(lens: Lens, r_max: float) -> float:
    """The undistorted radius (normalised) up to which the radial model keeps growing, at most ``r_max``:
    beyond it, points fold back onto the image and would show what lies elsewhere."""
    r = np.linspace(0.0, r_max, FOLD_SAMPLES)
    rd, _ = distort(Lens(lens.model, 1, 1, 0, 0, lens.coeffs[:4] + (0.0, 0.0), lens.size), r, np.zeros_like(r))
    falling = np.nonzero(np.diff(rd) <= 0)[0]
    return float(r[falling[0]]) if falling.size else math.inf


def capture_through(img: np.ndarray, f: float, model: str, coeffs: dict) -> np.ndarray:
    """(H, W, C) float ``img`` of a pinhole camera (focal ``f`` pixels, principal point at the
    centre) as a lens with ``coeffs`` (OpenCV's own model and functions, ``model`` ``OPENCV`` or
    ``OPENCV_FISHEYE``) would have captured it: to make distorted captures with a known lens."""
    if not coeffs:
        return img
    h, w = img.shape[:2]
    k = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pts = np.stack([u, v], -1).reshape(-1, 1, 2)
    if model == FISHEYE:
        und = cv2.fisheye.undistortPoints(pts, k, np.array([coeffs.get(c, 0.0) for c in ("k1", "k2", "k3", "k4")]))
    else:
        d = np.array([coeffs.get(c, 0.0) for c in ("k1", "k2", "p1", "p2", "k3")])
        und = cv2.undistortPoints(pts, k, d, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    und = und.reshape(h, w, 2)
    mx = (und[..., 0] * f + w / 2 - 0.5).astype(np.float32)
    my = (und[..., 1] * f + h / 2 - 0.5).astype(np.float32)
    return cv2.remap(img.astype(np.float32), mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
