"""View-dependent colour: spherical harmonics of the view direction, added at each ray's hit.

The grid's colour is diffuse: the same from every direction. Glossy
surfaces (a varnished wood, a metal, a plastic) change colour with the
direction they are seen from. A dense grid of coefficients of the real
spherical harmonics of degree 1 to 2 (the constant one excluded: that is
the grid's colour) gives each point a colour residual that varies smoothly
with the view direction. It is looked up once per ray, at the ray's
expected hit (``o + d * distance``), and added to the composited colour in
proportion to the ray's opacity: the cost grows with the rays, not their
samples. The hit and the opacity carry no gradient from the residual, so
that geometry is not bent to explain a highlight.

The table holds ``(resolution + 1)**3`` vertices per member, each with
``3 * ((degree + 1)**2 - 1)`` channels (the coefficients of red, then green,
then blue), member-interleaved as the grid's table is; it starts at 0, so an
untrained field is diffuse.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .grid import GridLayout, corners, reduce_mode

#: Most spherical-harmonic degree of the view-dependent colour.
MAX_VIEW_DEGREE = 2


def n_coefficients(degree: int) -> int:
    """Spherical harmonics of degrees 1 to ``degree``: 3 for degree 1, 8 for degree 2."""
    return (int(degree) + 1) ** 2 - 1


def view_layout(resolution: int) -> GridLayout:
    """The dense one-level layout of the coefficients' grid, ``resolution`` cells per axis."""
    r = int(resolution)
    n = (r + 1) ** 3
    return GridLayout((r,), (n,), (0,), (True,), n)


def sh_basis(d, degree: int) -> list:
    """Real spherical harmonics of degrees 1 to ``degree`` of unit directions
    ``d`` (``mi.Vector3f``): a list of :func:`n_coefficients` ``mi.Float``."""
    x, y, z = d[0], d[1], d[2]
    basis = [-0.48860251 * y, 0.48860251 * z, -0.48860251 * x]
    if degree >= 2:
        basis += [1.09254843 * x * y, -1.09254843 * y * z, 0.31539157 * (3.0 * z * z - 1.0),
                  -1.09254843 * x * z, 0.54627421 * (x * x - y * y)]
    return basis


def view_residual(table, resolution: int, degree: int, n_members: int, u, d, member):
    """Colour residual (``mi.Color3f``, per ray) at box-normalised points ``u``
    (``mi.Point3f``) seen along unit directions ``d`` (``mi.Vector3f``), of
    member ``member`` (an int or a ``mi.UInt32`` per ray), differentiable with
    respect to ``table`` (``mi.Float``, see the module docstring)."""
    n = n_coefficients(degree)
    C, K = 3 * n, int(n_members)
    XF = type(mi.ArrayXf())
    mem = mi.UInt32(member)
    coef = [mi.Float(0.0)] * C
    for _, idx, w in corners(view_layout(resolution), u):
        v = dr.gather(XF, table, idx * K + mem, mode=reduce_mode(), shape=(C, dr.width(idx)))
        coef = [dr.fma(v[c], w, coef[c]) for c in range(C)]
    basis = sh_basis(d, degree)
    return mi.Color3f(*[sum(coef[ch * n + j] * basis[j] for j in range(n)) for ch in range(3)])
