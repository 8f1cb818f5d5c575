"""Image and geometry metrics, and the robust statistics used in reports.

All image inputs are float arrays in [0, 1] of shape (H, W, 3); distances
are (H, W) in scene units with a boolean hit mask.
"""

from __future__ import annotations

import numbers

import numpy as np

#: Decimals that CSV files print each figure with (dB, SSIM, percent, seconds, scene units):
#: runs under one seed agree to about 1e-6, and more digits would differ between them.
DECIMALS = {"psnr": 4, "psnr_fg": 4, "ssim": 4, "distance_error": 4, "floor_psnr": 4, "floor_psnr_fg": 4,
            "fit_psnr": 4, "fit_start_psnr": 4, "eval_seconds": 3, "travel_distance": 4, "mission_time": 3}


def fixed(value, decimals: int | None):
    """A number with ``decimals`` decimals, as text; anything else (None, a count without decimals) as it is."""
    if decimals is None or isinstance(value, bool) or not isinstance(value, numbers.Real):
        return value
    return f"{value:.{decimals}f}"


def _same_shape(pred, target) -> tuple[np.ndarray, np.ndarray]:
    """Both as float64; ValueError for different shapes, which numpy would broadcast into a wrong score."""
    a, b = np.asarray(pred, np.float64), np.asarray(target, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"prediction and target differ in shape: {a.shape} and {b.shape}")
    return a, b


def psnr(pred: np.ndarray, target: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1] of one shape."""
    a, b = _same_shape(pred, target)
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def foreground_radius(width: int) -> int:
    """Pixels by which :func:`foreground_psnr` dilates the foreground of an image ``width`` pixels across.

    A 64th of the width, at least one pixel: the band around a silhouette
    covers the same part of the view at any resolution.
    """
    return max(1, round(width / 64))


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """(H, W) bool ``mask`` grown by ``radius`` pixels in every direction (a square window)."""
    m = np.asarray(mask, bool)
    if m.ndim != 2:
        raise ValueError(f"dilate: a mask is (H, W), got shape {m.shape}")
    if isinstance(radius, bool) or not isinstance(radius, numbers.Integral) or radius < 0:
        raise ValueError(f"dilate: the radius must be a whole number >= 0, got {radius!r}")
    for axis in (0, 1):  # a square window is a row window after a column window
        n = m.shape[axis]
        padded = np.pad(m, [(radius, radius) if a == axis else (0, 0) for a in range(2)])
        grown = np.zeros_like(m)
        for k in range(2 * radius + 1):
            grown |= np.take(padded, np.arange(k, k + n), axis=axis)
        m = grown
    return m


def masked_psnr(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float:
    """PSNR in dB over the pixels of the (H, W) bool ``mask`` of (H, W, 3) images in [0, 1] (NaN if none)."""
    a, b = _same_shape(pred, target)
    m = np.asarray(mask, bool)
    if m.shape != a.shape[:2]:
        raise ValueError(f"the mask is {m.shape}, the images {a.shape[:2]}")
    if not m.any():
        return float("nan")
    mse = float(np.mean((a[m] - b[m]) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def foreground_psnr(pred: np.ndarray, target: np.ndarray, foreground: np.ndarray) -> float:
    """PSNR in dB over the pixels that see geometry in the ground truth (``foreground``, (H, W) bool),
    dilated by :func:`foreground_radius`, so that geometry missing or added at the edges counts
    while the background far from it does not (NaN if no pixel sees geometry)."""
    fg = np.asarray(foreground, bool)
    if fg.ndim != 2:
        raise ValueError(f"the foreground is (H, W), got shape {fg.shape}")
    return masked_psnr(pred, target, dilate(fg, foreground_radius(fg.shape[1])))


def _gaussian_blur(img: np.ndarray, sigma=1.5, radius=5) -> np.ndarray:
    """Separable Gaussian filter over the first two axes, 'valid' region only."""
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    k /= k.sum()
    out = np.apply_along_axis(lambda r: np.convolve(r, k, mode="valid"), 0, img)
    return np.apply_along_axis(lambda r: np.convolve(r, k, mode="valid"), 1, out)


def ssim(pred: np.ndarray, target: np.ndarray) -> float:
    """Structural similarity (Wang et al. 2004): 11x11 Gaussian window, sigma 1.5, mean over channels."""
    a, b = _same_shape(pred, target)
    if min(a.shape[:2]) < 11:
        raise ValueError("SSIM needs images of at least 11x11 pixels")
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    mu_a, mu_b = _gaussian_blur(a), _gaussian_blur(b)
    var_a = _gaussian_blur(a * a) - mu_a ** 2
    var_b = _gaussian_blur(b * b) - mu_b ** 2
    cov = _gaussian_blur(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    return float(np.mean(s))


def distance_error(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float:
    """Mean relative distance error in percent over pixels that hit geometry (NaN if none)."""
    pred, target = _same_shape(pred, target)
    m = np.asarray(mask, bool) & (target > 0)
    if not m.any():
        return float("nan")
    return float(100.0 * np.mean(np.abs(pred[m] - target[m]) / target[m]))


def iqm(values) -> float:
    """Interquartile mean: the mean of the middle 50% of the sorted values.

    With n values, a quarter (n/4, fractional at the edges) is cut at each
    end and the remaining weight averaged: Agarwal et al.'s (2021) statistic,
    with fractional weights where n is not a multiple of 4 (their rliable
    library cuts whole values, ``scipy.stats.trim_mean(x, 0.25)``: for 5
    seeds it averages the middle 3 equally, where this weighs them 3/4, 1, 3/4).
    Two values give their mean; three weigh the middle one 4 times the others.
    """
    x = np.sort(np.asarray(values, dtype=np.float64).ravel())
    n = len(x)
    if n == 0:
        return float("nan")
    # Each sample covers [i, i+1) of [0, n); keep the part inside [n/4, 3n/4].
    lo, hi = n / 4.0, 3.0 * n / 4.0
    i = np.arange(n)
    w = np.clip(np.minimum(i + 1, hi) - np.maximum(i, lo), 0.0, 1.0)
    return float(np.sum(w * x) / np.sum(w))


def standard_error(values) -> float:
    """Standard error of the mean, std (ddof=1) / sqrt(n); 0 for a single value."""
    x = np.asarray(values, dtype=np.float64).ravel()
    return 0.0 if len(x) < 2 else float(np.std(x, ddof=1) / np.sqrt(len(x)))
