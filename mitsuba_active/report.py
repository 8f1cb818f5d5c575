"""Plots and image sheets for runs and benchmarks (matplotlib, Agg backend)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .imageio_utils import atomic_write


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


METRIC_LABELS = {"psnr": "held-out PSNR (dB)", "ssim": "held-out SSIM",
                 "distance_error": "distance error (%)"}


def plot_metrics(series: dict[str, list[dict]], out_dir, title: str = "", bands: dict | None = None) -> list[Path]:
    """One PNG per metric against views captured, a line per planner.

    Args:
        series: planner name -> list of metric records (``views``, ``psnr``, ...).
        out_dir: folder for ``psnr.png``, ``distance_error.png`` and ``ssim.png``.
        bands: optional planner name -> metric -> (lower, upper) arrays to shade.
    """
    plt = _plt()
    written = []
    for metric, label in METRIC_LABELS.items():
        fig, ax = plt.subplots(figsize=(5, 3.5), dpi=110)
        plotted = False
        for name, records in series.items():
            pts = [(r["views"], r[metric]) for r in records if r.get(metric) is not None]
            if not pts:
                continue
            x, y = np.array(pts, dtype=float).T
            ax.plot(x, y, marker="o", label=name)
            band = (bands or {}).get(name, {}).get(metric)
            if band is not None:
                ax.fill_between(x, band[0], band[1], alpha=0.2)
            plotted = True
        if not plotted:
            plt.close(fig)
            continue
        ax.set_xlabel("views captured")
        ax.xaxis.set_major_locator(plt.MaxNLocator(integer=True))
        ax.set_ylabel(label)
        ax.set_title(title)
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        path = Path(out_dir) / f"{metric}.png"
        with atomic_write(path) as tmp:
            fig.savefig(tmp, format="png")
        plt.close(fig)
        written.append(path)
    return written


def contact_sheet(images: list, labels: list[str], path, columns: int = 5) -> Path:
    """A grid of image files with a caption under each, saved as PNG."""
    import imageio.v3 as iio

    plt = _plt()
    n = len(images)
    cols = min(columns, max(n, 1))
    rows = max(1, -(-n // cols))
    fig, axes = plt.subplots(rows, cols, figsize=(2 * cols, 2.2 * rows), dpi=100, squeeze=False)
    for k, ax in enumerate(axes.ravel()):
        ax.axis("off")
        if k < n:
            ax.imshow(iio.imread(images[k]))
            ax.set_title(labels[k], fontsize=8)
    fig.tight_layout()
    with atomic_write(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return Path(path)
