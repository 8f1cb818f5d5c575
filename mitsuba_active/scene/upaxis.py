"""The up axis a mesh's shape shows: the one it rests on a flat base across.

Meshes come Y-up (OBJ and glTF by custom and by spec) or Z-up (CAD, STL,
many scans), and nothing in most files says which. A shape shows it when it
stands on a flat base (feet, a stand, landing gear, a cut scan) across one
of the two candidate axes and not across the other: the convex hull then
has a large facet facing down along that axis.
"""

from __future__ import annotations

import numpy as np

#: Share of the hull's outline across an axis that a flat base must cover to show it.
PLAIN_BASE = 0.1
#: At most this share across the other axis, for the shape to show one plainly.
NO_BASE = 0.05
#: Hull volume, as a share of the cube of the box's mean side, below which a shape is flat.
FLAT = 1e-6
#: Facets within this angle (degrees) of facing straight down make the base.
BASE_TILT = 3.0


def base_share(hull_normals: np.ndarray, hull_areas: np.ndarray, axis: int) -> float:
    """Share of the hull's outline across ``axis`` that its flat base covers.

    ``hull_normals``: (F, 3) unit outward facet normals of a convex hull;
    ``hull_areas``: (F,) their areas. The outline's area is half the sum of
    the facets' areas projected onto the plane across ``axis``.
    """
    along = hull_normals[:, axis]
    outline = 0.5 * float((np.abs(along) * hull_areas).sum())
    down = along < -np.cos(np.radians(BASE_TILT))
    return float(hull_areas[down].sum()) / outline if outline > 0 else 0.0


def shown_up_axis(mesh) -> str | None:
    """``"y"`` or ``"z"`` when the mesh (a trimesh.Trimesh) plainly rests on
    a flat base across that axis and not across the other, else None."""
    try:
        hull = mesh.convex_hull
    except Exception:  # flat or degenerate: no hull, no base
        return None
    extent = np.ptp(np.asarray(mesh.vertices, dtype=np.float64), axis=0)
    if not hull.volume > FLAT * float(np.prod(extent[extent > 0])) ** (3 / max(1, int((extent > 0).sum()))):
        return None  # a flat shape (a sheet, a sign) lies on either face: it shows no up
    y, z = (base_share(np.asarray(hull.face_normals), np.asarray(hull.area_faces), k) for k in (1, 2))
    if y >= PLAIN_BASE and z <= NO_BASE:
        return "y"
    if z >= PLAIN_BASE and y <= NO_BASE:
        return "z"
    return None
