"""A run's cameras as its 3D views draw them: poses with the up axis vertical, bounds, captures, scores.

The report's page (:mod:`.webpage`) and the viewer (:mod:`.viewer`) draw
what :func:`camera_scene` returns; it loads nothing but the cameras, so the
viewer opens without the libraries that plots and fields need.
"""

from __future__ import annotations

import numpy as np

from .cameras import Camera
from .upright import snapped_up, up_vertical


def _camera_entry(cam: Camera, up) -> dict:
    """A camera for the page's 3D view, in the frame whose third axis is ``up``."""
    axes = up_vertical(cam.to_world[:3, :3].T, up)  # rows: left, up and forward in the drawing frame
    return {"p": np.round(up_vertical([cam.position], up)[0], 5).tolist(),
            "left": np.round(axes[0], 5).tolist(), "up": np.round(axes[1], 5).tolist(),
            "fwd": np.round(axes[2] / np.linalg.norm(axes[2]), 5).tolist(),
            "fov": float(cam.fov), "aspect": cam.height / cam.width}


def camera_scene(rec: dict) -> dict:
    """What the page's 3D view draws, from a run record: cameras, bounds, captures and each round's scores."""
    # With the cameras the run added (views along the way, continuous candidates): captured indices name them.
    candidates = [Camera.from_dict(c) for c in rec["candidates"] + [a["camera"] for a in rec.get("added", ())]]
    heldout = [Camera.from_dict(c) for c in rec["heldout"]]
    up = snapped_up(candidates)
    bbox = rec.get("bbox")
    if bbox is None:  # a record from before bounds were kept: the cameras' extent
        pos = np.array([c.position for c in candidates + heldout])
        bbox = [pos.min(axis=0).tolist(), pos.max(axis=0).tolist()]
    lo, hi = np.asarray(bbox[0], float), np.asarray(bbox[1], float)
    corners = up_vertical([[(lo, hi)[i >> a & 1][a] for a in range(3)] for i in range(8)], up)
    rounds = [{"views": r["views"], "picks": r["picks"],
               "scores": None if r.get("scores") is None else [None if s is None else float(f"{s:.6g}")
                                                                for s in r["scores"]]}
              for r in rec.get("rounds", [])]
    cfg = rec.get("config", {})
    # The way a moving camera went to each capture (None: straight, or teleported).
    routes = [np.round(up_vertical(leg["route"], up), 5).tolist()
              if isinstance(leg, dict) and leg.get("route") and len(leg["route"]) > 1 else None
              for leg in (rec.get("travel") or [])[:len(rec["captured"])]]
    return {"corners": np.round(corners, 5).tolist(), "candidates": [_camera_entry(c, up) for c in candidates],
            "heldout": [_camera_entry(c, up) for c in heldout], "captured": list(rec["captured"]),
            "initial": min(int(cfg.get("initial_views", 0)), len(rec["captured"])), "rounds": rounds,
            "routes": routes}
