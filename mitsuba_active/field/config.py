"""Options of the radiance field (:class:`FieldConfig`).

Every option is a plain number so that the config round-trips through JSON
(it is stored inside saved ensembles, see :mod:`mitsuba_active.field.io`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ..checks import is_number, is_whole, unknown_choice
from ..errors import UserError


#: Most grid levels, cells per axis of the finest level, and samples (rays x
#: samples per ray) in one training or render batch of one member.
MAX_LEVELS = 16
MAX_RESOLUTION = 1 << 16
MAX_BATCH_SAMPLES = 1 << 24
#: Most members of an ensemble, and most steps of one training call (far
#: beyond any use: each member holds its own tables and Adam moments).
MAX_MEMBERS = 64
MAX_STEPS = 10_000_000
#: Most rows of the directional background's map (``background_resolution``).
MAX_SKY_RESOLUTION = 256
#: Rows of the map that a capture with a far background gets: a texel of
#: about 11 degrees is seen by several of 20 views, where finer maps only
#: memorise each view's own backdrop (docs/field.md, "Unbounded scenes").
CAPTURE_SKY_RESOLUTION = 16
#: Farthest reach of a contracted field, in half box sizes (past it the
#: contracted shell is thinner than float32 resolves near its edge).
MAX_CONTRACTION = 1e5


#: Levels of the hash grid from 100-pixel images on, the cells per axis of its
#: coarsest, and log2 of each hashed level's table (2^15 entries of 4 floats,
#: 512 KiB a member: a level's table stays in the L2 cache).
HASH_LEVELS = 12
HASH_BASE = 16
HASH_LOG2_TABLE = 15
#: Levels of the hash grid whose finest level has the given cells (64: images
#: of 100-128 pixels), where twelve levels, 1.13 times apart, would be more than
#: a fourfold range needs: six (1.32 apart) scored as well or better held out
#: and train in about half the time (docs/field-measurements.md).
HASH_LEVELS_BY_FINEST = {64: 6}
#: The evaluation field's ``occupancy_decay`` where its finest level has the
#: given cells (64: images of 100-128 pixels): its occupancy grid forgets the
#: early fog within about 7 refreshes, which halves the training there; on a
#: finer grid (Mic at 200 pixels) it cost 0.4 dB and no time, so there the
#: grid keeps FieldConfig's decay.
OCCUPANCY_DECAY_BY_FINEST = {64: 0.5}
#: The hash grids' ``coarse_steps``: a third of an evaluation field's 1,500
#: steps, the fog phase that cost more than the other two thirds at 128 px
#: (docs/field-measurements.md).
COARSE_STEPS = 500
#: ``FieldConfig.occupancy_decay``'s default.
OCCUPANCY_DECAY = 0.95
#: The hash grids' view-dependent colour up to a finest level of 64 cells
#: (images up to 128 pixels), and from 128 cells (from 200 pixels): there
#: degree 2 on 16 cells scored 0.25 dB more held out on Mic than degree 1
#: on 8 from 20 views, 0.5 dB more from 100 (docs/field-measurements.md).
VIEW_COARSE = {"view_degree": 1, "view_resolution": 8}
VIEW_FINE = {"view_degree": 2, "view_resolution": 16}


def image_scaled_grid(width: int) -> dict:
    """Grid options for images ``width`` pixels across.

    The finest level has about half as many cells across as the images have
    pixels (32 to 256 cells), a ray twice as many samples as that level has
    cells (64 to 256). Up to 64 pixels: two dense levels (16, 32 cells).
    From 100 pixels: a hash grid of 12 levels (6 where the finest has 64
    cells: :data:`HASH_LEVELS_BY_FINEST`) from 16 cells to that finest,
    in equal ratios, the levels whose vertices fit 2^15 entries dense, the
    others hashed into 2^15; empty space is skipped (the occupancy grid
    forgetting at :data:`OCCUPANCY_DECAY_BY_FINEST`) and the first
    :data:`COARSE_STEPS` steps take half the samples, the colour also depends
    on the view (degree 1 on 8 cells, from 200 pixels degree 2 on 16:
    :data:`VIEW_FINE`) and the distortion loss (0.01) keeps the weights
    compact.

    Finer levels than the images resolve only memorise the few views there
    are: at 64 pixels, 20 views of the bundled scene scored 22.9 dB held out
    with five levels and 30.7 dB with two (docs/field.md).
    """
    finest = min(256, max(32, 1 << max(0, round(math.log2(max(1, int(width)) / 2)))))
    if finest <= 32:
        return {"n_levels": 2, "n_samples": 64, "occupancy_resolution": 0}
    levels = HASH_LEVELS_BY_FINEST.get(finest, HASH_LEVELS)
    return {"n_levels": levels, "base_resolution": HASH_BASE,
            "per_level_scale": (finest / HASH_BASE) ** (1.0 / (levels - 1)),
            "log2_table_size": HASH_LOG2_TABLE, "n_samples": min(256, 2 * finest),
            "occupancy_resolution": 64, "coarse_steps": COARSE_STEPS,
            "occupancy_decay": OCCUPANCY_DECAY_BY_FINEST.get(finest, OCCUPANCY_DECAY),
            **(VIEW_FINE if finest >= 128 else VIEW_COARSE), "distortion_weight": 0.01}


@dataclass(frozen=True)
class FieldPreset:
    """Named settings of a run's fields (``--field NAME``).

    Attributes:
        options: :class:`FieldConfig` options over its defaults, of the
            evaluation field and the planner's ensemble.
        planner: options over those for the planner's ensemble alone.
        summary: one line for ``--help`` and the docs.
        image_scaled: the evaluation field's grid follows the images'
            width (:func:`image_scaled_grid`).
    """

    options: dict
    planner: dict
    summary: str
    image_scaled: bool = False

    def config_options(self, width: int | None = None, planner: bool = False) -> dict:
        """The FieldConfig options for images ``width`` pixels across (None: as
        :attr:`options` give them), of the evaluation field or the planner's ensemble."""
        options = dict(self.options)
        if self.image_scaled and width is not None:
            options.update(image_scaled_grid(width))
        if planner:
            options.update(self.planner)
        return options


#: From 5 to 20 views a gentler learning rate than FieldConfig's (which suits
#: 50+ views) generalises better, and the empty-ray loss keeps the background
#: out of the volume wherever the views say what is empty. The planner's
#: ensemble stays on two dense levels: its K members train at every round,
#: and finer levels' disagreement marks detail, not unseen parts (docs/field.md).
FIELD_PRESETS = {
    "fast": FieldPreset({"n_levels": 2, "lr": 0.01, "empty_weight": 0.01}, {},
                        "two dense levels (16, 32 cells), 64 samples a ray: for tests and quick sweeps"),
    "default": FieldPreset({"n_levels": 2, "log2_table_size": 18, "lr": 0.01, "empty_weight": 0.01},
                           {"n_levels": 2, "per_level_scale": 2.0, "log2_table_size": 17, "n_samples": 64,
                            "occupancy_resolution": 0, "coarse_steps": 0, "occupancy_decay": OCCUPANCY_DECAY,
                            "view_degree": 0,
                            "distortion_weight": 0.0},
                           "a grid that follows the images' width: fast's up to 64 pixels; from 100, a "
                           "12-level hash grid (6 levels at 100-128 pixels) from 16 cells to half the width (up to "
                           "256), twice as many samples a ray (up to 256), empty-space skipping, view-dependent "
                           "colour and the distortion loss",
                           image_scaled=True),
}
#: The preset of runs that do not name one.
DEFAULT_PRESET = "default"
#: The preset that run records written before presets existed trained with.
LEGACY_PRESET = "fast"


@dataclass(frozen=True)
class FieldConfig:
    """Model, renderer and optimiser options of an :class:`Ensemble`.

    Frozen: an ensemble keeps the config it was made with, so one config may
    be shared; ``dataclasses.replace(config, lr=0.02)`` makes a changed copy.

    Grid
    ----
    n_levels:
        Number of grid levels. Level ``l`` has ``base_resolution *
        per_level_scale**l`` cells per axis of the padded bounding box.
        Two levels (16 and 32 cells, both dense) fitted held-out views of
        50-view captures better than four (up to 128 cells, the finer two
        hashed) at 64 to 256 pixels, and train 2x faster; a third level
        fits fine texture at 256 pixels slightly better (docs/field.md).
    base_resolution:
        Cells per axis of the coarsest level.
    per_level_scale:
        Resolution factor between consecutive levels.
    log2_table_size:
        log2 of the maximum number of vertices stored per level. Levels whose
        ``(res+1)**3`` vertices fit are stored densely (no collisions); finer
        levels are hashed into a table of this size (Instant-NGP style).
    half_lookups:
        1 (the default): the lookups read a float16 copy of the grid table,
        made anew by every optimiser step, while the gradients and the
        optimiser's parameters stay float32 (Instant-NGP's mixed
        precision): half the bytes and fewer instructions per corner on
        the CPU, at equal held-out PSNR (docs/field-measurements.md). 0:
        they read the float32 table.
    anneal_steps:
        Coarse-to-fine annealing of the levels (FreeNeRF's frequency mask
        on grid levels): level 0 always counts, level ``l``'s features are
        weighted ``clip(step / anneal_steps * (n_levels - 1) - l + 1, 0, 1)``,
        so the finest reaches 1 at ``anneal_steps``; renders use the current
        weights, and empty-space skipping waits until it is over. 0 (the
        default) turns it off.
    n_features:
        Features per vertex; fixed at 4: (density logit, red, green, blue
        logits). The levels' trilinearly interpolated features are summed,
        so the "decoder" is just ``exp`` for density and a sigmoid for colour
        (no MLP: a tensor MLP costs more than the whole grid on a CPU).
    init_scale:
        Features start uniform in ``[-init_scale, init_scale]``. A visible
        scale matters: it is what makes ensemble members disagree where no
        training ray constrains them.
    density_bias:
        Added to the density logit. Density in 1/scene-unit is
        ``exp(logit + density_bias) / diag`` where ``diag`` is the padded
        bounding-box diagonal, so an untrained field has an optical depth of
        about ``exp(density_bias)`` along a diagonal.
    bbox_padding:
        The bounding box is grown by this fraction of its size on every side
        before the grid is laid out and rays are clipped.
    contraction:
        0 (the default): the field lives in the padded box and rays are
        sampled between their entry and exit of it. ``F`` > 1: the scene
        reaches ``F`` times the padded box's half size from its centre
        (instant-ngp's ``aabb_scale``), for captures whose background lies
        far beyond the object: positions in the box's normalised
        coordinates ``x`` (the box is ``[-1, 1]^3``) are contracted as in
        mip-NeRF 360 with the max-norm, ``x`` where ``|x| <= 1``, else
        ``(2 - 1/|x|) x/|x|``, so the grids cover the cube ``[-2, 2]^3``
        and the box keeps an undistorted half of each axis. Half of a ray's
        samples lie uniformly in the box, the rest beyond it, evenly spaced
        in contracted space (linear in disparity from the centre) up to
        ``F``; rays that miss the box get all of them there. Distances stay
        metric (see docs/field.md, "Unbounded scenes").
    background_resolution:
        0 (the default): each member's background is one learnt colour.
        ``N``: plus a learnt latitude-longitude map of ``N x 2N`` texels,
        so that every ray's background depends on its direction, as the
        world beyond a real capture's box does (see
        :mod:`mitsuba_active.field.sky`).

    Rendering
    ---------
    n_samples:
        Stratified samples per ray between the entry and exit of the padded
        box (64 by default). Kernels are compiled for this block size.
    render_batch:
        Most rays per member in one render kernel. A call's rays are padded
        to the next power of two (at least 64) below this, or to a whole
        number of such batches, so compiled kernels are reused.

    near:
        Samples start at least this fraction of the padded box's diagonal
        from a ray's origin (0: at the box, or at the camera inside it).
        Cameras inside a room see no empty rays that would clear the space
        in front of them; a near distance keeps each view from explaining
        itself with density just before its own lens (see docs/field.md,
        "Rooms").

    Training
    --------
    batch_rays:
        Rays per member per step, sampled uniformly with replacement from all
        training rays (4096 by default).
    coherent_batches:
        1: each step draws one ray from each of ``batch_rays`` equal strata
        of the training rays sorted by camera position and direction, so
        that neighbouring rays are marched together and share cached grid
        cells (every ray is as likely as before; see
        :mod:`mitsuba_active.field.batch`); 0 (the default): independent draws.
    lr, beta_1, beta_2, epsilon:
        Adam options (``drjit.opt.Adam``).
    lr_background:
        Learning rate of the per-member background colour logits.
    lr_decay_steps:
        Every learning rate falls tenfold over this many steps, smoothly
        (``0.1 ** (step / lr_decay_steps)``); 0 (the default): constant.
        Long runs (thousands of steps over many views) settle below the
        constant rate's noise with it.
    distance_weight:
        Weight of the distance loss (mean over the batch of ``hit *
        (d_pred - d_true)**2 / diag**2``); 0 disables it.
    empty_weight:
        Weight of the empty-ray loss (mean over the batch of ``(1 - hit) *
        opacity**2``): rays that hit nothing should reach the background.
        Without it a field may paint the background as fog at the far side
        of the box, which also leaves no empty space to skip; 0 disables it.

    Few-view regularisers (see :mod:`mitsuba_active.field.regularisers`)
    -------------------------------------------------------------------
    distortion_weight:
        Weight of mip-NeRF 360's distortion loss (mean over the batch of
        ``sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 / n_samples``, with
        the samples' distances ``m`` normalised by the ray's length in the
        box): it gathers a ray's weight into one short stretch, against
        floaters and fog; 0 (the default) disables it.
    occlusion_weight:
        Weight of FreeNeRF's occlusion penalty (mean over the batch of the
        optical depth of each ray's first samples in the box): density
        right in front of the training cameras is what few views fit with
        floaters; 0 (the default) disables it.
    smoothness_weight:
        Weight of a total-variation prior on the grid (Plenoxels'): the
        mean over the vertices of each dense level, and the three axes, of
        the squared difference of a vertex's 4 features from its neighbour's,
        summed over the dense levels (hashed levels have no neighbours to
        compare). Without a network between the grid and the colours,
        nothing else ties a vertex to the ones beside it; 0 (the default)
        disables it.
    occlusion_fraction:
        The leading fraction of a ray's samples (of its length in the box)
        that the occlusion penalty covers (at least one sample), in (0, 1].
    random_background:
        1: at each step, the rays known empty of views whose background
        colour is known (a dataset's transparent pixels, ``set_rays(...,
        empty=, background=)``) show a random colour per ray, as target and
        as the prediction's background (Instant-NGP's trick): the volume
        cannot paint the background in, only stay empty there. Other rays
        keep the learnt background. 0 (the default): off.

    View dependence (see :mod:`mitsuba_active.field.view`)
    ------------------------------------------------------
    view_degree:
        Degree (1 or 2) of the spherical harmonics of the view direction
        that add a colour residual at each ray's hit, for glossy surfaces;
        0 (the default): a diffuse field.
    view_resolution:
        Cells per axis of the dense grid of the residual's coefficients.

    Empty-space skipping (see :mod:`mitsuba_active.field.occupancy`)
    ------------------------------------------------------------------
    occupancy_resolution:
        Cells per axis of the occupancy grid; 0 (the default) turns skipping
        off. 32-64 suits objects in their box, fitted from many views
        (with few views it cost held-out PSNR; see docs/field.md).
    occupancy_threshold:
        A cell is skipped while every member's opacity over one sample step
        there stays below this.
    occupancy_interval:
        Training steps between refreshes of the grid.
    occupancy_decay:
        Factor applied to the grid's stored opacities at every refresh
        before the new ones are folded in (a decaying maximum), in (0, 1].
        Near 1 a cell that was foggy early on stays occupied, and costs its
        lookups, long after its density has gone; the default (0.95,
        Instant-NGP's) keeps it about 90 refreshes. The ``default`` preset's
        evaluation field at 100-128 pixels forgets within about 7 (0.5,
        :data:`OCCUPANCY_DECAY_BY_FINEST`): on the bundled
        scene at 128 px its 1,500 steps took 0.62 times as long at 0.03 dB
        less held-out PSNR (docs/field-measurements.md).
    occupancy_warmup:
        Training steps without skipping after the rays are set (or
        replaced), before the first refresh (0 acts as 1: the first grid
        comes from the fields after one step).
    stop_transmittance:
        With skipping, a ray's march stops once every member's transmittance
        has fallen below this (early ray termination; Instant-NGP's 1e-4):
        the samples behind would add less than this to its colour, and
        neither their colours nor their gradients are computed. 0: every
        occupied sample is marched.
    coarse_steps:
        With skipping, the first training steps take half of ``n_samples``
        a ray (bins twice as long): early on the field is fog that the
        occupancy grid cannot skip yet, and those steps cost most. 0: off.
    """

    n_levels: int = 2
    base_resolution: int = 16
    per_level_scale: float = 2.0
    log2_table_size: int = 17
    half_lookups: int = 1
    anneal_steps: int = 0
    n_features: int = 4
    init_scale: float = 0.1
    density_bias: float = -1.0
    bbox_padding: float = 0.05
    contraction: float = 0.0
    background_resolution: int = 0
    n_samples: int = 64
    near: float = 0.0
    render_batch: int = 4096
    batch_rays: int = 4096
    coherent_batches: int = 0
    lr: float = 0.05
    lr_background: float = 0.02
    lr_decay_steps: int = 0
    beta_1: float = 0.9
    beta_2: float = 0.99
    epsilon: float = 1e-8
    distance_weight: float = 0.0
    empty_weight: float = 0.0
    distortion_weight: float = 0.0
    occlusion_weight: float = 0.0
    smoothness_weight: float = 0.0
    occlusion_fraction: float = 0.1
    random_background: int = 0
    view_degree: int = 0
    view_resolution: int = 8
    occupancy_resolution: int = 0
    occupancy_threshold: float = 0.01
    occupancy_interval: int = 16
    occupancy_decay: float = OCCUPANCY_DECAY
    occupancy_warmup: int = 64
    stop_transmittance: float = 1e-4
    coarse_steps: int = 0

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not is_number(value, finite=True):
                raise UserError(f"FieldConfig.{f.name} must be a finite number, got {value!r}")
            if isinstance(f.default, int) and not is_whole(value):
                raise UserError(f"FieldConfig.{f.name} must be a whole number, got {value!r}")
        if self.n_features != 4:
            raise UserError("FieldConfig.n_features must be 4 (density + RGB)")
        # Ranges where training means what the option says (a negative rate
        # would climb the loss without any error).
        positive = ("per_level_scale", "lr", "epsilon")
        non_negative = ("init_scale", "bbox_padding", "near", "lr_background", "distance_weight", "empty_weight",
                        "distortion_weight", "occlusion_weight", "smoothness_weight")
        for name in positive:
            if not getattr(self, name) > 0:
                raise UserError(f"FieldConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in non_negative:
            if not getattr(self, name) >= 0:
                raise UserError(f"FieldConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not (0 <= self.beta_1 < 1 and 0 <= self.beta_2 < 1):
            raise UserError("FieldConfig.beta_1 and beta_2 must be in [0, 1)")
        for name in ("n_levels", "base_resolution", "log2_table_size", "n_samples",
                     "render_batch", "batch_rays"):
            if int(getattr(self, name)) < 1:
                raise UserError(f"FieldConfig.{name} must be >= 1")
        if not 0 <= int(self.lr_decay_steps) <= MAX_STEPS:
            raise UserError(f"FieldConfig.lr_decay_steps must be in [0, {MAX_STEPS}] (0: constant)")
        if not 0 <= int(self.anneal_steps) <= MAX_STEPS:
            raise UserError(f"FieldConfig.anneal_steps must be in [0, {MAX_STEPS}] (0: off)")
        if not 1 <= self.log2_table_size <= 26:
            raise UserError("FieldConfig.log2_table_size must be in [1, 26]")
        # Upper bounds where larger values only exhaust memory or overflow
        # the grid's 32-bit vertex coordinates, instead of a clear message.
        if self.n_levels > MAX_LEVELS:
            raise UserError(f"FieldConfig.n_levels must be at most {MAX_LEVELS}, got {self.n_levels}")
        # In logarithms: per_level_scale ** (n_levels - 1) may overflow a float.
        log_finest = math.log(self.base_resolution) + (self.n_levels - 1) * math.log(self.per_level_scale)
        if log_finest > math.log(MAX_RESOLUTION):
            raise UserError(f"FieldConfig: the finest level would have more than {MAX_RESOLUTION} cells per axis "
                            f"(base_resolution * per_level_scale ** (n_levels - 1))")
        if self.near >= 1:
            raise UserError(f"FieldConfig.near must be below 1 (a fraction of the box's diagonal), got {self.near}")
        if self.bbox_padding > 1:
            raise UserError(f"FieldConfig.bbox_padding must be at most 1 (a fraction of the box per side), "
                            f"got {self.bbox_padding}")
        if not (self.contraction == 0 or 1 < self.contraction <= MAX_CONTRACTION):
            raise UserError(f"FieldConfig.contraction must be 0 (off) or in (1, {MAX_CONTRACTION:g}] (how many "
                            f"half box sizes the scene reaches), got {self.contraction}")
        if self.contraction and self.n_samples < 2:
            raise UserError("FieldConfig: a contracted field needs n_samples >= 2 (half in the box, half beyond)")
        for name in ("batch_rays", "render_batch"):
            if getattr(self, name) * self.n_samples > MAX_BATCH_SAMPLES:
                raise UserError(f"FieldConfig: {name} x n_samples = {getattr(self, name) * self.n_samples} "
                                f"samples per batch, more than {MAX_BATCH_SAMPLES}")
        if not 0 <= int(self.view_degree) <= 2 or not 1 <= int(self.view_resolution) <= 256:
            raise UserError("FieldConfig.view_degree must be in [0, 2] (0: diffuse) and view_resolution in [1, 256]")
        if not 0 < self.occlusion_fraction <= 1:
            raise UserError(f"FieldConfig.occlusion_fraction must be in (0, 1], got {self.occlusion_fraction}")
        if self.half_lookups not in (0, 1):
            raise UserError(f"FieldConfig.half_lookups must be 0 (float32) or 1 (float16), got {self.half_lookups}")
        if self.coherent_batches not in (0, 1):
            raise UserError(f"FieldConfig.coherent_batches must be 0 (off) or 1, got {self.coherent_batches}")
        if self.random_background not in (0, 1):
            raise UserError(f"FieldConfig.random_background must be 0 (off) or 1, got {self.random_background}")
        if not 0 <= int(self.background_resolution) <= MAX_SKY_RESOLUTION:
            raise UserError(f"FieldConfig.background_resolution must be in [0, {MAX_SKY_RESOLUTION}] (0: one colour), "
                            f"got {self.background_resolution}")
        if not 0 <= int(self.occupancy_resolution) <= 256:
            raise UserError("FieldConfig.occupancy_resolution must be in [0, 256] (0: off)")
        if not self.occupancy_threshold > 0 or int(self.occupancy_interval) < 1 \
                or int(self.occupancy_warmup) < 0:
            raise UserError("FieldConfig: occupancy_threshold must be > 0, occupancy_interval >= 1 "
                            "and occupancy_warmup >= 0")
        if not 0 < self.occupancy_decay <= 1:
            raise UserError(f"FieldConfig.occupancy_decay must be in (0, 1], got {self.occupancy_decay}")
        if int(self.coarse_steps) < 0:
            raise UserError(f"FieldConfig.coarse_steps must be >= 0 (0: off), got {self.coarse_steps}")
        if not 0 <= self.stop_transmittance < 1:
            raise UserError(f"FieldConfig.stop_transmittance must be in [0, 1) (0: off), got {self.stop_transmittance}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def preset(cls, name: str, width: int | None = None, planner: bool = False, **options) -> "FieldConfig":
        """The config of the preset ``name`` (:data:`FIELD_PRESETS`) for images
        ``width`` pixels across: its evaluation field's, or with ``planner``
        its planner's ensemble's; ``options`` over it.

        Raises:
            UserError: an unknown preset.
        """
        if name not in FIELD_PRESETS:
            raise UserError(unknown_choice("field preset", name, FIELD_PRESETS))
        return cls(**{**FIELD_PRESETS[name].config_options(width, planner), **options})

    @classmethod
    def from_options(cls, items, **base) -> "FieldConfig":
        """A config from ``OPTION=VALUE`` strings (typed like the defaults) over ``base``.

        Raises:
            UserError: an unknown option, or a value of the wrong type.
        """
        # Every option is an int or a float (see the module docstring), so the
        # type of its default parses its value.
        known = {f.name: type(f.default) for f in dataclasses.fields(cls)}
        options = dict(base)
        for item in items:
            key, sep, value = item.partition("=")
            if not sep or key not in known:
                raise UserError(f"expected OPTION=VALUE with a FieldConfig option, got '{item}'")
            try:
                options[key] = known[key](value)
            except ValueError:
                raise UserError(f"FieldConfig.{key} must be of type {known[key].__name__}, got '{value}'") from None
        return cls(**options)

    @classmethod
    def from_dict(cls, d: dict) -> "FieldConfig":
        """The config a saved field records; UserError on a key that is no option."""
        if not isinstance(d, dict):
            raise UserError("its config is not a JSON object")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise UserError(f"its config has unknown field option {', '.join(unknown)}")
        return cls(**d)
