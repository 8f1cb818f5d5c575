"""A run folder's ensemble rendered from a camera: the mean image and its variance as a colour map.

The viewer loads this module on its first click, not when it opens: it
brings the field and its renderer, which drawing the cameras does not need.
"""

from __future__ import annotations

from pathlib import Path

from .cameras import Camera
from .field import Ensemble
from .imageio_utils import colorize
from .training import predict_view


class RunEnsemble:
    """The planner's ensemble that the run in ``run_dir`` keeps (its record's ``ensemble_file``), read once a file."""

    def __init__(self, run_dir):
        self.run_dir = Path(run_dir)
        self._loaded = None  # (file name, ensemble) last read

    def field(self, rec: dict) -> Ensemble | None:
        """The ensemble the record ``rec`` names; None when the run keeps none."""
        name = rec.get("ensemble_file")
        if not name or not (self.run_dir / name).is_file():
            return None
        if self._loaded is None or self._loaded[0] != name:
            self._loaded = (name, Ensemble.load(str(self.run_dir / name)))
        return self._loaded[1]

    def render(self, rec: dict, camera: Camera) -> dict | None:
        """From ``camera``: ``mean``, the members' mean RGB (H, W, 3) float in [0, 1], and ``variance``,
        their variance (mean over RGB) colour-mapped to RGB (H, W, 3) in [0, 1]; None without an ensemble."""
        field = self.field(rec)
        if field is None:
            return None
        pred = predict_view(field, camera)
        return {"mean": pred["rgb"], "variance": colorize(pred["rgb_var"].mean(axis=2), vmin=0.0)}
