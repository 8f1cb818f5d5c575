"""A world's up axis, stood upright: the axis its cameras were set up around, and frames that turn it.

Light on purpose (numpy only): the report's page and the viewer draw with it
without loading the rigs' or the plots' libraries.
"""

from __future__ import annotations

import numpy as np


def snapped_up(cameras) -> np.ndarray:
    """The world axis (3,) closest to the cameras' mean up vector, with its sign:
    the up axis of a scene or dataset as its cameras were set up (Y without cameras)."""
    up = np.zeros(3)
    mean = np.mean([c.to_world[:3, 1] for c in cameras], axis=0) if len(cameras) else np.array([0.0, 1.0, 0.0])
    axis = int(np.argmax(np.abs(mean)))
    up[axis] = 1.0 if mean[axis] >= 0 else -1.0
    return up


def up_frame(up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """(3, 3) rotation whose second column is ``up``: maps a Y-up rig into a world with that up axis."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    z = np.cross(a, up)
    z /= np.linalg.norm(z)
    return np.stack([np.cross(up, z), up, z], axis=1)


def up_vertical(points, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World points (N, 3) in a frame whose third axis is ``up``: matplotlib's
    3D axes draw their third axis vertically."""
    q = np.asarray(points, dtype=np.float64).reshape(-1, 3) @ up_frame(up)  # columns: side, up, side
    return q[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # keep the frame right-handed
