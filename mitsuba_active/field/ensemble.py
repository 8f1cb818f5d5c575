"""An ensemble of K radiance fields trained together in fused kernels.

All members share one member-interleaved parameter table (``n_entries * K *
4`` floats, see :mod:`mitsuba_active.field.grid`) and one background array
(``K * 3``). A training step samples one batch of ``batch_rays`` rays, looks
up all K members' features of every sample with one packet gather per grid
corner, composites each member, and minimises the *sum* of the members' mean
losses (so each member's gradient equals what it would get if trained
alone); a single Adam update then advances every member.

Randomness (ray batches, sample jitter) comes from integer hashes of the sample
index and an opaque per-step key: deterministic under the seed, and the compiled
kernels are reused from step to step.
"""

from __future__ import annotations

import dataclasses
import json

import drjit as dr
import mitsuba as mi
import numpy as np
from tqdm import tqdm

from ..checks import is_whole
from ..errors import TrainingDiverged, UserError
from ..variant import require_variant
from .batch import draw_batch, ray_order
from .bootstrap import BOOTSTRAP_KINDS, bootstrap_weights, weighted
from .config import MAX_MEMBERS, MAX_STEPS, FieldConfig
from .fisher import fisher_diagonal
from .grid import GridLayout, anneal_weights, half_table, init_grid
from .inputs import checked_rays, padded_rays, point, triples
from .io import load_ensemble, save_ensemble
from .occupancy import cell_opacity
from .regularisers import grid_smoothness, random_background, ray_regularisers
from .render import render_members
from .samples import FieldParams
from .sky import sky_size
from .view import n_coefficients, view_layout


#: Side given to the fields' box where the object is flat (a side at most
#: 1e-6 of the longest), as a fraction of the longest side.
MIN_BOX_SIDE = 0.05

#: A background started at a given colour starts at most this close to 0 or 1
#: per channel (the sigmoid's gradient vanishes at its ends).
BACKGROUND_CLIP = 0.02

#: The optimised parameters that learn at ``FieldConfig.lr_background`` (the others at ``lr``).
BACKGROUND_KEYS = ("background", "sky")


def _member_seeds(seed: int, n: int):
    """Independent per-member seed sequences; member k does not depend on n."""
    return [np.random.SeedSequence(int(seed), spawn_key=(k,)) for k in range(n)]


class Ensemble:
    """K radiance fields on one bounding box, trained on the same rays.

    Args:
        bbox_min, bbox_max: array-likes of 3 floats (scene units), the
            region the fields live in (padded by ``config.bbox_padding``;
            a flat object's zero side is first widened to ``MIN_BOX_SIDE``
            of the longest).
        n_members: K.
        config: :class:`FieldConfig` (defaults if None).
        seed: base seed; member k is initialised from ``(seed, k)``.
        bootstrap: ``"none"``: every member fits every training ray alike;
            ``"rays"`` or ``"views"``: every member but the first fits its
            own resample of them (see :mod:`.bootstrap`).
    """

    #: ``kind`` of the saved file (see :mod:`.io`).
    KIND = "mitsuba_active.field.Ensemble"

    def __init__(self, bbox_min, bbox_max, n_members: int = 4,
                 config: FieldConfig | None = None, seed: int = 0, bootstrap: str = "none"):
        require_variant("Ensemble")
        self._variant = mi.variant()  # its Dr.Jit arrays are of this variant's backend
        if config is not None and not isinstance(config, FieldConfig):
            raise UserError(f"Ensemble: config must be a FieldConfig (e.g. FieldConfig(n_levels=2)), "
                            f"got {type(config).__name__}")
        self.config = config if config is not None else FieldConfig()
        self.bbox_min, self.bbox_max = (point(p, "Ensemble", name) for p, name in ((bbox_min, "bbox_min"),
                                                                                      (bbox_max, "bbox_max")))
        extent = self.bbox_max - self.bbox_min
        if not (np.all(np.isfinite(extent)) and np.all(extent >= 0) and extent.max() > 0):
            raise UserError("Ensemble needs a finite bounding box with bbox_max >= bbox_min, "
                            "not a single point")
        if not is_whole(n_members) or not 1 <= n_members <= MAX_MEMBERS:
            raise UserError(f"Ensemble needs a whole number n_members in [1, {MAX_MEMBERS}], got {n_members!r}")
        self.n_members = int(n_members)
        if not is_whole(seed) or not 0 <= seed < 2**63:  # numpy's seeds, and the file's int64
            raise UserError(f"Ensemble needs a whole number seed in [0, 2^63), got {seed!r}")
        self.seed = int(seed)
        if bootstrap not in BOOTSTRAP_KINDS:
            raise UserError(f"Ensemble: bootstrap must be one of {', '.join(BOOTSTRAP_KINDS)}, got {bootstrap!r}")
        self.bootstrap = bootstrap
        self.layout = GridLayout.from_config(self.config)
        pad = self.config.bbox_padding * extent
        box_min, box_max = self.bbox_min - pad, self.bbox_max + pad
        # A flat object (a sign, a single triangle) has no depth along some
        # axis; the field's box gets MIN_BOX_SIDE of the longest side there.
        # Thin but not flat boxes stay as they are (saved ensembles keep their box).
        flat = extent <= 1e-6 * extent.max()
        if flat.any():
            centre = 0.5 * (self.bbox_min + self.bbox_max)
            half = 0.5 * MIN_BOX_SIDE * extent.max() * (1.0 + 2.0 * self.config.bbox_padding)
            box_min[flat], box_max[flat] = centre[flat] - half, centre[flat] + half
        self.box_min = tuple(float(v) for v in box_min)
        self.box_max = tuple(float(v) for v in box_max)

        seqs = _member_seeds(self.seed, self.n_members)
        grid0 = self._initial_grid(init_grid(self.layout, self.config, seqs))
        bg0 = np.stack([np.random.default_rng(s.spawn(1)[0]).uniform(-0.1, 0.1, 3)
                        for s in seqs]).astype(np.float32)
        self._background0 = bg0
        self._make_optimizer(grid0, bg0)
        self._step = 0
        self._n_rays = 0
        self._rays = None
        self._known_background = False  # set_rays was told the empty rays' colour
        self._reset_occupancy()

    # ------------------------------------------------------------------ state
    def _initial_grid(self, grid: np.ndarray) -> np.ndarray:
        """The starting table (K, E, 4) from the members' seeded draws (a
        subclass with other starting values changes it here)."""
        return grid

    def _make_optimizer(self, grid, bg, adam_state=None, view=None, sky=None):
        """Adam over the grid table (K, E, 4), the backgrounds (K, 3), with
        ``view_degree`` the view-dependent colour's table (flat, as
        :meth:`view_numpy` gives it; None: zeros) and with
        ``background_resolution`` the directional background's (as
        :meth:`sky_numpy` gives it; None: zeros); ``adam_state`` as saved."""
        cfg = self.config
        self._opt = dr.opt.Adam(lr=cfg.lr, beta_1=cfg.beta_1, beta_2=cfg.beta_2,
                                epsilon=cfg.epsilon)
        self._half = None  # (grid table, its float16 copy), see _half_grid
        # (K, E, 4) member-major on the host -> (E, K, 4) interleaved table.
        table = np.ascontiguousarray(np.transpose(np.asarray(grid, np.float32), (1, 0, 2)))
        self._opt["grid"] = mi.Float(table.ravel())
        self._opt["background"] = mi.Float(np.ascontiguousarray(bg, np.float32).ravel())
        if cfg.view_degree > 0:  # a diffuse start: the residual is 0 until views ask for it
            self._opt["view"] = mi.Float(np.zeros(self.view_size, np.float32) if view is None else
                                         np.ascontiguousarray(view, np.float32).ravel())
        if cfg.background_resolution > 0:  # the constant background until views ask for more
            self._opt["sky"] = mi.Float(np.zeros(self.sky_size, np.float32) if sky is None else
                                        np.ascontiguousarray(sky, np.float32).ravel())
        self._opt.set_learning_rate({key: cfg.lr_background for key in BACKGROUND_KEYS if key in self._opt.keys()})
        if adam_state is not None:
            for key, (t, m, v) in adam_state.items():
                value, promoted, lr, _ = self._opt.state[key]
                self._opt.state[key] = (value, promoted, lr,
                                        (mi.UInt32(int(t)), mi.Float(m), mi.Float(v), None))

    def _check_variant(self):
        """UserError unless Mitsuba runs the variant this field was made in (its arrays are of
        that variant's types: in another, every call would fail deep inside Dr.Jit)."""
        if mi.variant() != self._variant:
            raise UserError(f"this {type(self).__name__} was made under Mitsuba variant '{self._variant}', but "
                            f"'{mi.variant()}' is set; call mitsuba.set_variant('{self._variant}') first")

    def params(self, n_samples: int | None = None) -> FieldParams:
        """Current parameters as a :class:`FieldParams` (Dr.Jit arrays), for
        rays of ``n_samples`` samples (None: ``FieldConfig.n_samples``)."""
        self._check_variant()
        cfg = self.config
        return FieldParams(grid=self._opt["grid"], background=self._opt["background"],
                           layout=self._annealed_layout(), box_min=self.box_min, box_max=self.box_max,
                           n_samples=int(cfg.n_samples if n_samples is None else n_samples),
                           density_bias=float(cfg.density_bias),
                           n_members=self.n_members, occupancy=self._occupied,
                           occupancy_resolution=int(cfg.occupancy_resolution),
                           stop_transmittance=float(cfg.stop_transmittance),
                           view=self._opt["view"] if cfg.view_degree > 0 else None,
                           view_degree=int(cfg.view_degree), view_resolution=int(cfg.view_resolution),
                           contraction=float(cfg.contraction),
                           near=float(cfg.near) * float(np.linalg.norm(np.subtract(self.box_max, self.box_min))),
                           sky=self._opt["sky"] if cfg.background_resolution > 0 else None,
                           sky_resolution=int(cfg.background_resolution),
                           half_grid=self._half_grid(), half_of=self._opt["grid"])

    def _half_grid(self, evaluate: bool = True):
        """The grid table's float16 copy that the lookups read (``half_lookups``),
        made once per value of the table, or None (they read the table)."""
        if not self.config.half_lookups:
            return None
        grid = self._opt["grid"]
        if self._half is None or self._half[0] is not grid:
            self._half = (grid, half_table(grid))
            if evaluate:
                dr.eval(self._half[1])
        return self._half[1]

    def _annealed_layout(self) -> GridLayout:
        """The layout with the levels' annealing weights (:func:`.grid.anneal_weights`) as opaque
        scalars (kernels compile once for all steps), or as it is once they are all 1."""
        w = anneal_weights(self.config.n_levels, self.config.anneal_steps, self._step)
        if np.all(w == 1.0):
            return self.layout
        return dataclasses.replace(self.layout, weights=tuple(dr.opaque(mi.Float, float(x)) for x in w))

    @property
    def view_size(self) -> int:
        """Floats of the view-dependent colour's table, all members (0 for a diffuse field)."""
        cfg = self.config
        if cfg.view_degree == 0:
            return 0
        return view_layout(cfg.view_resolution).n_entries * self.n_members * 3 * n_coefficients(cfg.view_degree)

    def view_numpy(self) -> np.ndarray:
        """The view-dependent colour's table as flat float32 (:attr:`view_size`,),
        laid out as in memory (see :mod:`.view`); empty for a diffuse field."""
        return self._numpy("view") if self.config.view_degree > 0 else np.zeros(0, np.float32)

    @property
    def sky_size(self) -> int:
        """Floats of the directional background's map, all members (0 without one)."""
        return sky_size(self.config.background_resolution, self.n_members) if self.config.background_resolution else 0

    def sky_numpy(self) -> np.ndarray:
        """The directional background's map as flat float32 (:attr:`sky_size`,), laid
        out as in memory (see :mod:`.sky`); empty without one."""
        return self._numpy("sky") if self.config.background_resolution > 0 else np.zeros(0, np.float32)

    def options(self) -> dict:
        """Options beyond :class:`FieldConfig` that a saved file keeps (``bootstrap``, when on)."""
        return {} if self.bootstrap == "none" else {"bootstrap": self.bootstrap}

    @property
    def n_outputs(self) -> int:
        """Renders per training step whose photometric losses are summed: K."""
        return self.n_members

    @property
    def n_params(self) -> int:
        """Trainable parameters of one member (grid floats + 3 background; the
        view-dependent colour's table, :meth:`view_numpy`, is apart)."""
        return self.layout.n_grid_params + 3

    def member_params(self, member: int) -> np.ndarray:
        """Flat float32 (P,) parameters of one member: grid then background."""
        self._check_member(member)
        grid = self.grid_numpy()[member].ravel()
        bg = self._numpy("background").reshape(self.n_members, 3)[member]
        return np.concatenate([grid, bg])

    def grid_numpy(self) -> np.ndarray:
        """Grid parameters as float32 (K, n_entries, 4), member-major."""
        t = self._numpy("grid").reshape(self.layout.n_entries, self.n_members, 4)
        return np.ascontiguousarray(np.transpose(t, (1, 0, 2)))

    def _numpy(self, key) -> np.ndarray:
        return np.array(dr.detach(self._opt[key]), dtype=np.float32)

    def _check_member(self, member):
        if not is_whole(member) or not 0 <= member < self.n_members:
            raise UserError(f"member must be a whole number in [0, {self.n_members}), got {member!r}")

    # ------------------------------------------------------------------- data
    def set_rays(self, origins, directions, rgb, distance, hit, reset_occupancy: bool = True, empty=None,
                 background=None):
        """Replace the training rays (parameters and Adam state are kept).

        Args:
            origins: (M,3) ray origins (scene units), directions: (M,3) unit,
            rgb: (M,3) target colour in [0,1], distance: (M,) metric distance
            from the origin to the surface (ignored where ``~hit``), or None
            without distances (then ``config.distance_weight`` must be 0),
            hit: (M,) bool, where ``distance`` is known.
            reset_occupancy: start the occupancy grid over (new rays may show
                surfaces where earlier ones saw empty space); False keeps
                it, e.g. when giving a loaded ensemble back the rays it was
                trained on.
            empty: (M,) bool, the rays known to meet no geometry (the
                empty-ray loss clears them), or None: every ray that does not hit.
            background: the colour (3 floats in [0, 1]) that empty rays are
                known to show (a dataset's images composited on it), or None;
                an untrained ensemble's background starts there.
        """
        self._check_variant()
        o, d = checked_rays(origins, directions, "set_rays")
        c = triples(rgb, "set_rays", "rgb")
        m = o.shape[0]
        if distance is None and self.config.distance_weight > 0:
            raise UserError("set_rays: distance is None, but the distance loss (config.distance_weight "
                            f"= {self.config.distance_weight}) needs the rays' distances")
        dist = np.zeros(m, np.float32) if distance is None else np.asarray(distance, np.float32).reshape(-1)
        h = np.asarray(hit).reshape(-1)
        if h.dtype != bool and not np.isin(h, (0, 1)).all():  # 0.2 would read as a hit
            raise UserError("set_rays: hit must be booleans (or 0 and 1)")
        h = h.astype(bool)
        e = ~h if empty is None else np.asarray(empty).reshape(-1)
        if e.dtype != bool and not np.isin(e, (0, 1)).all():
            raise UserError("set_rays: empty must be booleans (or 0 and 1)")
        e = e.astype(bool)
        for name, n in (("rgb", c.shape[0]), ("distance", dist.shape[0]), ("hit", h.shape[0]),
                        ("empty", e.shape[0])):
            if n != m:
                raise UserError(f"set_rays: {name} describes {n} rays, origins and directions {m}")
        if m == 0:
            raise UserError("set_rays: no rays")
        if m >= 2**31:
            raise UserError("set_rays: too many rays (max 2^31)")
        # Bad rays would only show later, as a diverged loss or NaN distances.
        if not np.isfinite(c).all():
            raise UserError("set_rays: rgb must be finite numbers")
        if c.min() < -1e-3 or c.max() > 1.0 + 1e-3:
            raise UserError(f"set_rays: rgb must lie in [0, 1] (got {c.min():.4g} to {c.max():.4g}; "
                            "divide 8-bit colours by 255)")
        if not (np.isfinite(dist[h]).all() and (dist[h] >= 0).all()):
            raise UserError("set_rays: distance must be a finite number >= 0 where a ray hits")
        dist = np.where(h, dist, 0.0).astype(np.float32)  # unused where nothing is hit
        e = e & ~h  # a ray with a distance met something
        if background is not None:
            bg = np.asarray(background, np.float64).reshape(-1)
            if bg.shape != (3,) or not (np.isfinite(bg).all() and (bg >= 0).all() and (bg <= 1).all()):
                raise UserError(f"set_rays: background must be 3 numbers in [0, 1], got {background!r}")
            if self._step == 0:
                self._start_background(bg)
        self._known_background = background is not None
        self._rays = dict(o=mi.Point3f(o.T), d=mi.Vector3f(d.T), rgb=mi.Color3f(c.T),
                          distance=mi.Float(dist), hit=mi.Bool(h), empty=mi.Bool(e))
        if self.config.coherent_batches:
            self._rays["order"] = mi.UInt32(ray_order(o, d))
        dr.eval(self._rays)
        self._n_rays = m
        if reset_occupancy:
            self._reset_occupancy()

    def _start_background(self, colour):
        """Start every member's background at ``colour`` plus its seeded jitter:
        a field whose background starts far from the known one paints fog in
        front of it faster than the background learns."""
        p = np.clip(colour, BACKGROUND_CLIP, 1.0 - BACKGROUND_CLIP)
        logits = self._background0 + np.log(p / (1.0 - p))[None, :]
        self._opt["background"] = mi.Float(np.ascontiguousarray(logits, np.float32).ravel())

    # -------------------------------------------------------------- occupancy
    def _reset_occupancy(self):
        """No skipping until the warm-up is over (see :mod:`.occupancy`)."""
        self._occupancy = None  # decaying max of cell opacities (mi.Float G^3)
        self._occupied = None  # occupancy > threshold (mi.Bool G^3)
        self._occupancy_age = 0  # training steps since the reset

    def _refresh_occupancy(self):
        """Fold the current fields' cell opacities into the grid."""
        cfg = self.config
        key = dr.opaque(mi.UInt32, (self.seed * 0x2545F491 + self._step * 0x9E3779B9) & 0xFFFFFFFF)
        value = cell_opacity(self.params(), cfg.occupancy_resolution, key)
        if self._occupancy is not None:
            value = dr.maximum(value, self._occupancy * float(cfg.occupancy_decay))
        self._set_occupancy(value)

    def _set_occupancy(self, value):
        self._occupancy = mi.Float(value)
        self._occupied = self._occupancy > float(self.config.occupancy_threshold)
        dr.eval(self._occupancy, self._occupied)

    def occupancy(self) -> np.ndarray | None:
        """Occupied cells as a bool (G, G, G) array indexed [z, y, x], or None
        while nothing is skipped (skipping off, or still warming up)."""
        if self._occupied is None:
            return None
        G = int(self.config.occupancy_resolution)
        return np.array(self._occupied, dtype=bool).reshape(G, G, G)

    # --------------------------------------------------------------- training
    def _training_samples(self) -> int:
        """Samples a ray of the next training step takes (see ``FieldConfig.coarse_steps``)."""
        cfg = self.config
        n = int(cfg.n_samples)
        coarse = cfg.occupancy_resolution > 0 and self._step < int(cfg.coarse_steps)
        return max(1, n // 2) if coarse else n

    def _batch(self):
        """Ray indices and per-sample jitter of this step (:func:`.batch.draw_batch`).

        All members see the same rays and samples in a step (that is what
        lets them share one lookup kernel); they differ by initialisation.
        """
        cfg = self.config
        order = self._rays["order"] if cfg.coherent_batches else None
        return draw_batch(self.seed, self._step, self._n_rays, int(cfg.batch_rays), self._training_samples(), order)

    def ray_weights(self, origins, indices) -> np.ndarray:
        """(K, N) float32 weights of training rays in each member's loss:
        ``indices`` (N,) of the rays among those set, ``origins`` (N, 3) of
        them; all ones without ``bootstrap``."""
        self._check_variant()
        o = triples(origins, "ray_weights", "origins")
        idx = np.asarray(indices, np.int64).reshape(-1)
        if idx.shape[0] != o.shape[0] or (idx < 0).any() or (idx >= 2**32).any():
            raise UserError("ray_weights: one index in [0, 2^32) per origin")
        w = bootstrap_weights(self.bootstrap, self.seed, self.n_members, mi.UInt32(idx.astype(np.uint32)),
                              mi.Point3f(o.T)) or [np.ones(len(idx), np.float32)] * self.n_members
        return np.stack([np.array(wk, np.float32).reshape(-1) for wk in w])

    def training_loss(self):
        """Trace (do not evaluate) the loss of the next training step.

        Returns:
            (mse, loss): ``mi.Float`` scalars; ``mse`` is the photometric
            squared error summed over members (divide by :attr:`n_outputs` for the mean),
            ``loss`` adds the distance and empty-ray terms. Call ``dr.backward(loss)`` and
            :meth:`optimizer_step` to take the step (what :meth:`train` does).
        """
        self._check_variant()
        if self._rays is None:
            raise UserError("train: call set_rays() first")
        cfg = self.config
        N = int(cfg.batch_rays)
        idx, jitter = self._batch()
        R = self._rays
        o = dr.gather(mi.Point3f, R["o"], idx)
        d = dr.gather(mi.Vector3f, R["d"], idx)
        target = dr.gather(mi.Color3f, R["rgb"], idx)
        reg = ray_regularisers(cfg, self._training_samples())
        outs, regulariser = self._training_outputs(o, d, jitter, reg)
        if cfg.random_background and self._known_background:
            target, outs = random_background(self.params(), self._rays, idx, target, outs, self.seed, self._step)
        # Sum of the members' mean losses: each member gets the gradient
        # it would get if trained alone (on its resample, with ``bootstrap``).
        weights = bootstrap_weights(self.bootstrap, self.seed, self.n_members, idx, o)
        if weights is not None:
            outs = [{**out, "weight": w} for out, w in zip(outs, weights)]
        sq = 0.0
        for out in outs:
            sq = sq + weighted(out, dr.squared_norm(out["rgb"] - target))
        mse = dr.sum(sq) * (1.0 / (N * 3))
        loss = mse + regulariser
        if reg is not None:
            loss = loss + 1.0 / N * dr.sum(sum(weighted(out, out["regulariser"]) for out in outs))
        if cfg.smoothness_weight > 0:
            loss = loss + float(cfg.smoothness_weight) * grid_smoothness(self._opt["grid"], self.layout, self.n_members)
        dw, ew = float(cfg.distance_weight), float(cfg.empty_weight)
        if ew > 0:
            # Rays that meet nothing should see the background colour, not
            # fog painted in front of it.
            empty = dr.gather(mi.Bool, R["empty"], idx)
            esq = 0.0
            for out in outs:
                esq = esq + weighted(out, dr.select(empty, dr.square(out["opacity"]), 0.0))
            loss = loss + ew / N * dr.sum(esq)
        if dw > 0:
            hit = dr.gather(mi.Bool, R["hit"], idx)
            inv_diag2 = 1.0 / float(np.sum(np.subtract(self.box_max, self.box_min) ** 2))
            dt = dr.gather(mi.Float, R["distance"], idx)
            dsq = 0.0
            for out in outs:
                dsq = dsq + weighted(out, dr.square(dr.select(hit, out["distance"] - dt, 0.0)))
            loss = loss + dw * inv_diag2 / N * dr.sum(dsq)
        return mse, loss

    def _training_outputs(self, o, d, jitter, reg=None):
        """Renders of a training batch (one per member; with ``reg``, see
        :func:`.regularisers.ray_regularisers`, each has its ``regulariser``)
        and a loss term added to theirs (none here)."""
        return render_members(self.params(self._training_samples()), o, d, jitter, reg=reg), 0.0

    def optimizer_step(self):
        """Apply one Adam update from the accumulated gradients (and refresh
        the occupancy grid when one is due)."""
        self._check_variant()
        cfg = self.config
        if cfg.lr_decay_steps > 0:
            self._decay_learning_rates(0.1 ** (self._step / cfg.lr_decay_steps))
        self._opt.step(eval=False)
        # The lookups' float16 copy is written by the update's own kernel.
        dr.schedule(self._half_grid(evaluate=False))
        dr.eval()
        self._step += 1
        if cfg.occupancy_resolution > 0:
            self._occupancy_age += 1
            # The age is counted after each step, so a warm-up of 0 refreshes after the first step.
            since = self._occupancy_age - max(1, int(cfg.occupancy_warmup))
            # Not while annealing: the coarse levels alone are too faint for the threshold.
            annealing = self._step < int(cfg.anneal_steps)
            if since >= 0 and not annealing and (since % int(cfg.occupancy_interval) == 0
                                                 or self._occupancy is None):
                self._refresh_occupancy()

    def _decay_learning_rates(self, factor: float):
        """Every parameter's learning rate, times ``factor``."""
        cfg = self.config
        rates = {key: factor * (cfg.lr_background if key in BACKGROUND_KEYS else cfg.lr)
                 for key in self._opt.keys()}
        self._opt.set_learning_rate(rates)

    def train(self, steps: int, progress: bool = False) -> np.ndarray:
        """Run ``steps`` Adam steps on all members; returns (steps,) float64
        photometric MSE averaged over members (per step, before the update).

        Raises:
            UserError: no rays set; TrainingDiverged (a UserError): the loss became NaN/inf.
        """
        if not is_whole(steps) or not 0 <= steps <= MAX_STEPS:
            raise UserError(f"train: steps must be a whole number in [0, {MAX_STEPS:,}], got {steps!r}")
        K = self.n_outputs
        losses = np.zeros(int(steps), np.float64)
        it = range(int(steps))
        bar = None
        if progress:
            bar = tqdm(it, desc="field", unit="step")
            it = bar
        for j in it:
            mse, loss = self.training_loss()
            dr.backward(loss)
            self.optimizer_step()
            # One read-back per step (it synchronises): photometric MSE and
            # total loss, the latter to catch a diverging distance term too.
            both = np.array(dr.detach(mi.Vector2f(mse, loss))).ravel()
            value = float(both[0]) / K
            losses[j] = value
            if not np.all(np.isfinite(both)):
                if bar is not None:
                    bar.close()
                # Large loss weights diverge as a large learning rate does: name those set.
                names = ("distance_weight", "empty_weight", "distortion_weight", "occlusion_weight",
                         "smoothness_weight")
                weights = [f"{n} = {getattr(self.config, n):g}" for n in names if getattr(self.config, n) > 0]
                lower = "FieldConfig.lr" + (f" or the loss weights ({', '.join(weights)})" if weights else "")
                raise TrainingDiverged(f"training diverged at step {self._step} (loss {value}); lower {lower} "
                                       "and start from a new ensemble (this one's parameters are no longer finite)")
            if bar is not None and (j % 10 == 0):
                bar.set_postfix(mse=f"{value:.4g}")
        return losses

    # -------------------------------------------------------------- inference
    def render_dr(self, params, o, d, offset: int = 0):
        """Render Dr.Jit rays (``mi.Point3f`` origins, ``mi.Vector3f`` unit
        directions) with ``params`` (:meth:`params`), deterministically: a list of
        one :func:`.render.render_flat` dict per member. ``offset``: the index of
        the first ray among all rendered (a VariationalField's draws follow it)."""
        return render_members(params, o, d)

    def _render_all(self, origins, directions):
        """Render every ray with every member; numpy (K, N, ...) outputs."""
        rays = padded_rays(origins, directions, self.config.render_batch)
        rgb, dist, opac = [], [], []
        params = self.params()
        with dr.suspend_grad():
            for s, o, d in rays.batches():
                outs = self.render_dr(params, o, d, s)
                dr.eval(outs)
                rgb.append([np.array(out["rgb"]).T for out in outs])
                dist.append([np.array(out["distance"]) for out in outs])
                opac.append([np.array(out["opacity"]) for out in outs])
        # (batches, K, B, ...) -> (K, N, ...)
        return tuple(np.concatenate(np.asarray(a, np.float32), axis=1)[:, :rays.n] for a in (rgb, dist, opac))

    def render(self, origins, directions) -> dict:
        """Render (N,3) rays with every member.

        Returns:
            dict: ``rgb`` (K,N,3) in [0,1], ``distance`` (K,N) expected metric
            distance of the hit from the origin, given a hit (the mean depth of
            whatever density a ray meets, however faint; it falls to 0 only
            below an opacity of 1e-6, and is 0 for a ray that misses the box),
            ``opacity`` (K,N).
        """
        rgb, dist, opac = self._render_all(origins, directions)
        return dict(rgb=rgb, distance=dist, opacity=opac)

    def predict(self, origins, directions) -> dict:
        """Per-ray statistics across members.

        Returns:
            dict: ``rgb_mean`` (N,3), ``rgb_var`` (N,3) population variance
            across members per channel (zeros for K=1), ``distance_mean`` (N,),
            ``distance_var`` (N,), ``opacity`` (N,) mean over members.
        """
        out = self.render(origins, directions)
        return dict(rgb_mean=out["rgb"].mean(0), rgb_var=out["rgb"].var(0),
                    distance_mean=out["distance"].mean(0),
                    distance_var=out["distance"].var(0),
                    opacity=out["opacity"].mean(0))

    # ----------------------------------------------------------------- fisher
    def fisher_diag(self, origins, directions, member: int = 0, probes: int = 1,
                    seed: int = 0) -> np.ndarray:
        """Hutchinson estimate of diag(J^T J) for one member: (P,) float64, in
        :meth:`member_params`' order (see :mod:`.fisher`)."""
        self._check_variant()
        self._check_member(member)
        return fisher_diagonal(self, origins, directions, member, probes, seed)

    # ----------------------------------------------------------------- save
    def save(self, path):
        """Write the ensemble to ``path`` (.npz, see :mod:`.io`)."""
        return save_ensemble(self, path)

    @classmethod
    def load(cls, path) -> "Ensemble":
        """Read an ensemble written by :meth:`save`."""
        return load_ensemble(cls, path)

    def __repr__(self):
        return (f"Ensemble(K={self.n_members}, P={self.n_params}, rays={self._n_rays}, "
                f"step={self._step}, config={json.dumps(self.config.to_dict())})")
