"""`TTOConfig`: the schedule, sample counts and ablation switches of test-time optimisation (docs/architecture.md
section 6).

Presets: "cpu" (the default: a few minutes per object on 2 cores), "gpu" (quality: more steps, larger ray batches,
more bounces) and "tiny" (tests: seconds). The switches select the paper's variants:

- field: "triplane" (ours) or "uv" (latent UV textures on an xatlas unwrap; ablation);
- init: "lmrm" (the LMRM's triplane), "random" (a random triplane, same frozen decoders; ablation) or "pbr" (first
  `pbr_steps` steps of the PBR baseline's TTO from the LMRM's PBR head, then the neural triplane starts from that
  PBR solution expressed in the basis, `tto/pbr_start.py`; neural triplane only);
- reg: "uncertainty" (ours: weights exp(-log_var) of the LMRM), "none", "oracle" (weights 1 / squared error of
  the LMRM G-buffers against ground truth; needs a synthetic object's ground truth) or "start" (init "pbr" only:
  weight 1 towards the neural start, i.e. the PBR solution expressed in the basis);
- material: "neural" (ours) or "pbr" (the NVDiffRecMC++ baseline: the same loop with the LMRM's PBR head);
- estimator: "path" (default: every step path traces its pixels) or "cached" (the light transport of `cache_pixels`
  photo pixels is cached every `cache_every` steps, `render/transport_cache.py`, and each step re-evaluates only
  the material; cheaper steps, but it measured worse at equal time so far: docs/design-notes.md, item 22);
- photo_loss: "l2" (the paper's: the squared error of each pixel's spp-sample mean), "decorrelated" (the product of
  two independent half-estimates' errors), "linear_decorrelated" (products of distinct samples' errors in linear
  radiance), so the render's Monte Carlo variance adds no gradient (tto/loss.py; measured worse on the benchmark:
  docs/design-notes.md, item 28), or "decorrelated_debiased" ("decorrelated" with each half less the tonemap's gap,
  estimated from its samples: least at a noise-free photo; item 53);
- optimizer: "adam" (default) or "gauss_newton" (the field tensor's step from the photo and consistency terms'
  curvature, tto/gauss_newton.py; measured no better: docs/design-notes.md, item 57); control_variate: "off"
  (default), "settle" or "all" (renders through a frozen copy of the field with the same random numbers,
  tto/control_variate.py; item 57);
- basis: "" (the default neural basis) or the id of another installed basis (materials/data/bases/; with init
  "pbr" or "random" and reg "none", since the LMRM's latents are the default basis's: docs/design-notes.md, item 25).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any, Literal

from neumatex_core.config import Range, check_choices, check_known_keys, check_ranges
from neumatex_core.materials.neural_basis import LATENT_DIM, basis_latent_dim, installed_bases
from neumatex_core.tto.loss import PhotoLossKind

FieldKind = Literal["triplane", "uv"]
InitKind = Literal["lmrm", "random", "pbr"]
RegKind = Literal["uncertainty", "none", "oracle", "start"]
ConsistencyKind = Literal["change", "value", "value_latent", "value_rho"]
MaterialKind = Literal["neural", "pbr"]
EstimatorKind = Literal["cached", "path"]
OptimizerKind = Literal["adam", "gauss_newton"]
ControlVariateKind = Literal["off", "settle", "all"]
PixelOrderKind = Literal["random", "shuffled"]
PRESETS = ("tiny", "cpu", "gpu")
BIG = 1 << 24
# consistency_rho_value of the "uniform" variation (one material over the whole object): on the Cycles captures,
# sheen relit - PBR +2.09 dB, coat +3.71 (without it +1.26, +2.98); on textured objects it costs 1.2-1.8 dB
# (docs/design-notes.md item 35)
UNIFORM_RHO_VALUE = 3.0
# The start from the LMRM that select_lmrm_start tries beside the PBR start: nearly all the LMRM's prediction (the PBR
# start's variance taken as 1, so the LMRM's share is 1 / (1 + its variance)), anchored (0.1) where the LMRM made it
# (docs/design-notes.md items 96-98)
LMRM_START_FULL: dict[str, Any] = {"lmrm_start_var": 1.0, "lmrm_start_anchor": True, "lambda_reg": 0.1}
# The allowed values of the numeric fields (checked by TTOConfig.check; the job service's bounds).
RANGES: dict[str, Range] = {
    "steps": Range(1, 100_000), "pixels": Range(1, 1 << 20), "spp": Range(1, 4096), "max_bounces": Range(1, 64),
    "lr": Range(0, 100, lo_open=True), "lr_final": Range(0, 1, lo_open=True), "lr_warmup": Range(0, 100_000),
    "lambda_reg": Range(0, 1e6),
    "lambda_consistency": Range(0, 1e6), "consistency_sigma": Range(0, 100, lo_open=True),
    "consistency_rho_value": Range(0, 1e6), "consistency_latent_value": Range(0, 1e6), "lambda_smooth": Range(0, 1e6),
    "coarse_factor": Range(1, 64),
    "reg_points": Range(1, 1 << 20), "reg_pool": Range(1, BIG), "uv_resolution": Range(1, 8192),
    "random_std": Range(0, 100), "checkpoint_every": Range(0, 100_000), "seed": Range(0, 2**31 - 1),
    "cache_pixels": Range(1, 1 << 20), "cache_directions": Range(1, 4096), "cache_every": Range(1, 100_000),
    "pbr_steps": Range(1, 100_000), "pbr_fit_steps": Range(1, 100_000), "pbr_fit_lr": Range(0, 100, lo_open=True),
    "pbr_fit_batch": Range(1, 1 << 24), "lmrm_start_var": Range(0, 1e6), "pbr_bsdf_fit_steps": Range(0, 100_000),
    "neural_lr_scale": Range(0, 100, lo_open=True), "average_tail": Range(0, 0.99),
    "settle_fraction": Range(0, 1), "settle_spp": Range(1, 4096), "settle_lr": Range(0, 100, lo_open=True),
    "settle_lr_final": Range(0, 1, lo_open=True),
    "adam_beta1": Range(0, 0.9999), "adam_beta2": Range(0, 0.99999), "adam_eps": Range(0, 1),
    "gn_lr_scale": Range(0, 100, lo_open=True), "gn_beta2": Range(0, 0.99999), "gn_damping": Range(0, 1e6),
    "gn_max_step": Range(0, 100, lo_open=True), "gn_warmup": Range(0, 100_000), "cv_spp": Range(1, 4096),
    "cv_refresh": Range(0, 100_000),
    "photo_weight_radius": Range(0, 64),
    "decoder_lr": Range(0, 100, lo_open=True), "exposure_lr": Range(0, 100, lo_open=True),
    "validation_photos": Range(1, 100_000), "select_margin_db": Range(-100, 100),
    "select_fraction": Range(0, 1, lo_open=True), "basis_margin_db": Range(-100, 100),
    "select_continue_lr": Range(0, 100, lo_open=True),
    "validation_spp": Range(2, 4096), "validation_stride": Range(1, 4096)}  # fmt: skip


@dataclass(frozen=True)
class TTOConfig:
    """steps: Adam steps; pixels: photo pixels per step (drawn uniformly over the foreground of all photos);
    spp: path samples per pixel; max_bounces: surface interactions per path; lr: Adam learning rate (cosine-decayed
    to lr * lr_final); lambda_reg: weight of the uncertainty-weighted anchor; reg_points: surface points per step
    for the anchor (drawn from a fixed pool of `reg_pool` area-uniform points); uv_resolution: texels of the UV
    ablation's textures; random_std: standard deviation of a random triplane; checkpoint_every: steps between
    checkpoints (0: only when stopped); seed: every random draw of step s depends only on (seed, s).
    train_decoder: the triplane variants also fine-tune (a copy of) their decoder, at lr x decoder_lr (the frozen
    LMRM decoder caps what a triplane can express: docs/design-notes.md, "TTO fine-tunes the decoder").
    photo_exposure: also fit each photo's exposure (hand-held photos whose exposures are not known): a learnable
    log-scale per photo on top of the capture's given exposure, its mean over photos pinned to 0, Adam at
    exposure_lr (cosine-decayed like lr; tto/optimise.py `ExposureFit`).
    estimator "cached": each cache holds `cache_pixels` pixels x spp camera rays with `cache_directions` incident
    directions per hit and is rebuilt (new pixels, new directions, indirect light of the current material) every
    `cache_every` steps; a step draws its `pixels` pixels from the current cache.

    The loss is taken after the (concave) tonemap, so few samples per pixel bias it: the presets spend rays on
    spp >= 8 rather than on more pixels (docs/design-notes.md, item 21), and max_bounces should match the
    photos' light transport (3 for synthetic objects)."""

    steps: int = 400
    pixels: int = 1024
    spp: int = 8
    max_bounces: int = 3
    # lr measured on benchmark object 0, PathTrace after 400 steps: 0.02 21.8 dB, 0.08 23.1, 0.2 23.7, 0.5 23.8
    lr: float = 0.2
    lr_final: float = 0.1
    # the rate ramps up linearly over the first lr_warmup steps (0: none): Adam's first steps move every number by
    # about lr whatever its gradient (its second moment is then the mean of a few squares), so a start that is
    # already good is kicked away before the moments mean anything (docs/design-notes.md item 57)
    lr_warmup: int = 0
    lambda_reg: float = 0.02
    reg_points: int = 1024
    reg_pool: int = 1 << 15
    uv_resolution: int = 128
    random_std: float = 0.1
    checkpoint_every: int = 50
    seed: int = 0
    field: FieldKind = "triplane"
    init: InitKind = "lmrm"
    reg: RegKind = "uncertainty"
    material: MaterialKind = "neural"
    # measured on benchmark object 0 (PBR, 400 steps, clean PathTrace): path 32.0 dB in 0.92 min; cached with
    # 8192 pixels rebuilt every 100 steps 30.0 dB in 0.47 min, 2048 pixels every 10 steps 31.4 dB in 0.83 min
    # (a fixed sample set is over-fitted between rebuilds; docs/design-notes.md, item 22)
    estimator: EstimatorKind = "path"
    cache_pixels: int = 2048
    cache_directions: int = 32
    cache_every: int = 10
    pbr_steps: int = 200
    # Adam steps fitting the neural triplane to the PBR solution (tto/pbr_start.py). Measured on benchmark object 0
    # (bench/pbr_start.py, clean PathTrace, PBR solution 30.0 dB): 300 steps 26.9 dB, 1500 steps 29.0 dB (14 s),
    # the per-point conversion without the triplane 29.2 dB (docs/design-notes.md, item 26)
    pbr_fit_steps: int = 1500
    # their Adam learning rate (cosine-decayed to 0) and surface points per step. 750 steps of 4096 points at 0.3 fit
    # better in a quarter of the time, but the TTO from that start was no better (PathTrace -0.15 +- 0.17 dB on 11
    # benchmark objects; docs/design-notes.md item 46)
    pbr_fit_lr: float = 0.05
    pbr_fit_batch: int = 8192
    # then Adam steps refining that start so its BSDF matches PBR's (tto/pbr_start.py `refine_to_pbr_bsdf`)
    pbr_bsdf_fit_steps: int = 0
    # init "pbr": before the planes are fitted, the cells of the object whose photos a material family's prototype
    # reproduces better under direct light than the PBR start take that prototype's fit (tto/appearance_start.py)
    appearance_start: bool = False
    # init "pbr": > 0 blends the start with the LMRM's prediction channel by channel by their precisions, this being
    # the PBR start's error variance (G-buffer units squared) and exp(log_var) the LMRM's; the latent in the default
    # basis only (tto/lmrm_start.py; 0: the PBR start alone; docs/design-notes.md item 96)
    lmrm_start_var: float = 0.0
    # with lmrm_start_var, reg "start": the anchor to the start weighs each channel by the LMRM's share of it
    # (`lmrm_share`) instead of 1, so lambda_reg holds what the LMRM put in and leaves the PBR start's part free
    lmrm_start_anchor: bool = False
    # init "pbr": the neural phase's learning rate is lr x neural_lr_scale (it starts at a fitted solution, not at
    # the LMRM's guess that lr was tuned for)
    neural_lr_scale: float = 1.0
    # the result is the mean of the field's tensor over this last fraction of the steps (0: the last iterate;
    # tto/optimise.py `IterateAverage`)
    average_tail: float = 0.0
    # the last settle_fraction of the steps settle: each traces the same rays as before at settle_spp samples per
    # pixel (pixels x spp / settle_spp pixels), and the learning rate starts a second cosine from lr x settle_lr
    # down to lr x settle_lr x settle_lr_final. Measured (docs/design-notes.md, item 50): from the ground truth, half
    # the steps settling keep 34.6 of its 50.0 dB (33.4 without); from the PBR start, all 40 benchmark objects,
    # PathTrace +0.44 +- 0.13 dB. The extraction presets set 7/9 and settle_lr 1.0 (pipeline.NEURAL_FROM_PBR; the
    # full rate again: item 65; 7/9 of 2.25x the steps: item 74); 0 here, so a bare TTOConfig (the PBR baseline, the
    # paper's variants) is the plain cosine schedule.
    settle_fraction: float = 0.0
    settle_spp: int = 32
    settle_lr: float = 0.1
    # where the settling's cosine ends, as a fraction of where it starts (lr_final's part in the steps before): the
    # rate of the last steps sets how far each step's noise moves the result (docs/design-notes.md items 49, 72)
    settle_lr_final: float = 0.1
    # the settling steps' photometric loss ("" = photo_loss): e.g. the L2 moves the material far at the high rate
    # and a loss least at a noise-free photo settles it (docs/design-notes.md, item 53)
    settle_photo_loss: Literal[PhotoLossKind, ""] = ""
    # Adam's moment decay rates and epsilon (torch's defaults). A large epsilon makes the steps of parameters whose
    # gradient is mostly noise small: from the truth 1e-3 keeps 37.3 dB, 1e-2 41.4, but from the PBR start the
    # neural phase then hardly moves (1e-3: PathTrace -1.33 +- 0.23 dB against the default; item 50)
    adam_beta1: float = 0.9
    adam_beta2: float = 0.999
    adam_eps: float = 1e-8
    # the field tensor's step: "adam", or "gauss_newton" (tto/gauss_newton.py: a damped fraction lr x gn_lr_scale of
    # the diagonal Gauss-Newton step of the photo and consistency terms, its curvature estimated by one more backward
    # pass a step, moving averages at adam_beta1 / gn_beta2; damping gn_damping x the mean curvature, each step
    # clamped to gn_max_step, the rate ramped up over the first gn_warmup steps), so a texel that few photo pixels
    # see is not walked by its noise at Adam's full step
    # (docs/design-notes.md item 57). The neural phase's alone: the PBR phase is the baseline's own TTO. The decoder
    # and the exposures keep Adam.
    optimizer: OptimizerKind = "adam"
    gn_lr_scale: float = 1.0
    gn_beta2: float = 0.99
    gn_damping: float = 0.01
    gn_max_step: float = 0.2
    gn_warmup: int = 20
    # the Gauss-Newton step solved per texel over its feature channels (which the decoder mixes) instead of per number
    gn_block: bool = False
    # a control variate for the photo renders (tto/control_variate.py): each render is taken less the same rays'
    # render under a frozen copy of the field and plus that copy's radiance of every photo pixel, rendered at cv_spp
    # samples: the same expectation, much less fresh noise (docs/design-notes.md item 57). "settle": in the settling
    # phase (its copy made at the phase's first step), "all": in every step (copies at step 0 and at the settling
    # phase's first step); either way a new copy every cv_refresh steps after those (0: none)
    control_variate: ControlVariateKind = "off"
    # the photo pixels each step draws: "random" (uniformly, with replacement, each step on its own) or "shuffled"
    # (random reshuffling: the draws run through one random permutation of every foreground pixel after another, so
    # over an epoch each pixel is drawn once and none is left out or drawn five times; tto/data.py
    # `shuffled_pixels`, docs/design-notes.md item 71)
    pixel_order: PixelOrderKind = "random"
    # each half of a pixel's samples takes Latin-hypercube random numbers for its first bounce's light and BSDF
    # samples (`PathTracer.render_rays` strata): the same expectation per sample, a quieter half-mean
    # (docs/design-notes.md item 71)
    stratified: bool = False
    cv_spp: int = 32
    cv_refresh: int = 0
    train_decoder: bool = False
    decoder_lr: float = 0.1
    # init "pbr" with train_decoder: whether the neural phase fine-tunes its decoder where it runs in a basis other
    # than the default (alternative_basis taken, or `basis`) too; False: there only the PBR phase does (the LMRM's
    # material decoder was trained for the default basis; docs/design-notes.md item 41)
    decoder_in_other_basis: bool = True
    # "" = the default neural basis; another installed basis (materials/data/bases/) by id. The LMRM predicts the
    # default basis's latents, so another basis needs a start and an anchor that do not come from it.
    basis: str = ""
    # init "pbr": another installed basis to start the neural phase in when the PBR solution expressed in `basis`
    # reproduces the photos worse than PBR itself by more than basis_margin_db and expressed in this one better
    # than in `basis` by more than basis_margin_db (held-out or spread photos, `photo_psnr`): a basis that cannot
    # hold the PBR solution cannot begin where PBR ends (Cycles metals: the default basis's start 7 dB below PBR,
    # v4's 6 dB above it). At 2 dB the demo and benchmark object 17 switched too, on margins of 2.1-2.4 dB, and
    # gained nothing (tto/pbr_start.py `choose_basis`, docs/design-notes.md item 38)
    alternative_basis: str = ""
    basis_margin_db: float = 3.0
    photo_exposure: bool = False
    exposure_lr: float = 0.05
    photo_loss: PhotoLossKind = "l2"
    # photo_loss "linear_decorrelated": each pixel's error is weighed by the tonemap's slope at its photo's mean over
    # the (2 r + 1)^2 window of foreground pixels around it (0: at its own value, which a noisy photo's noise moves;
    # tto/loss.py `photometric_loss`)
    photo_weight_radius: int = 0
    # init "pbr", reg "start": the neural phase is run twice, with the anchor (lambda_reg) and without it, on all
    # photos but `validation_photos` (spread over the capture, each with a fitted photo within 30 degrees), and the
    # result that reproduces those held-out photos better is kept: the anchored one unless dropping the anchor
    # gains more than select_margin_db of PSNR
    # (tto/pbr_start.py `solve`; docs/design-notes.md item 32)
    select_anchor: bool = False
    validation_photos: int = 4
    select_margin_db: float = 0.25
    # a choice (select_anchor / select_uniform, alternative_basis) scores its results (`photo_psnr`, two halves of
    # each pixel's samples) at validation_spp path samples per pixel, on every validation_stride-th foreground pixel
    # of the scored photos. Neither is cut to save time: at 16 samples the tonemap of a half's mean biases the score
    # by an amount that depends on the material (a Cycles coat's PBR - start gap moved by 1.1 dB), and on every other
    # pixel the choice between uniform and textured moved by up to 0.25 dB and flipped on benchmark object 6 (-1.4 dB
    # PathTrace); docs/design-notes.md item 42
    validation_spp: int = 32
    validation_stride: int = 1
    # init "pbr", lambda_consistency > 0: the same choice between this config with the base colours' values compared
    # too (consistency_rho_value UNIFORM_RHO_VALUE: one uniform material, whose start carries the capture's light
    # painted into rho_d) and this config (several materials, or textured); uniform is kept unless textured
    # reproduces the held-out photos better by more than select_margin_db (docs/design-notes.md item 36)
    select_uniform: bool = False
    # select_anchor / select_uniform: each candidate's neural phase during the choice runs this fraction of `steps`
    # (the TTO with the chosen config then runs all of them on every photo). At 0.5 the choice matched the
    # full-length one on all 8 Cycles captures and 6 benchmark objects, so the results were bit for bit the same, in
    # 1200 steps instead of 1600 (the demo's TTO 129 s instead of 153 s; docs/design-notes.md item 37). At 0.25
    # (since 2026-11-29) the results were the same bit for bit as at 0.5 on 4 Cycles coats and sheens and on 14 of
    # 16 benchmark objects (over the 16: PathTrace -0.01 +- 0.08, relit +0.04 +- 0.03 dB), 200 candidate steps fewer
    # (docs/design-notes.md item 47)
    select_fraction: float = 0.25
    # select_anchor / select_uniform: the TTO with the chosen config starts its neural phase on every photo from the
    # start the choice made (the PBR phase on all photos but the held-out ones, expressed in the chosen basis)
    # instead of running the PBR phase and the start's fit again; that saves a PBR phase and a start fit (the demo's
    # TTO 180 s -> 146 s), and the held-out photos still reach the result through the neural phase
    # (docs/design-notes.md item 40). Without a choice it changes nothing.
    select_reuse_start: bool = False
    # select_reuse_start: the TTO after the choice goes on from the chosen candidate's result (its planes, decoder
    # and exposures after its select_steps() on all photos but the held-out ones) for the remaining
    # steps - select_steps() neural steps on every photo (a new cosine schedule from lr), instead of running all
    # `steps` again from the start: the candidate's steps are not thrown away (docs/design-notes.md item 45).
    # Without select_reuse_start and a choice it changes nothing. Those steps' schedule starts at
    # select_continue_lr x lr (0.5: about where a single cosine over all `steps` would be at that point). Not the
    # default: on benchmark objects 0-7 it cost PathTrace 0.22 dB (0.15 at select_continue_lr 0.5)
    select_continue: bool = False
    select_continue_lr: float = 1.0
    # with select_anchor / select_uniform: another installed basis (any latent size) whose candidates join the choice:
    # the same PBR solution expressed in it (no alternative basis there), its two candidates run and scored on the
    # same held-out photos, its decoder fine-tuned (its latent rows beyond the LMRM's are untrained; frozen, basis
    # v6 lost 2-5 dB, docs/design-notes.md item 78). Each basis keeps its candidate by the choice's rule; the other
    # basis is taken when its kept candidate scores better than the configured basis's by more than
    # select_margin_db. So one capture's material can be one that v6's 16 latents hold better (metals, most of the
    # benchmark) while another keeps v1 (Cycles sheens, which v6 loses by 5 dB; item 80)
    select_basis: str = ""
    # with select_anchor / select_uniform: each basis's two candidates run a second time from the start taken from the
    # LMRM's prediction (`LMRM_START_FULL`, `lmrm_started`) and join the choice on the same held-out photos, taken
    # where their kept candidate scores better than the PBR start's by more than select_margin_db. A better LMRM's
    # start gains 5-7 dB where the PBR start fails and loses up to 4 dB where it is best (docs/design-notes.md
    # items 97-98); the choice costs two (with select_basis four) more candidates' steps
    select_lmrm_start: bool = False
    # reg "start": weight of the consistency term (tto/loss.py `consistency`): pairs of anchor points whose start
    # G-buffers are alike (Gaussian weight of width consistency_sigma in G-buffer units) must change alike from the
    # start (consistency_of "change"; "value": end alike), so the neural phase may move a material everywhere at once
    # (what PBR could not represent) but not paint the capture's lighting onto parts of it (docs/design-notes.md,
    # item 34)
    lambda_consistency: float = 0.0
    consistency_sigma: float = 0.25
    consistency_of: ConsistencyKind = "change"
    # and, at these weights relative to the term, the same pairs' base colours rho_d / latents must end alike
    # (docs/design-notes.md, item 35)
    consistency_rho_value: float = 0.0
    consistency_latent_value: float = 0.0
    # weight of the smoothness term: the mean squared difference between neighbouring texels of the TTO's change to
    # its tensor (`Parametrisation.texel_variation`; the tensor minus the one it started from). A texel that few
    # photo pixels reach gets a gradient that is mostly Monte Carlo noise, and Adam moves it by about lr a step
    # whatever that noise (docs/design-notes.md item 50); coupled to its neighbours its change is pulled towards
    # theirs. Of the change, not the values: the start (the PBR solution's planes) is not smooth, and smoothing it
    # away cost 5 dB. The neural phase's alone: the PBR phase (the baseline's own TTO) drops it. Off: at 0.1, on
    # benchmark objects 0-5, PathTrace -0.02 +- 0.22 dB against the default (docs/design-notes.md item 52)
    lambda_smooth: float = 0.0
    # the high-rate steps (before the settling) move the planes in blocks of this many texels a side: each step's
    # gradient is projected onto a grid this many times coarser (`Parametrisation.coarsen_gradient`), so a texel
    # that few photo pixels reach moves with its neighbours' photo pixels too; the settling steps move every texel
    # (1: off; the neural phase's alone, docs/design-notes.md item 56)
    coarse_factor: int = 1

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> TTOConfig:
        """'tiny', 'cpu' (default) or 'gpu', with field overrides."""
        if name == "tiny":
            base = cls(steps=12, pixels=128, spp=2, max_bounces=1, lr=0.05, reg_points=256, reg_pool=4096,
                       uv_resolution=32, checkpoint_every=4, cache_pixels=512, cache_directions=8, cache_every=4,
                       pbr_steps=6, pbr_fit_steps=300)  # fmt: skip
        elif name == "cpu":
            base = cls()
        elif name == "gpu":
            base = cls(steps=3000, pixels=8192, spp=16, max_bounces=4, lr=0.01, reg_points=16384, reg_pool=1 << 18,
                       uv_resolution=512, checkpoint_every=200, cache_pixels=16384, cache_directions=64,
                       cache_every=20)  # fmt: skip
        else:
            raise ValueError(f"unknown TTO preset {name!r} (expected one of {', '.join(PRESETS)})")
        return replace(base, **overrides)

    def check(self) -> None:
        """ValueError naming the first bad field."""
        check_ranges(self, RANGES, "TTO")
        check_choices(self, "TTO")
        if self.init == "pbr" and (self.material != "neural" or self.field != "triplane"):
            raise ValueError("TTO init='pbr' starts a neural triplane from a PBR fit: it needs material='neural' and "
                             f"field='triplane', got {self.material!r} and {self.field!r}")
        for key in ("basis", "alternative_basis", "select_basis"):
            name = getattr(self, key)
            if name and name not in installed_bases():
                raise ValueError(f"TTO {key}={name!r} is not installed (installed: {', '.join(installed_bases())})")
            size = basis_latent_dim(name) if name else LATENT_DIM
            if size != LATENT_DIM and (key == "alternative_basis" or self.field != "triplane"):
                # e.g. basis v5: the triplane's decoder takes its size (docs/design-notes.md item 78), but the
                # choice between two bases' starts and the UV textures hold one size of G-buffer
                raise ValueError(f"TTO {key}={name!r} has {size} latent numbers: only a triplane field in `basis` "
                                 f"or `select_basis` takes a latent size other than {LATENT_DIM}")
        if self.select_basis and (not (self.select_anchor or self.select_uniform) or self.init != "pbr"
                                  or self.select_basis == self.basis):
            raise ValueError("TTO select_basis joins another basis's candidates to the choice on held-out photos: it "
                             "needs init 'pbr', select_anchor or select_uniform, and a basis other than `basis`; got "
                             f"init {self.init!r}, select_anchor {self.select_anchor}, select_uniform "
                             f"{self.select_uniform}, basis {self.basis!r}, select_basis {self.select_basis!r}")
        if self.select_lmrm_start and (not (self.select_anchor or self.select_uniform) or self.init != "pbr"
                                       or self.reg != "start"):
            raise ValueError("TTO select_lmrm_start joins candidates started from the LMRM to the choice on held-out "
                             "photos: it needs init 'pbr', reg 'start' and select_anchor or select_uniform; got init "
                             f"{self.init!r}, reg {self.reg!r}, select_anchor {self.select_anchor}, select_uniform "
                             f"{self.select_uniform}")
        if self.alternative_basis and (self.init != "pbr" or self.material != "neural"):
            raise ValueError("TTO alternative_basis is tried for the start of the neural phase from the PBR solution: "
                             f"it needs init 'pbr' and material 'neural', got {self.init!r}, {self.material!r}")
        if self.optimizer == "gauss_newton" and (self.estimator != "path" or self.field != "triplane"):
            raise ValueError("TTO optimizer 'gauss_newton' probes the curvature through the traced photo batch of a "
                             f"triplane: it needs estimator 'path' and field 'triplane', got {self.estimator!r}, "
                             f"{self.field!r}")
        if self.control_variate != "off" and self.stratified:
            raise ValueError("TTO control_variate renders its copy with plain random numbers: it needs stratified off")
        if self.control_variate != "off" and self.estimator != "path":
            raise ValueError("TTO control_variate renders the traced photo batch a second time: it needs estimator "
                             f"'path', got {self.estimator!r}")
        if self.settle_fraction > 0 and self.estimator == "cached":
            raise ValueError("TTO settle_fraction changes the samples per pixel of the traced batches: it needs "
                             f"estimator 'path', got {self.estimator!r}")
        losses = [(self.photo_loss, self.spp)]
        if self.settle_fraction > 0:
            losses.append((self.loss_at(self.settle_start()), self.settle_spp))
        for kind, spp in losses:
            least = 4 if kind == "decorrelated_debiased" else 2
            if kind != "l2" and spp < least:
                raise ValueError(f"TTO photo loss {kind!r} pairs each pixel's samples: it needs spp >= {least}, got "
                                 f"{spp} (spp {self.spp}, settle_spp {self.settle_spp})")
        if self.select_anchor and (self.reg != "start" or self.init != "pbr" or self.lambda_reg <= 0):
            raise ValueError("TTO select_anchor chooses between the anchor to the PBR start and none: it needs init "
                             f"'pbr', reg 'start' and lambda_reg > 0, got {self.init!r}, {self.reg!r}, "
                             f"{self.lambda_reg}")
        if self.select_uniform and (self.init != "pbr" or self.lambda_consistency <= 0 or self.select_anchor):
            raise ValueError("TTO select_uniform chooses whether the consistency term also compares base colours: it "
                             f"needs init 'pbr' and lambda_consistency > 0, without select_anchor; got init "
                             f"{self.init!r}, lambda_consistency {self.lambda_consistency}, select_anchor "
                             f"{self.select_anchor}")
        if self.lambda_consistency > 0 and self.reg in ("uncertainty", "oracle"):
            raise ValueError(f"TTO lambda_consistency compares each point's change from the PBR start: it needs reg "
                             f"'start', got {self.reg!r}")
        if (self.consistency_rho_value > 0 or self.consistency_latent_value > 0) and self.lambda_consistency <= 0:
            raise ValueError("TTO consistency_rho_value and consistency_latent_value weigh parts of the consistency "
                             f"term: they need lambda_consistency > 0, got {self.lambda_consistency}")
        if self.lmrm_start_anchor and self.lmrm_start_var <= 0:
            raise ValueError("TTO lmrm_start_anchor weighs the anchor to the start by the LMRM's share of it: it needs "
                             f"lmrm_start_var > 0, got {self.lmrm_start_var}")
        if self.reg == "start" and self.init != "pbr":
            raise ValueError(f"TTO reg='start' anchors to the PBR start: it needs init 'pbr', got {self.init!r}")
        if self.basis and (self.init == "lmrm" or self.reg not in ("none", "start")):
            raise ValueError(f"TTO basis={self.basis!r}: the LMRM's latents are in the default basis, so another basis "
                             f"needs init 'pbr' or 'random' and reg 'none' or 'start', got init {self.init!r}, "
                             f"reg {self.reg!r}")

    def steps_scaled(self, scale: float) -> TTOConfig:
        """This config with `scale` times its steps (at least one): a neural phase made longer on any preset's
        schedule (pipeline.ExtractConfig.neural_steps_scale, the eval variants' "steps_scale")."""
        return replace(self, steps=max(1, round(self.steps * scale)))

    def settle_start(self) -> int:
        """The first step (0-based) of the settling phase; `steps` when there is none."""
        return self.steps - round(self.settle_fraction * self.steps)

    def cv_round(self, step: int) -> int:
        """The first step of the control variate's reference that step `step` uses (-1: none): step 0 ("all") and the
        settling phase's first step (0 without one), each followed by one every cv_refresh steps."""
        if self.control_variate == "off":
            return -1
        settle = self.settle_start() if self.settle_fraction > 0 else 0
        if step < settle and self.control_variate == "settle":
            return -1
        first = settle if step >= settle else 0
        if self.cv_refresh == 0:
            return first
        return first + (step - first) // self.cv_refresh * self.cv_refresh

    def coarse_at(self, step: int) -> int:
        """The block size (texels a side) of step `step`'s move of the planes: coarse_factor before the settling."""
        return self.coarse_factor if step < self.settle_start() else 1

    def loss_at(self, step: int) -> PhotoLossKind:
        """The photometric loss of step `step`."""
        if step >= self.settle_start() and self.settle_fraction > 0 and self.settle_photo_loss:
            return self.settle_photo_loss
        return self.photo_loss

    def batch_at(self, step: int) -> tuple[int, int]:
        """(pixels, samples per pixel) of step `step`'s photo batch."""
        if step < self.settle_start():
            return self.pixels, self.spp
        return max(1, self.pixels * self.spp // self.settle_spp), self.settle_spp

    def pixels_before(self, step: int) -> int:
        """Photo pixels the steps before `step` drew (`batch_at`): step `step`'s first draw position."""
        start = self.settle_start()
        if step <= start:
            return step * self.pixels
        return start * self.pixels + (step - start) * self.batch_at(start)[0]

    def total_steps(self) -> int:
        """Adam steps of the whole TTO: with init "pbr", the PBR phase's and then the neural phase's."""
        return self.steps + (self.pbr_steps if self.init == "pbr" else 0)

    def select_steps(self) -> int:
        """Adam steps of each candidate's neural phase during select_anchor's / select_uniform's choice."""
        return max(1, round(self.steps * self.select_fraction))

    def run_steps(self) -> int:
        """Adam steps the TTO runs (its progress counts these): total_steps, and with select_anchor or
        select_uniform first the choice (the PBR phase and two neural phases of select_steps on all photos but the
        held-out ones per side: twice as many sides with select_basis, and twice again with select_lmrm_start),
        after which select_reuse_start runs the neural phase alone (select_continue: its remaining continue_steps)."""
        if not (self.select_anchor or self.select_uniform):
            return self.total_steps()
        choice = self.pbr_steps + 2 * self.select_steps() * self.select_sides()
        if not self.select_reuse_start:
            return choice + self.total_steps()
        return choice + (self.continue_steps() if self.select_continue else self.steps)

    def select_sides(self) -> int:
        """How many sides the choice on held-out photos has, two candidates each: the configured basis, with
        select_basis the other, each from the PBR start and with select_lmrm_start from the LMRM's too."""
        return (2 if self.select_basis else 1) * (2 if self.select_lmrm_start else 1)

    def lmrm_started(self) -> TTOConfig:
        """This config with its start taken from the LMRM (`LMRM_START_FULL`): select_lmrm_start's other sides."""
        return replace(self, **LMRM_START_FULL, select_lmrm_start=False)

    def continue_steps(self) -> int:
        """Neural steps on every photo after the choice with select_continue: those the chosen candidate did not run."""
        return max(1, self.steps - self.select_steps())

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TTOConfig:
        check_known_keys(cls, data, "TTO config")
        return cls(**data)
