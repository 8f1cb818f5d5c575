"""Ground truth: physically rendered RGB and distance for any camera, cached as EXR.

RGB comes from the scene's own integrator (``mi.render``; a path tracer when
the XML names none); distance is the length of the pixel-centre ray from the
optical centre to the first hit (not Mitsuba's ``aov`` depth, which starts at
the near-clip plane). Renders are cached in a content-addressed EXR store:
the key hashes the scene's content, the pose, the intrinsics, the clip
distances, the resolution and the sample count. An entry that cannot be read,
or does not hold the finite RGB and distance of its camera's size, is rendered
again, with a warning that names it.
"""

from __future__ import annotations

import functools
import hashlib
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .cameras import Camera, sensor_rays_dr
from .checks import is_whole
from .errors import UserError
from .imageio_utils import linear_to_srgb, read_exr, write_exr
from .interrupts import waiting_for
from .variant import require_variant

CACHE_VERSION = "1"


def default_cache_dir() -> Path:
    """``$MITSUBA_ACTIVE_CACHE``, else ``$XDG_CACHE_HOME/mitsuba-active``, else ``~/.cache/mitsuba-active``."""
    if os.environ.get("MITSUBA_ACTIVE_CACHE"):
        return Path(os.environ["MITSUBA_ACTIVE_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "mitsuba-active"


@dataclass
class View:
    """One captured view.

    Attributes:
        rgb: (H, W, 3) float32 sRGB colour in [0, 1].
        distance: (H, W) float32 distance from the optical centre in scene units; 0 where ``mask`` is False.
        mask: (H, W) bool, True where the pixel-centre ray hits geometry.
        camera: the camera it was taken with.
        known_empty: (H, W) bool, True where the pixel is known to see no
            geometry at all (a dataset image's alpha is 0 there), or None
            (a rendered view's): where neither its centre ray nor those of
            its 8 neighbours hit (see :attr:`empty`).
        background: the RGB colour the known-empty pixels show exactly (a
            dataset's images are composited on it), or None (a rendered
            view's background is its scene's environment).
    """

    rgb: np.ndarray
    distance: np.ndarray
    mask: np.ndarray
    camera: Camera
    known_empty: np.ndarray | None = None
    background: tuple | None = None

    @property
    def foreground(self) -> np.ndarray:
        """(H, W) bool: the pixels that see geometry, whose colour the foreground PSNR scores.

        The hits, and for a dataset's view every pixel its alpha covers (all of
        them where its images have no alpha).
        """
        mask = np.asarray(self.mask, bool)
        return mask if self.known_empty is None else mask | ~np.asarray(self.known_empty, bool)

    @property
    def empty(self) -> np.ndarray:
        """(H, W) bool: the pixels known to see nothing, whose rays the empty-ray loss clears.

        A rendered pixel's colour averages its whole footprint, so one whose
        centre ray misses may still show an edge: only pixels whose 3x3
        neighbourhood misses count.
        """
        if self.known_empty is not None:
            return self.known_empty
        hit = np.pad(np.asarray(self.mask, bool), 1, mode="edge")
        h, w = hit.shape[0] - 2, hit.shape[1] - 2
        near = np.zeros((h, w), bool)
        for dy in range(3):
            for dx in range(3):
                near |= hit[dy:dy + h, dx:dx + w]
        return ~near


def render_distance(mi_scene, camera: Camera) -> np.ndarray:
    """(H, W) float32 distance from the optical centre along pixel-centre rays, 0 where nothing is hit."""
    o, d = sensor_rays_dr(camera.sensor(), camera.width, camera.height)
    si = mi_scene.ray_intersect(mi.Ray3f(o, d))
    t = dr.select(si.is_valid(), si.t, 0.0)
    return np.array(t, dtype=np.float32).reshape(camera.height, camera.width)


#: Most samples Mitsuba renders at once: it traces all of a render's samples
#: as one wavefront, so larger renders are split into passes of fewer samples
#: per pixel (averaged), lest they run out of memory.
MAX_PASS_SAMPLES = 1 << 24
#: Most samples per pixel of ground truth (far beyond a converged render).
MAX_SPP = 65536


def render_rgb(mi_scene, camera: Camera, spp: int, seed: int = 0) -> np.ndarray:
    """(H, W, 3) float32 linear radiance from the scene's integrator (a path
    tracer when the scene names none, as Mitsuba XMLs may)."""
    integrator = mi_scene.integrator() or _path_integrator(mi.variant())
    per_pass = max(1, MAX_PASS_SAMPLES // (camera.width * camera.height))
    # One pass (most renders) gives Mitsuba's image exactly: k * x / k is x in float64.
    total = np.zeros((camera.height, camera.width, 3))
    for n, start in enumerate(range(0, spp, per_pass)):
        k = min(per_pass, spp - start)
        img = waiting_for(mi.render, mi_scene, sensor=camera.sensor(k), integrator=integrator, spp=k, seed=seed + n)
        total += k * np.array(img, dtype=np.float64)[..., :3]
    return (total / spp).astype(np.float32)


@functools.lru_cache(maxsize=None)
def _path_integrator(variant: str):
    """A default path tracer, made once per variant (the cache key) rather than once per render."""
    return mi.load_dict({"type": "path"})


def read_entry(path: Path, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """The (H, W, 3) float32 linear RGB and (H, W) float32 distance of the
    cache entry ``path`` for ``camera``; ValueError saying what is wrong with
    an entry that cannot be that render (unreadable, other channels, another
    size, values that are not finite)."""
    try:
        ch = read_exr(path)
    except ValueError as exc:
        raise ValueError(f"unreadable: {exc}") from None
    if set(ch) != {"RGB", "Z"}:
        raise ValueError(f"channels {', '.join(sorted(ch)) or 'none'}, not RGB and Z")
    linear, distance = ch["RGB"], ch["Z"]
    wanted = (camera.height, camera.width)
    for shape in (linear.shape[:2], distance.shape):
        if shape != wanted:
            raise ValueError(f"{shape[1]}x{shape[0]} pixels, not {wanted[1]}x{wanted[0]}")
    if not (np.isfinite(linear).all() and np.isfinite(distance).all()):
        raise ValueError("NaN or infinite values")
    return linear, distance


class GroundTruth:
    """Renders and caches the views of one scene.

    Args:
        scene: a :class:`mitsuba_active.scene.Scene`.
        spp: samples per pixel of the RGB render.
        cache_dir: EXR cache folder (``None``: :func:`default_cache_dir`; ``False``: no cache).

    Cache keys hash the scene's files (``scene.content_hash``), not the
    Mitsuba scene in memory: a scene edited through ``mi.traverse`` needs
    ``cache_dir=False``.
    """

    def __init__(self, scene, spp: int = 64, cache_dir=None):
        if not is_whole(spp) or not 0 < spp <= MAX_SPP:
            raise UserError(f"samples per pixel must be a whole number in [1, {MAX_SPP}], got {spp!r}")
        self.scene = scene
        self.spp = int(spp)
        self.cache_dir = None if cache_dir is False else Path(cache_dir or default_cache_dir())

    def key(self, camera: Camera) -> str:
        h = hashlib.sha256()
        h.update(f"v{CACHE_VERSION}|{self.scene.content_hash}|{self.spp}|".encode())
        h.update(np.round(camera.to_world, 9).astype(np.float64).tobytes())
        h.update(f"|{camera.fov:.9g}|{camera.width}|{camera.height}|{camera.near:.9g}|{camera.far:.9g}".encode())
        return h.hexdigest()

    def render(self, camera: Camera) -> View:
        """The view from ``camera``, from the cache when it is there."""
        path = None
        if self.cache_dir is not None:
            key = self.key(camera)
            path = self.cache_dir / key[:2] / f"{key}.exr"
            if path.is_file():
                try:
                    linear, distance = read_entry(path, camera)
                except ValueError as exc:
                    warnings.warn(f"cached ground truth {path} is unusable ({exc}); rendering it again", stacklevel=2)
                else:
                    return self._view(linear, distance, camera)
        require_variant("rendering ground truth")
        # Seed from the pose so that views are independent but reproducible.
        seed = int(self.key(camera)[:7], 16)
        linear = render_rgb(self.scene.mi_scene, camera, self.spp, seed)
        distance = render_distance(self.scene.mi_scene, camera)
        if path is not None:
            try:
                write_exr(path, {"RGB": linear, "Z": distance})
            except OSError as exc:
                raise UserError(f"cannot write the ground-truth cache in {self.cache_dir} ({exc.strerror or exc}); "
                                "set MITSUBA_ACTIVE_CACHE to a writable folder") from None
        return self._view(linear, distance, camera)

    @staticmethod
    def _view(linear, distance, camera) -> View:
        return View(linear_to_srgb(linear), distance.astype(np.float32), distance > 0, camera)
