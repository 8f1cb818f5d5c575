"""Rooms seen from inside: which scenes are rooms to the fields, and the settings they get.

Cameras inside a room see no ray that meets nothing, so no view says which
space is empty, and a field fitted to the colours alone fills the room with
fog: each view is painted on density just in front of its own camera, and
the finer levels, or a colour that depends on the view direction, let every
view keep its own (docs/field.md, "Rooms"). A room's fields trained on colour
alone start their samples a little away from the camera
(``FieldConfig.near``), with a diffuse colour and no distortion loss; the
evaluation field takes three dense levels (16, 32, 64 cells) held smooth
by the grid's total variation (``smoothness_weight``), the planner's
ensemble its two coarse levels. Trained on the distance maps too, they keep
the preset's grid with a diffuse colour (a near distance would cut the
surfaces that cameras stand close to), the evaluation field its dense
levels held smooth too.
"""

from __future__ import annotations

import numpy as np

from ..rigs import INTERIOR_CLEARANCE
from .config import FieldConfig

#: Where a room's fields trained on colour alone start their samples
#: (``FieldConfig.near``, a fraction of the padded box's diagonal): at the
#: interior rig's clearance, so that no generated camera sees a surface closer
#: (rounded, as run records print it).
ROOM_NEAR = round(INTERIOR_CLEARANCE / (1.0 + 2.0 * FieldConfig.bbox_padding), 6)
#: Field options of rooms seen from inside: the evaluation field's and the
#: planner's ensemble's trained on colour alone, and both fields' with the
#: distance loss, the planner's without the smoothness (:func:`room_options`;
#: measured in docs/field.md, "Rooms").
#: 2^19 entries keep the 64-cell level dense, which the smoothness needs;
#: images that resolve less than 64 cells keep the levels up to what they
#: resolve (:func:`room_options`).
ROOM_OPTIONS = {"n_levels": 3, "per_level_scale": 2.0, "log2_table_size": 19, "smoothness_weight": 0.01,
                "near": ROOM_NEAR, "view_degree": 0, "distortion_weight": 0.0}
ROOM_PLANNER_OPTIONS = {"n_levels": 2, "near": ROOM_NEAR, "view_degree": 0, "distortion_weight": 0.0}
ROOM_DISTANCE_OPTIONS = {"view_degree": 0, "smoothness_weight": 0.01}


def cameras_inside(cameras, bbox_min, bbox_max) -> bool:
    """Whether most of ``cameras`` (objects with a ``position``) stand inside the box: a room seen from inside."""
    pos = np.array([c.position for c in cameras], np.float64).reshape(-1, 3)
    inside = np.all((pos > np.asarray(bbox_min)) & (pos < np.asarray(bbox_max)), axis=1)
    return bool(len(pos)) and bool(inside.mean() > 0.5)


def room_options(cameras, bbox_min, bbox_max, distance_weight: float = 0.0, planner: bool = False,
                 finest: float | None = None) -> dict:
    """Where the cameras stand inside the box, for fields trained on colour
    alone (``distance_weight`` 0) :data:`ROOM_OPTIONS` (an evaluation field)
    or :data:`ROOM_PLANNER_OPTIONS` (``planner``: the planner's ensemble),
    else :data:`ROOM_DISTANCE_OPTIONS` (the planner's ensemble without its
    smoothness, which was measured on evaluation fields alone); elsewhere none.

    ``finest``: cells per axis of the finest level that the preset gives
    the images (None: any); the evaluation field's levels double from 16
    cells up to it, two at least, :data:`ROOM_OPTIONS`' at most.
    """
    if not cameras_inside(cameras, bbox_min, bbox_max):
        return {}
    if distance_weight > 0:
        options = dict(ROOM_DISTANCE_OPTIONS)
        if planner:
            del options["smoothness_weight"]
        return options
    if planner:
        return dict(ROOM_PLANNER_OPTIONS)
    options = dict(ROOM_OPTIONS)
    if finest is not None:
        options["n_levels"] = int(np.clip(1 + round(np.log2(max(finest, 1.0) / 16.0)), 2, options["n_levels"]))
    return options
