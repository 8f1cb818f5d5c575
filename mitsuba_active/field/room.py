"""Rooms seen from inside: which scenes are rooms to the fields, and the settings they get.

Cameras inside a room see no ray that meets nothing, so no view says which
space is empty, and a field fitted to the colours alone fills the room with
fog: each view is painted on density just in front of its own camera, and
the finer levels, or a colour that depends on the view direction, let every
view keep its own (docs/field.md, "Rooms"). A room's fields trained on colour
alone start their samples a little away from the camera
(``FieldConfig.near``), keep to the two coarse levels, a diffuse colour and
no distortion loss; trained on the distance maps too, they keep the preset's
grid with a diffuse colour (a near distance would cut the surfaces that
cameras stand close to).
"""

from __future__ import annotations

import numpy as np

#: Field options of rooms seen from inside, trained on colour alone and with
#: the distance loss (:func:`room_options`; measured in docs/field.md, "Rooms").
ROOM_OPTIONS = {"n_levels": 2, "near": 0.05, "view_degree": 0, "distortion_weight": 0.0}
ROOM_DISTANCE_OPTIONS = {"view_degree": 0}


def cameras_inside(cameras, bbox_min, bbox_max) -> bool:
    """Whether most of ``cameras`` (objects with a ``position``) stand inside the box: a room seen from inside."""
    pos = np.array([c.position for c in cameras], np.float64).reshape(-1, 3)
    inside = np.all((pos > np.asarray(bbox_min)) & (pos < np.asarray(bbox_max)), axis=1)
    return bool(len(pos)) and bool(inside.mean() > 0.5)


def room_options(cameras, bbox_min, bbox_max, distance_weight: float = 0.0) -> dict:
    """Where the cameras stand inside the box, :data:`ROOM_OPTIONS` for fields
    trained on colour alone (``distance_weight`` 0), else
    :data:`ROOM_DISTANCE_OPTIONS`; elsewhere none."""
    if not cameras_inside(cameras, bbox_min, bbox_max):
        return {}
    return dict(ROOM_DISTANCE_OPTIONS if distance_weight > 0 else ROOM_OPTIONS)
