"""Plots and image sheets for runs and benchmarks (matplotlib, Agg backend)."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

from .imageio_utils import atomic_write
from .upright import up_vertical


def _plt():
    """matplotlib's pyplot, loaded on the first plot with the file-only backend chosen before it."""
    import matplotlib  # here, not above: a caller's own backend stays until a plot is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path) -> Path:
    """Lay out ``fig``, write it to ``path`` as PNG (atomically) and free it."""
    fig.tight_layout()
    with atomic_write(path) as tmp:
        fig.savefig(tmp, format="png")
    _plt().close(fig)
    return Path(path)


METRIC_LABELS = {"psnr": "held-out PSNR (dB)", "psnr_fg": "held-out foreground PSNR (dB)",
                 "ssim": "held-out SSIM", "distance_error": "distance error (%)"}
#: Records' scores of the trivial prediction (the background colour alone), drawn in their metric's plot.
FLOORS = {"psnr": "floor_psnr", "psnr_fg": "floor_psnr_fg"}


def plot_metrics(series: dict[str, list[dict]], out_dir, title: str = "", bands: dict | None = None,
                 colors: dict | None = None) -> list[Path]:
    """One PNG per metric against views captured, a line per planner.

    Args:
        series: planner name -> list of metric records (``views``, ``psnr``, ...).
        out_dir: folder for ``psnr.png``, ``psnr_fg.png``, ``distance_error.png`` and ``ssim.png``
            (the PSNRs with a dashed line of the background colour alone where records have it:
            the first planner's, as every planner is scored on the same held-out views).
        bands: optional planner name -> metric -> (lower, upper) arrays to shade.
        colors: optional planner name -> Matplotlib colour, so that a planner
            keeps its colour across plots (default: the colour cycle).
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
            (line,) = ax.plot(x, y, marker="o", label=name, color=(colors or {}).get(name))
            band = (bands or {}).get(name, {}).get(metric)
            if band is not None:
                ax.fill_between(x, band[0], band[1], alpha=0.2, color=line.get_color())
            plotted = True
        if not plotted:
            plt.close(fig)
            continue
        floors = ([(r["views"], r[FLOORS[metric]]) for r in records if r.get(FLOORS[metric]) is not None]
                  for records in series.values() if metric in FLOORS)
        floor = next((points for points in floors if points), [])
        if floor:
            x, y = np.array(floor, dtype=float).T
            ax.plot(x, y, ls="--", color="0.5", label="background alone")
        ax.set_xlabel("views captured")
        ax.xaxis.set_major_locator(plt.MaxNLocator(integer=True))
        ax.set_ylabel(label)
        # Nearly equal values would otherwise get ticks relative to an offset (+8.217): unreadable.
        ax.ticklabel_format(axis="y", useOffset=False)
        ax.set_title(title)
        ax.grid(alpha=0.3)
        ax.legend()
        written.append(_save(fig, Path(out_dir) / f"{metric}.png"))
    return written


def contact_sheet(images: list, labels: list[str], path, columns: int = 5) -> Path:
    """A grid of images with a caption under each, saved as PNG.

    Args:
        images: image files, or (H, W, 3) arrays of display values in [0, 1].
    """
    plt = _plt()
    n = len(images)
    cols = min(columns, max(n, 1))
    rows = max(1, -(-n // cols))
    fig, axes = plt.subplots(rows, cols, figsize=(2 * cols, 2.2 * rows), dpi=100, squeeze=False)
    for k, ax in enumerate(axes.ravel()):
        ax.axis("off")
        if k < n:
            img = images[k]
            ax.imshow(np.clip(img, 0.0, 1.0) if isinstance(img, np.ndarray) else iio.imread(img))
            ax.set_title(labels[k], fontsize=8)
    return _save(fig, path)


def plot_views(candidates, captured, heldout, bbox_min, bbox_max, path, up=(0.0, 1.0, 0.0),
               initial: int = 0, title: str = "", routes=None, along=()) -> Path:
    """Where the cameras are: a 3D plot of camera positions, ``up`` vertical.

    Candidates are grey dots, held-out views blue crosses, and captured views are
    coloured by capture order (the first ``initial`` ones, chosen at random, as
    squares), each with its capture number and a short line along its viewing
    direction; the scene's bounding box is a wireframe. A moving camera's path between the
    captures is a thin line (``routes``), views captured along the way small triangles.

    Args:
        candidates, heldout: :class:`~mitsuba_active.cameras.Camera` lists.
        captured: candidate indices in capture order (repeats allowed).
        routes: the way to each capture, (N, 3) scene units, in capture order (None: not drawn).
        along: capture numbers of the views taken along the way.
        bbox_min, bbox_max: (3,) scene bounds in scene units.
    """
    plt = _plt()
    pos = up_vertical([c.position for c in candidates], up)
    fwd = up_vertical([c.forward for c in candidates], up)
    held = up_vertical([c.position for c in heldout], up) if heldout else np.zeros((0, 3))
    lo, hi = np.asarray(bbox_min, dtype=np.float64), np.asarray(bbox_max, dtype=np.float64)
    corners = up_vertical([[(lo, hi)[i >> a & 1][a] for a in range(3)] for i in range(8)], up)
    fig = plt.figure(figsize=(5.5, 5), dpi=110)
    ax = fig.add_subplot(projection="3d")
    for i in range(8):
        for a in range(3):
            j = i | (1 << a)
            if j != i:
                ax.plot(*corners[[i, j]].T, color="0.6", lw=0.8)
    ax.scatter(*pos.T, s=6, color="0.7", label="candidates")
    if len(held):
        ax.scatter(*held.T, s=14, marker="x", color="tab:blue", label="held out")
    everything = np.concatenate([pos, held, corners])
    arrow = 0.08 * float(np.ptp(everything, axis=0).max())
    colours = plt.get_cmap("viridis")(np.linspace(0.0, 1.0, max(len(captured), 1)))
    for n, route in enumerate(routes or ()):
        if route is not None and len(route) > 1:
            ax.plot(*up_vertical(route, up).T, color="0.35", lw=0.7, label="path" if n == 1 else None)
    along = set(along)
    # The first of each kind names it in the legend.
    chosen = [n for n in range(initial, len(captured)) if n not in along]
    firsts = {min(chosen, default=None): "captured (colour: order)", min(along, default=None): "along the way",
              0 if initial else None: "initial (random)"}
    for n, idx in enumerate(captured):
        p, f = pos[idx], fwd[idx]
        ax.scatter(*p, s=12 if n in along else 28, color=colours[n],
                   marker="s" if n < initial else "^" if n in along else "o", depthshade=False,
                   label=firsts.get(n))
        if n in along:
            continue
        ax.plot(*np.stack([p, p + arrow * f]).T, color=colours[n], lw=1.2)
        ax.text(*(p + 0.3 * arrow), str(n), fontsize=7)
    centre, half = everything.mean(axis=0), 0.5 * float(np.ptp(everything, axis=0).max())
    ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half),
           zlim=(centre[2] - half, centre[2] + half), xticklabels=[], yticklabels=[], zticklabels=[])
    ax.set_box_aspect((1, 1, 1))
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper left", fontsize=7)
    return _save(fig, path)
