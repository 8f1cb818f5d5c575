"""Plots of a moving camera's run: held-out PSNR against travel, and the route flown.

Written next to the run's other plots when its camera moved
(:mod:`~mitsuba_active.travel`): ``psnr_travel.png`` (PSNR against the
distance travelled and the mission time) and ``route.png`` (the route
between the captures, seen from above).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .report import _plt, _save


def plot_travel(record: dict, out_dir, title: str = "") -> list[Path]:
    """The travel plots of a run record (a dict from run.json); none for a run whose camera did not move."""
    legs, metrics = record.get("travel") or [], record.get("metrics") or []
    points = [(m["travel_distance"], m["mission_time"], m["psnr"]) for m in metrics
              if m.get("travel_distance") is not None and m.get("mission_time") is not None]
    if not legs or not any(leg["distance"] > 0 or leg["time"] > 0 for leg in legs):
        return []
    written = []
    if points:
        plt = _plt()
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.5), dpi=110, sharey=True)
        distance, time, psnr = np.array(points, dtype=float).T
        for ax, x, label in ((axes[0], distance, "distance travelled (scene units)"),
                             (axes[1], time, "mission time (s)")):
            ax.plot(x, psnr, marker="o")
            ax.set_xlabel(label)
            ax.grid(alpha=0.3)
        axes[0].set_ylabel("held-out PSNR (dB)")
        axes[0].ticklabel_format(axis="y", useOffset=False)
        fig.suptitle(title)
        written.append(_save(fig, Path(out_dir) / "psnr_travel.png"))
    routes = [np.asarray(leg["route"], dtype=float) for leg in legs if leg.get("route")]
    if routes:
        # Captures of cameras the run added along a route (its record's "added", after the candidates).
        base, added = len(record.get("candidates") or ()), record.get("added") or ()
        along = [n for n, i in enumerate(record.get("captured") or ())
                 if i >= base and added[i - base].get("kind") == "along the way"]  # run.record.ALONG_THE_WAY
        written.append(plot_route(routes, record.get("bbox"), Path(out_dir) / "route.png",
                                  up=record.get("up") if record.get("up") is not None else (0.0, 1.0, 0.0),
                                  title=title, along=along))
    return written


def plot_route(routes: list[np.ndarray], bbox, path, up=(0.0, 1.0, 0.0), title: str = "", along=()) -> Path:
    """The route between captures seen from above (along ``up``): each leg's points
    (N, 3) scene units as a line, the captures numbered, those in ``along`` (capture numbers
    of views along the way) as small triangles; ``bbox`` (2, 3) as a rectangle."""
    plt = _plt()
    up = np.asarray(up, dtype=float)
    keep = [i for i in range(3) if i != int(np.argmax(np.abs(up)))]  # the two axes across up
    fig, ax = plt.subplots(figsize=(5, 5), dpi=110)
    if bbox is not None:
        (x0, y0), (x1, y1) = np.asarray(bbox, dtype=float)[:, keep]
        ax.plot([x0, x1, x1, x0, x0], [y0, y0, y1, y1, y0], color="0.6", lw=1)
    colors = plt.cm.viridis(np.linspace(0, 1, max(len(routes), 1)))
    for n, (route, color) in enumerate(zip(routes, colors)):
        xy = route[:, keep]
        ax.plot(xy[:, 0], xy[:, 1], color=color, lw=1.5)
        if n in along:
            ax.plot(*xy[-1], marker="^", ms=4, color=color)
        else:
            ax.annotate(str(n + 1), xy[-1], fontsize=7)
    first = routes[0][0, keep]
    ax.plot(*first, marker="s", color="k")
    ax.set_aspect("equal")
    ax.set_xlabel("xyz"[keep[0]])
    ax.set_ylabel("xyz"[keep[1]])
    ax.set_title(title)
    ax.grid(alpha=0.3)
    return _save(fig, path)
