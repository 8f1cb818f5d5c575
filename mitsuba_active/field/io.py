"""Ensemble file format (``.npz``, version 1).

An uncompressed NumPy ``.npz`` archive with these arrays:

=====================  ================  ==========================================
key                    dtype / shape     meaning
=====================  ================  ==========================================
``format_version``     int64 ()          1
``kind``               str ()            ``"mitsuba_active.field.Ensemble"``, or
                                         ``"mitsuba_active.field.VariationalField"``
``config``             str ()            JSON of :class:`FieldConfig`
``options``            str ()            JSON of the kind's own options (``{}`` for
                                         an Ensemble; optional on read)
``bbox_min/bbox_max``  float64 (3,)      unpadded bounding box (scene units)
``n_members``          int64 ()          K (a VariationalField: 2, its mean and
                                         scale slots)
``seed``               int64 ()          base seed
``step``               int64 ()          training steps taken so far
``grid``               float32 (K,E,4)   grid table: E entries per member, channels
                                         (density logit, r, g, b logits); levels
                                         concatenated in order, dense levels
                                         x-fastest, hashed levels by hash slot
``background``         float32 (K,3)     background colour logits (sigmoid -> RGB)
``adam_t``             int64 ()          Adam step count (always written; optional on read, for warm start)
``adam_{m,v}_grid``    float32 (E*K*4,)  Adam moments of ``grid`` in the in-memory
                                         member-interleaved order [entry][member]
                                         [channel] (optional)
``adam_{m,v}_background`` float32 (K*3,) Adam moments of ``background`` (optional)
``view``               float32 (V,)      the view-dependent colour's table, as in
                                         memory (only with ``view_degree``; see
                                         :mod:`.view`), with ``adam_{m,v}_view``
``sky``                float32 (B,)      the directional background's map, as in
                                         memory (only with ``background_resolution``;
                                         see :mod:`.sky`), with ``adam_{m,v}_sky``
``occupancy``          float32 (G,G,G)   decaying max of cell opacities, [z,y,x]
                                         (only with empty-space skipping active)
``occupancy_age``      int64 ()          steps since the grid was reset (with
                                         ``occupancy_resolution > 0``, warm-up included)
=====================  ================  ==========================================

Training rays are not stored (call ``set_rays`` again after loading).
"""

from __future__ import annotations

import json
import zipfile
import zlib
from pathlib import Path

import drjit as dr
import numpy as np

from ..errors import UserError
from ..imageio_utils import atomic_write
from .config import FieldConfig
from .grid import N_CHANNELS

FORMAT_VERSION = 1


def save_ensemble(ens, path) -> Path:
    """Write ``ens`` to ``path`` (used as given: no suffix is added)."""
    path = Path(path)
    K = ens.n_members
    arrays = dict(
        format_version=np.int64(FORMAT_VERSION),
        kind=np.array(ens.KIND),
        config=np.array(json.dumps(ens.config.to_dict())),
        options=np.array(json.dumps(ens.options())),
        bbox_min=ens.bbox_min.astype(np.float64),
        bbox_max=ens.bbox_max.astype(np.float64),
        n_members=np.int64(K),
        seed=np.int64(ens.seed),
        step=np.int64(ens._step),
        grid=ens.grid_numpy(),
        background=ens._numpy("background").reshape(K, 3),
    )
    keys = ("grid", "background")
    if ens.config.view_degree > 0:
        arrays["view"] = ens.view_numpy()
        keys += ("view",)
    if ens.config.background_resolution > 0:
        arrays["sky"] = ens.sky_numpy()
        keys += ("sky",)
    st = ens._opt.state
    arrays["adam_t"] = np.int64(int(np.array(st["grid"][3][0]).ravel()[0]))
    for key in keys:
        _, m, v, _ = st[key][3]
        arrays[f"adam_m_{key}"] = np.array(m, np.float32)
        arrays[f"adam_v_{key}"] = np.array(v, np.float32)
    if ens.config.occupancy_resolution > 0:  # the age counts the warm-up too
        arrays["occupancy_age"] = np.int64(ens._occupancy_age)
    if ens._occupancy is not None:
        G = int(ens.config.occupancy_resolution)
        arrays["occupancy"] = np.array(ens._occupancy, np.float32).reshape(G, G, G)
    if path.is_dir():
        raise UserError(f"cannot write ensemble file {path}: it is a folder")
    try:
        with atomic_write(path) as tmp, open(tmp, "wb") as f:  # a failed write leaves no partial file
            np.savez(f, **arrays)
    except OSError as exc:
        raise UserError(f"cannot write ensemble file {path}: {exc.strerror or exc}") from None
    return path


def _kinds(cls) -> dict:
    """``{KIND: class}`` of ``cls`` and those of its subclasses that name a
    kind of their own; a subclass that only inherits a ``KIND`` (a user's
    ``class Logged(Ensemble)``) never stands in for the class it came from."""
    found, todo = {cls.KIND: cls}, list(cls.__subclasses__())
    while todo:
        c = todo.pop()
        if "KIND" in c.__dict__:
            found.setdefault(c.KIND, c)
        todo += c.__subclasses__()
    return found


def load_ensemble(cls, path):
    """Read an ensemble written by :func:`save_ensemble`: of class ``cls``, or
    of a subclass of it when the file holds one (``Ensemble.load`` reads a
    VariationalField too)."""
    path = Path(path)
    if path.is_file() and not zipfile.is_zipfile(path):  # np.load would guess at a pickle
        raise UserError(f"cannot read ensemble file {path}: not a whole .npz archive "
                        "(damaged, or another kind of file)")
    try:
        with np.load(path, allow_pickle=False) as z:
            ens = _ensemble_from(cls, z, path)
    # A truncated or foreign file fails in the zip reader, the decompressor or a lookup.
    except (OSError, ValueError, EOFError, KeyError, TypeError, AttributeError, RecursionError, zipfile.BadZipFile,
            zlib.error) as exc:
        raise UserError(f"cannot read ensemble file {path}: {exc}") from None
    dr.eval(ens._opt["grid"], ens._opt["background"])
    return ens


def _ensemble_from(cls, z, path):
    kind = str(z["kind"]) if "kind" in z else ""
    if "format_version" not in z or not kind.startswith("mitsuba_active.field."):
        raise UserError(f"{path} is not a mitsuba-active field ensemble")
    kinds = _kinds(cls)
    if kind not in kinds:
        raise UserError(f"{path} is a saved {kind.rsplit('.', 1)[-1]}, not a {cls.__name__}")
    version = int(z["format_version"])
    if version != FORMAT_VERSION:
        raise UserError(f"{path}: unsupported field format_version {version} "
                        f"(this version reads {FORMAT_VERSION})")
    options = json.loads(str(z["options"])) if "options" in z else {}
    if not isinstance(options, dict):
        raise UserError(f"{path}: its options are not a JSON object")
    try:
        cfg = FieldConfig.from_dict(json.loads(str(z["config"])))
        ens = kinds[kind](z["bbox_min"], z["bbox_max"], n_members=int(z["n_members"]),
                          config=cfg, seed=int(z["seed"]), **options)
    except UserError as exc:  # a hand-edited file: name it
        raise UserError(f"{path}: {exc}") from None
    grid = z["grid"]
    if grid.shape != (ens.n_members, ens.layout.n_entries, N_CHANNELS):
        raise UserError(f"{path}: grid shape {grid.shape} does not match its config")
    keys, view = ("grid", "background"), None
    if cfg.view_degree > 0:
        view = z["view"]
        if view.shape != (ens.view_size,):
            raise UserError(f"{path}: view table shape {view.shape} does not match its config")
        keys += ("view",)
    sky = None
    if cfg.background_resolution > 0:
        sky = z["sky"]
        if sky.shape != (ens.sky_size,):
            raise UserError(f"{path}: sky map shape {sky.shape} does not match its config")
        keys += ("sky",)
    adam = None
    if "adam_t" in z:
        adam = {key: (int(z["adam_t"]), z[f"adam_m_{key}"], z[f"adam_v_{key}"]) for key in keys}
    ens._make_optimizer(grid, z["background"], adam, view, sky)
    ens._step = int(z["step"])
    if "occupancy" in z:
        G = int(cfg.occupancy_resolution)
        if z["occupancy"].shape != (G, G, G):
            raise UserError(f"{path}: occupancy shape {z['occupancy'].shape} does not match its config")
        ens._set_occupancy(z["occupancy"].ravel())
    if "occupancy_age" in z:
        ens._occupancy_age = int(z["occupancy_age"])
    return ens
