"""The ``radiance_field`` integrator: render a saved ensemble with ``mi.render``.

.. code-block:: python

    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "radiance_field", "filename": "field.npz"},
        "sensor": {"type": "perspective", ...},
    })
    img = mi.render(scene)  # (H, W, 3 + 6): RGB, then the AOVs below

Parameters:
    filename: an ensemble written by ``Ensemble.save`` (``.npz``; a saved
        VariationalField too, whose draws take the members' place below); a relative
        path is read from the current folder or, failing that, beside the scene XML.
    linear: bool, default True. The field stores sRGB colours in [0, 1];
        with ``linear`` the mean colour is converted to linear RGB, so that
        Mitsuba's film, EXR and PNG writers treat it as radiance. False
        returns the field's sRGB values unchanged.

Outputs, per sample (the film averages them over a pixel's samples):
    RGB: mean colour over the ensemble members (linear or sRGB, see above);
    ``variance.R/G/B``: population variance over members of the sRGB colour;
    ``distance.Y``: mean over members of the expected distance (scene units)
    from the sensor's optical centre, given a hit (faint density gives its
    depth too: weigh it by the opacity); 0 where a ray misses the field's box;
    ``distance_var.Y``: its variance over members;
    ``opacity.Y``: mean accumulated opacity in [0, 1] (an ``rgba`` film's
    alpha is 1 everywhere: Mitsuba's alpha marks valid samples, and every ray is one).

Mitsuba starts camera rays on the near-clip plane; the integrator moves each
origin back along its ray onto the plane of the sensor's centre (for a
perspective sensor: onto the optical centre itself), so ray parameters are
distances from the optical centre, as in :func:`mitsuba_active.cameras.sensor_rays_dr`.
The sensor comes from the ``render`` call; :meth:`sample` called on its own
keeps the origins it is given.

Variants ``llvm_ad_rgb`` and ``cuda_ad_rgb`` only.
"""

from __future__ import annotations

import os

NAME = "radiance_field"
AOV_NAMES = ["variance.R", "variance.G", "variance.B", "distance.Y", "distance_var.Y", "opacity.Y"]

_classes: dict = {}  # variant -> integrator class (each variant has its own mi.SamplingIntegrator)


def supported(variant: str | None) -> bool:
    """True for the variants the integrator (and every field) runs on."""
    from mitsuba_active.variant import VARIANTS

    return variant in VARIANTS


def integrator_class():
    """The integrator class for the current Mitsuba variant (created on first use)."""
    import mitsuba as mi

    variant = mi.variant()
    if not supported(variant):
        raise RuntimeError(f"the {NAME} integrator needs Mitsuba variant llvm_ad_rgb or cuda_ad_rgb, not {variant}")
    if variant not in _classes:
        _classes[variant] = _make_class(mi.SamplingIntegrator)
    return _classes[variant]


def _ensemble_path(filename: str) -> str:
    """``filename`` as given when it names a file from the current folder;
    otherwise as Mitsuba's file resolver finds it, which while a scene XML
    loads looks beside that XML first. (The resolver alone would also search
    the folder Python was started in, and could find another run's
    ``ensemble_NNN.npz`` there.)"""
    import mitsuba as mi

    if os.path.isabs(filename) or os.path.exists(filename):
        return filename
    return str(mi.file_resolver().resolve(filename))


def create(props):
    """Constructor handed to ``mi.register_integrator``."""
    return integrator_class()(props)


def _srgb_to_linear(x):
    import drjit as dr

    return dr.select(x <= 0.04045, x * (1.0 / 12.92), dr.power((x + 0.055) * (1.0 / 1.055), 2.4))


def _make_class(base):
    import drjit as dr
    import mitsuba as mi

    class RadianceFieldIntegrator(base):
        """Renders a saved :class:`~mitsuba_active.field.Ensemble` (see the module docstring)."""

        def __init__(self, props):
            super().__init__(props)
            from mitsuba_active.field import Ensemble

            if "filename" not in props:
                raise ValueError(f"{NAME}: the 'filename' parameter (a saved ensemble) is required")
            self.filename = _ensemble_path(str(props["filename"]))
            self.linear = props.get("linear", True)
            if not isinstance(self.linear, bool):  # e.g. the string "false", which bool() reads as true
                raise ValueError(f"{NAME}: 'linear' must be a boolean, got {self.linear!r}")
            self.ensemble = Ensemble.load(self.filename)
            self._sensor = None

        def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
            # Remember the sensor: sample() needs its optical centre.
            self._sensor = sensor if isinstance(sensor, mi.Sensor) else scene.sensors()[int(sensor)]
            try:
                return super().render(scene, self._sensor, seed, spp, develop, evaluate)
            finally:
                self._sensor = None

        def _origins(self, ray):
            """Ray origins moved back onto the plane through the sensor's centre, facing its axis."""
            o, d = mi.Point3f(ray.o), dr.normalize(mi.Vector3f(ray.d))
            if self._sensor is None:
                return o, d
            to_world = self._sensor.world_transform()
            centre = to_world @ mi.Point3f(0.0, 0.0, 0.0)
            axis = dr.normalize(to_world @ mi.Vector3f(0.0, 0.0, 1.0))
            cos = dr.dot(d, axis)
            back = dr.select(dr.abs(cos) > 1e-6, dr.dot(o - centre, axis) / cos, 0.0)
            return dr.fma(d, -back, o), d

        def sample(self, scene, sampler, ray, medium=None, active=True):
            o, d = self._origins(ray)
            with dr.suspend_grad():
                # One render per member (a VariationalField: per draw).
                outs = self.ensemble.render_dr(self.ensemble.params(), o, d)
            k = len(outs)
            # Population statistics over members, as Ensemble.predict computes them.
            rgb = sum(out["rgb"] for out in outs) / k
            dist = sum(out["distance"] for out in outs) / k
            opacity = sum(out["opacity"] for out in outs) / k
            var = sum(dr.square(out["rgb"] - rgb) for out in outs) / k
            dist_var = sum(dr.square(out["distance"] - dist) for out in outs) / k
            colour = _srgb_to_linear(rgb) if self.linear else rgb
            aovs = [var.x, var.y, var.z, dist, dist_var, opacity]
            return mi.Spectrum(colour), mi.Bool(active), aovs

        def aov_names(self):
            return list(AOV_NAMES)

        def to_string(self):
            return f"RadianceFieldIntegrator[filename={self.filename!r}, linear={self.linear}]"

    return RadianceFieldIntegrator
