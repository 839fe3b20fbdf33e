"""The TTO loop (docs/architecture.md section 6): Adam on the material field's tensor only, random pixel batches of the
photos rendered through the differentiable path tracer, an uncertainty-weighted anchor to the LMRM's G-buffers.

    problem = build_problem(config, mesh, envmap, photos, tonemap, prediction, basis)
    result = optimise(problem, config, progress=..., should_stop=..., checkpoint=work / "checkpoint.pt")

Every random draw of step s (pixels, jitter, paths, anchor points) comes from a generator seeded with
(config.seed, s), and the learning rate is a function of s; the transport cache (estimator "cached") is rebuilt at
steps 0, cache_every, 2 cache_every, ... from the tensor of that step, which the checkpoint keeps. So a run stopped
after step s and resumed from its checkpoint gives the same tensor, bit for bit on one device, as an uninterrupted
run.

With config.photo_exposure the loop also fits each photo's exposure (`ExposureFit`: hand-held photos, each exposed
differently and not known): a scale per photo multiplies its pixels' rendered radiance before the tonemap.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from neumatex_core.assets.bake import bake, rasterize_uv
from neumatex_core.assets.uv_unwrap import unwrap
from neumatex_core.atomic import replaced_atomically
from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.fields.decoders import MaterialDecoder
from neumatex_core.fields.triplane import Triplane
from neumatex_core.fields.uv_textures import PBR_CHANNELS, material_channels
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.lmrm.inference import LMRMPrediction
from neumatex_core.materials.neural_basis import NeuralBasis
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.render.transport_cache import TransportCache, TransportCacheConfig
from neumatex_core.tto.config import TTOConfig
from neumatex_core.tto.control_variate import ControlVariate, clone_generator
from neumatex_core.tto.data import PhotoSet
from neumatex_core.tto.gauss_newton import DiagonalGaussNewton, sign_probe
from neumatex_core.tto.loss import (
    Anchor,
    consistency,
    consistency_residuals,
    oracle_weights,
    photo_residuals,
    photometric_loss,
    regulariser,
    uncertainty_weights,
)
from neumatex_core.tto.params import PBRUV, NeuralTriplane, NeuralUV, Parametrisation, PBRTriplane

Progress = Callable[[int, int, dict[str, float]], None]
Truth = Callable[[torch.Tensor], torch.Tensor]  # points [P, 3] -> ground-truth (rho_d, latent) [P, 9]
CHECKPOINT_FORMAT = "nmx-tto-2"


class ExposureFit:
    """The per-photo exposures TTO fits (TTOConfig.photo_exposure): a learnable log-scale u [F] per photo (a leaf,
    initialised at 0, i.e. at the capture's given exposure) and the unitless multipliers s_f = exp(u_f - mean(u))
    that scale photo f's rendered radiance before the tonemap, on top of its given exposure.

    The mean of u over the photos is pinned to 0 (it is subtracted in `scale`, and `project` removes it from u after
    each step, which changes no scale): the photos only see s_f times the material's radiance, so a common factor
    c on every s_f and 1 / c on the material's albedo would render the same photos. Unpinned, the loss cannot tell
    them apart and the overall brightness would drift between exposures and material, which the known environment
    map's radiance fixes in absolute terms (and relighting needs). Pinned, the fit only redistributes brightness
    among the photos; their geometric mean stays at the given exposures'.
    """

    def __init__(self, count: int, device: torch.device | str = "cpu") -> None:
        self.log_scale = torch.zeros(count, device=device, requires_grad=True)

    def scale(self) -> torch.Tensor:
        """s [F]: each photo's fitted exposure multiplier, geometric mean 1 (differentiable)."""
        return torch.exp(self.log_scale - self.log_scale.mean())

    def project(self) -> None:
        """Remove the mean from the log-scales (after an optimiser step)."""
        with torch.no_grad():
            self.log_scale -= self.log_scale.mean()

    def values(self) -> list[float]:
        """The fitted multipliers s_f as floats (photo order)."""
        return [float(v) for v in self.scale().detach().cpu()]

    def start_at(self, scales: Sequence[float]) -> None:
        """Start from multipliers [F] fitted before (e.g. by an earlier phase), renormalised to geometric mean 1."""
        with torch.no_grad():
            self.log_scale.copy_(torch.log(torch.as_tensor(scales, dtype=torch.float32)).to(self.log_scale.device))
        self.project()


@dataclass
class TTOProblem:
    """One object's TTO: the scene mesh (normalised frame; xatlas-unwrapped for UV fields), lighting, photos and
    their tonemap, the parametrisation being optimised, the anchor (None: no regulariser) and the photos' fitted
    exposures (None: the given ones are used as they are)."""

    mesh: Mesh
    envmap: EnvironmentMap
    photos: PhotoSet
    tonemap: Tonemap
    params: Parametrisation
    anchor: Anchor | None
    device: torch.device
    exposure: ExposureFit | None = None

    def photo_scale(self, frame: torch.Tensor, given: torch.Tensor) -> torch.Tensor:
        """[n] the exposure multiplier of pixels of photos `frame` [n] (int64) whose given exposures are `given` [n]:
        given times the fitted one (differentiable in the fitted log-scales)."""
        return given if self.exposure is None else given * self.exposure.scale()[frame]


@dataclass
class TTOResult:
    """params: the optimised parametrisation; history: one row per step (step, loss, photo, reg, psnr, lr);
    steps_done of config.steps; finished: False when stopped early; seconds: wall time of this call; mesh: the
    problem's mesh; exposure: with config.photo_exposure, each photo's fitted exposure multiplier on top of its
    given one (unitless, geometric mean 1; `ExposureFit`), else None; selection: with config.select_anchor or
    select_uniform, the held-out photos' PSNR (dB) of the two candidates and which was kept, with
    config.alternative_basis the scores that chose the basis (tto/pbr_start.py); pbr_solution: with init="pbr", the
    PBR phase's own result that the neural phase started from (fitted on the photos the choice did not hold out), a
    candidate for the asset's PBR fallback (`tto/fallback_choice.py`)."""

    params: Parametrisation
    history: list[dict[str, float]] = field(default_factory=list)
    steps_done: int = 0
    finished: bool = False
    seconds: float = 0.0
    mesh: Mesh | None = None  # the mesh the field lives on (xatlas-unwrapped for UV fields)
    exposure: list[float] | None = None
    selection: dict[str, float] = field(default_factory=dict)
    # with config.alternative_basis: the basis the neural material is in when the TTO switched to it (None: the
    # basis it was given; tto/pbr_start.py `choose_basis`)
    basis: NeuralBasis | None = None
    pbr_solution: Parametrisation | None = None


def _neural_gbuffer(prediction: LMRMPrediction, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(G_mat [P, 9], log_var [P, 9]) of the LMRM at points."""
    rho, lat, log_var = prediction.gbuffers(points)
    return torch.cat([rho, lat], dim=-1), log_var


def _pbr_gbuffer(prediction: LMRMPrediction, points: torch.Tensor) -> torch.Tensor:
    base, rough, metal = prediction.pbr(points)
    return torch.cat([base, rough.unsqueeze(-1), metal.unsqueeze(-1)], dim=-1)


def build_problem(config: TTOConfig, mesh: Mesh, envmap: EnvironmentMap, photos: PhotoSet, tonemap: Tonemap,
                  prediction: LMRMPrediction, basis: NeuralBasis, anchor_available: bool = True,
                  truth: Truth | None = None) -> TTOProblem:
    """Set up the variant `config` selects. `prediction`: the LMRM's triplane and frozen decoders (the anchor and,
    with init="lmrm", the starting point); `anchor_available`: False when the prediction is not a trained LMRM's
    (then config.reg must be "none"); `truth`: ground-truth G-buffers, needed by reg="oracle"."""
    config.check()
    device = photos.device
    if config.reg in ("uncertainty", "oracle") and not anchor_available:
        raise ValueError(f"TTO reg={config.reg!r} anchors to the LMRM's prediction, but there is none (no trained "
                         "LMRM): use reg='none'")  # fmt: skip
    if config.reg == "oracle" and (truth is None or config.material != "neural"):
        raise ValueError("TTO reg='oracle' needs ground-truth G-buffers (a synthetic object) and material='neural'")
    if config.init in ("lmrm", "pbr") and not anchor_available:
        raise ValueError(f"TTO init={config.init!r} needs a trained LMRM's prediction; use init='random'")
    with torch.no_grad():
        pred_planes = prediction.triplane.planes.detach().to(device)
        if config.init in ("lmrm", "pbr"):
            planes = pred_planes.clone()
        else:
            g = torch.Generator().manual_seed(config.seed)
            planes = (torch.randn(pred_planes.shape, generator=g) * config.random_std).to(device)
    anchor_pred = LMRMPrediction(Triplane.from_planes(pred_planes), prediction.material_decoder.to(device),
                                 prediction.uncertainty_decoder.to(device), prediction.pbr_decoder.to(device))
    for module in (anchor_pred.triplane, anchor_pred.material_decoder, anchor_pred.uncertainty_decoder,
                   anchor_pred.pbr_decoder, basis):  # fmt: skip
        module.requires_grad_(False)
    start = Triplane.from_planes(planes)
    start.requires_grad_(True)
    scene_mesh = mesh if mesh.vertex_normals is not None else mesh.with_smooth_normals()
    params: Parametrisation
    if config.field == "uv":
        scene_mesh = unwrap(scene_mesh, config.uv_resolution)
        samples = rasterize_uv(scene_mesh, config.uv_resolution)
        init_field = Triplane.from_planes(planes)
        if config.material == "neural":
            init_pred = LMRMPrediction(init_field, anchor_pred.material_decoder, anchor_pred.uncertainty_decoder,
                                       anchor_pred.pbr_decoder)  # fmt: skip
            tex = bake(samples, lambda p: _neural_gbuffer(init_pred, p)[0], material_channels(basis),
                       device=device)
            params = NeuralUV(tex, basis)
        else:
            init_pred = LMRMPrediction(init_field, anchor_pred.material_decoder, anchor_pred.uncertainty_decoder,
                                       anchor_pred.pbr_decoder)  # fmt: skip
            tex = bake(samples, lambda p: _pbr_gbuffer(init_pred, p), PBR_CHANNELS, device=device)
            params = PBRUV(tex)
        params.project()
    elif config.material == "neural":
        params = NeuralTriplane(start, _decoder_copy(decoder_for(anchor_pred.material_decoder, basis), config), basis)
    else:
        params = PBRTriplane(start, _decoder_copy(anchor_pred.pbr_decoder, config))
    anchor = None
    if config.reg in ("uncertainty", "oracle") and config.lambda_reg > 0:  # "start": tto/pbr_start.py
        points, uv = scene_mesh.sample_surface(config.reg_pool, seed=config.seed)
        points = points.to(device)
        uv = None if uv is None else uv.to(device)
        with torch.no_grad():
            if config.material == "pbr":
                target = _pbr_gbuffer(anchor_pred, points)
                weight = torch.ones_like(target)
            else:
                target, log_var = _neural_gbuffer(anchor_pred, points)
                if config.reg == "oracle":
                    assert truth is not None
                    weight = oracle_weights(target, truth(points).to(device))
                else:
                    weight = uncertainty_weights(log_var)
        anchor = Anchor(points, uv, target, weight)
    exposure = ExposureFit(photos.count, device) if config.photo_exposure else None
    return TTOProblem(scene_mesh, envmap, photos, tonemap, params, anchor, device, exposure)


def decoder_for(decoder: MaterialDecoder, basis: NeuralBasis) -> MaterialDecoder:
    """The LMRM's material decoder, or where `basis` has another latent size (TTOConfig.basis) its copy of that
    size (`MaterialDecoder.with_latent_dim`: the same copy at every call, since the start's planes are fitted through
    one and read through another, and the export stage reads the result through it)."""
    size = basis.arch.latent_dim  # the copy is frozen like the decoder it is made from
    return decoder if size == decoder.latent_dim else decoder.with_latent_dim(size)


def _decoder_copy(decoder: Any, config: TTOConfig) -> Any:
    """The decoder a triplane parametrisation reads: the frozen one, or a private trainable copy (train_decoder)."""
    if not config.train_decoder:
        return decoder
    return copy.deepcopy(decoder).requires_grad_(True)


def make_optimizer(params: Parametrisation, config: TTOConfig,
                   exposure: ExposureFit | None = None) -> torch.optim.Optimizer:
    """Adam over the field's tensor (group 0), with train_decoder its decoder (lr x decoder_lr) and with `exposure`
    the photos' log-scales (at exposure_lr, on the same cosine schedule). With config.optimizer "gauss_newton" the
    field's tensor takes diagonal Gauss-Newton steps at lr x gn_lr_scale instead (tto/gauss_newton.py), the other
    groups the same Adam steps."""
    gauss_newton = config.optimizer == "gauss_newton"
    groups: list[dict[str, Any]] = [{"params": [params.tensor],
                                     "lr_scale": config.gn_lr_scale if gauss_newton else 1.0}]
    if params.decoder_parameters():
        groups.append({"params": params.decoder_parameters(), "lr_scale": config.decoder_lr})
    if exposure is not None:
        groups.append({"params": [exposure.log_scale], "lr_scale": config.exposure_lr / config.lr})
    betas = (config.adam_beta1, config.adam_beta2)
    if not gauss_newton:
        return torch.optim.Adam(groups, lr=config.lr, betas=betas, eps=config.adam_eps)
    groups[0].update(curvature=True, betas=(config.adam_beta1, config.gn_beta2),
                     block_dim=params.channel_dim if config.gn_block else None)
    return DiagonalGaussNewton(groups, lr=config.lr, betas=betas, eps=config.adam_eps, damping=config.gn_damping,
                               max_step=config.gn_max_step, warmup=config.gn_warmup)


def curvature_generator(config: TTOConfig, step: int, device: torch.device) -> torch.Generator:
    """The generator of step `step`'s Gauss-Newton probe signs: apart from `step_generator`, so the pixels, paths
    and anchor pairs are those of an Adam run with the same seed."""
    return torch.Generator(device=device).manual_seed(config.seed * 1_000_003 + step + 500_000_003)


class IterateAverage:
    """The uniform average of the field's tensor over the last `config.average_tail` of the steps (Polyak-Ruppert
    averaging): each step's tensor carries the noise of its 8-spp gradient, and the mean of the iterates around the
    optimum has less of it than the last one. `update(step, tensor)` after every step; `mean` (None before the tail
    starts) replaces the tensor at the end. The decoder, where TTO trains it, is not averaged."""

    def __init__(self, config: TTOConfig) -> None:
        self.start = config.steps - round(config.average_tail * config.steps)
        self.mean: torch.Tensor | None = None

    def update(self, step: int, tensor: torch.Tensor) -> None:
        """Fold in the tensor after `step` steps (1-based)."""
        n = step - self.start
        if n <= 0:
            return
        t = tensor.detach()
        self.mean = t.clone() if self.mean is None or n == 1 else self.mean + (t - self.mean) / n


def learning_rate(config: TTOConfig, step: int) -> float:
    """Cosine decay from lr to lr * lr_final over the steps; with settle_fraction, over the steps before the settling
    phase, which has its own cosine from lr * settle_lr to lr * settle_lr * settle_lr_final; with lr_warmup, times a
    linear ramp from 1 / lr_warmup to 1 over the first lr_warmup steps."""
    start = config.settle_start()
    if step < start:
        t, top, final = step / max(start, 1), config.lr, config.lr_final
    else:
        t = min((step - start) / max(config.steps - start, 1), 1.0)
        top, final = config.lr * config.settle_lr, config.settle_lr_final
    ramp = min(1.0, (step + 1) / config.lr_warmup) if config.lr_warmup > 0 else 1.0
    return ramp * top * (final + (1 - final) * 0.5 * (1 + math.cos(math.pi * t)))


def step_generator(config: TTOConfig, step: int, device: torch.device) -> torch.Generator:
    """The generator of every random draw of `step`."""
    return torch.Generator(device=device).manual_seed(config.seed * 1_000_003 + step)


def _save_checkpoint(path: Path, config: TTOConfig, step: int, params: Parametrisation,
                     opt: torch.optim.Optimizer, history: list[dict[str, float]],
                     cache_tensor: torch.Tensor | None, exposure: ExposureFit | None = None,
                     average: torch.Tensor | None = None, cv_state: dict[str, Any] | None = None) -> None:
    trained = params.trained_decoder()  # a frozen decoder is not the run's own: nothing to keep
    with replaced_atomically(path) as tmp:
        torch.save({"format": CHECKPOINT_FORMAT, "config": config.to_dict(), "step": step,
                    "tensor": params.tensor.detach().cpu(), "optimizer": opt.state_dict(), "history": history,
                    "decoder": None if trained is None else trained.state_dict(),
                    "cache_tensor": None if cache_tensor is None else cache_tensor.cpu(),
                    "exposure": None if exposure is None else exposure.log_scale.detach().cpu(),
                    "average": None if average is None else average.cpu(),
                    "control_variate": cv_state}, tmp)  # fmt: skip


def _load_checkpoint(path: Path, config: TTOConfig, params: Parametrisation, opt: torch.optim.Optimizer,
                     exposure: ExposureFit | None = None, average: IterateAverage | None = None,
                     ) -> tuple[int, list[dict[str, float]], torch.Tensor | None, dict[str, Any] | None]:
    try:
        state: dict[str, Any] = torch.load(path, map_location=params.tensor.device, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - a torn or foreign file: start over rather than fail
        raise ValueError(f"{path}: unreadable TTO checkpoint ({exc}); delete it to start the TTO over") from None
    if state.get("format") != CHECKPOINT_FORMAT or state.get("config") != config.to_dict():
        raise ValueError(f"{path}: TTO checkpoint of another configuration; delete it to start the TTO over")
    with torch.no_grad():
        params.tensor.copy_(state["tensor"])
    # a frozen decoder is shared: writing it, even with its own values, broke another thread's backward pass
    trained = params.trained_decoder()
    if trained is not None and state.get("decoder") is not None:
        trained.load_state_dict(state["decoder"])
    if exposure is not None and state.get("exposure") is not None:
        with torch.no_grad():
            exposure.log_scale.copy_(state["exposure"])
    opt.load_state_dict(state["optimizer"])
    if average is not None and state.get("average") is not None:
        average.mean = state["average"].to(params.tensor)
    cache_tensor = state.get("cache_tensor")
    return (int(state["step"]), list(state["history"]),
            None if cache_tensor is None else cache_tensor.to(params.tensor), state.get("control_variate"))


class CachedPhotos:
    """The estimator "cached": a TransportCache of `config.cache_pixels` random photo pixels (spp jittered rays
    each), rebuilt every `config.cache_every` steps from the parametrisation's tensor at that step."""

    def __init__(self, problem: TTOProblem, config: TTOConfig, scene: Scene, weights: torch.Tensor | None) -> None:
        self.problem, self.config, self.scene = problem, config, scene
        self.cache_config = TransportCacheConfig(directions=config.cache_directions,
                                                 indirect_bounces=config.max_bounces - 1)  # fmt: skip
        self.cache: TransportCache | None = None
        self.target = torch.empty(0)
        self.frame, self.given = torch.empty(0, dtype=torch.int64), torch.empty(0)
        self.tensor_at_build: torch.Tensor | None = None
        self.weights = weights  # `photo_weights` [M, 3] or None, and below those of the cached pixels
        self.weight_target: torch.Tensor | None = None

    def build(self, step: int, tensor: torch.Tensor) -> None:
        """Cache the transport of round step // cache_every with the material of `tensor` (a copy of the
        parametrisation's tensor at the round's first step)."""
        params, cfg = self.problem.params, self.config
        g = torch.Generator(device=self.problem.device).manual_seed(cfg.seed * 1_000_003 + 7_919 * (step + 1) + 1)
        live = params.tensor.detach().clone()
        with torch.no_grad():
            params.tensor.copy_(tensor)
            batch = self.problem.photos.batch(cfg.cache_pixels, cfg.spp, g)
            self.cache = TransportCache.build(self.scene, batch.origins, batch.directions, g, self.cache_config)
            params.tensor.copy_(live)
        self.target, self.tensor_at_build = batch.target, tensor.detach().clone()
        self.frame, self.given = batch.frame, batch.exposure
        self.weight_target = None if self.weights is None else self.weights[batch.index]

    def loss(self, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """L_photo of `config.pixels` pixels of the current cache: (objective, mse) as `photometric_loss`."""
        assert self.cache is not None
        cfg = self.config
        pix = torch.randint(0, cfg.cache_pixels, (cfg.pixels,), generator=g, device=self.problem.device)
        rays = (pix.unsqueeze(-1) * cfg.spp + torch.arange(cfg.spp, device=pix.device)).reshape(-1)
        radiance = self.cache.radiance(self.problem.params.field(), rays)
        scale = self.problem.photo_scale(self.frame[pix], self.given[pix])
        weight_target = None if self.weight_target is None else self.weight_target[pix]
        return photometric_loss(radiance, self.target[pix], cfg.spp, self.problem.tonemap, scale, cfg.photo_loss,
                                weight_target)  # fmt: skip


def _control_variate(problem: TTOProblem, config: TTOConfig, scene: Scene, tracer: PathTracer,
                     state: dict[str, Any]) -> ControlVariate:
    """The control variate of round state["round"] (tto/control_variate.py): its reference is the field with
    state's tensor and trained decoder (the field at that round's first step, kept in the checkpoint), its radiance of
    every photo pixel rendered with a generator of (config.seed, round)."""
    frozen = copy.deepcopy(problem.params)  # the live parametrisation is not touched
    trained = frozen.trained_decoder()
    with torch.no_grad():
        frozen.tensor.copy_(state["tensor"].to(frozen.tensor))
        if trained is not None and state["decoder"] is not None:
            trained.load_state_dict(state["decoder"])
    g = torch.Generator(device=problem.device).manual_seed(config.seed * 1_000_003 + 7_919 * (state["round"] + 1) + 3)
    return ControlVariate(frozen, scene, problem.photos, tracer, config.cv_spp, g)


def photo_weights(problem: TTOProblem, config: TTOConfig) -> torch.Tensor | None:
    """[M, 3] display values at which the loss weighs each foreground pixel of the photos (None: its own)."""
    if "linear_decorrelated" not in (config.photo_loss, config.settle_photo_loss) or config.photo_weight_radius <= 0:
        return None
    return problem.photos.smoothed_colour(config.photo_weight_radius)


def optimise(problem: TTOProblem, config: TTOConfig, progress: Progress | None = None,
             should_stop: Callable[[], bool] | None = None, checkpoint: Path | None = None) -> TTOResult:
    """Run (or resume from `checkpoint`) the TTO; see the module docstring. `progress(step, total, row)` after every
    step; `should_stop()` is checked before every step: when true the state is checkpointed and the result comes
    back with finished=False."""
    t0 = time.perf_counter()
    params, exposure = problem.params, problem.exposure
    opt = make_optimizer(params, config, exposure)
    step, history = 0, list[dict[str, float]]()
    cache_tensor: torch.Tensor | None = None
    cv_state: dict[str, Any] | None = None  # the control variate's reference: its tensor and trained decoder
    average = IterateAverage(config) if config.average_tail > 0 else None
    origin = params.tensor.detach().clone() if config.lambda_smooth > 0 else None  # before a checkpoint's tensor
    if checkpoint is not None and checkpoint.is_file():
        step, history, cache_tensor, cv_state = _load_checkpoint(checkpoint, config, params, opt, exposure, average)
    scene = Scene(problem.mesh, problem.envmap, params.field(), device=problem.device)
    tracer = PathTracer(PathTracerConfig(max_bounces=config.max_bounces, rr_depth=max(config.max_bounces, 1),
                                         spp=config.spp))  # fmt: skip
    weights = photo_weights(problem, config)
    cached = CachedPhotos(problem, config, scene, weights) if config.estimator == "cached" else None
    if cached is not None and step % config.cache_every != 0:  # resumed inside a round: its cache again
        cached.build(step - step % config.cache_every, params.tensor if cache_tensor is None else cache_tensor)
    anchor = problem.anchor
    variate: ControlVariate | None = None
    while step < config.steps:
        if should_stop is not None and should_stop():
            if checkpoint is not None:
                _save_checkpoint(checkpoint, config, step, params, opt, history,
                                 None if cached is None else cached.tensor_at_build, exposure,
                                 None if average is None else average.mean, cv_state)  # fmt: skip
            return TTOResult(params, history, step, False, time.perf_counter() - t0, problem.mesh,
                             None if exposure is None else exposure.values())  # fmt: skip
        g = step_generator(config, step, problem.device)
        residuals: list[torch.Tensor] = []  # with the Gauss-Newton step: those whose curvature it takes
        lr = learning_rate(config, step)
        for group in opt.param_groups:
            group["lr"] = lr * group["lr_scale"]
        if cached is not None:
            if step % config.cache_every == 0:
                cached.build(step, params.tensor)
            photo, mse_t = cached.loss(g)
        else:
            pixels, spp = config.batch_at(step)
            if config.pixel_order == "shuffled":
                batch = problem.photos.shuffled_batch(config.pixels_before(step), pixels, spp, config.seed, g)
            else:
                batch = problem.photos.batch(pixels, spp, g)
            cv_at = config.cv_round(step)
            if cv_at >= 0 and (cv_state is None or cv_state["round"] != cv_at):  # a new round: this step's field
                trained = params.trained_decoder()
                cv_state = {"round": cv_at, "tensor": params.tensor.detach().cpu().clone(),
                            "decoder": None if trained is None else copy.deepcopy(trained.state_dict())}
                variate = None
            if cv_at >= 0 and variate is None:  # a new round, or resumed inside one (cv_state from the checkpoint)
                assert cv_state is not None
                variate = _control_variate(problem, config, scene, tracer, cv_state)
            twin = clone_generator(g) if cv_at >= 0 else None
            strata = spp // 2 if config.stratified and spp >= 4 else 1  # each half on its own (the decorrelated losses)
            radiance = tracer.render_rays(scene, batch.origins, batch.directions, g, strata)
            if variate is not None and twin is not None:
                radiance = variate.radiance(radiance, batch.origins, batch.directions, batch.index, spp, twin)
            scale = problem.photo_scale(batch.frame, batch.exposure)
            weight_target = None if weights is None else weights[batch.index]
            photo, mse_t = photometric_loss(radiance, batch.target, spp, problem.tonemap, scale, config.loss_at(step),
                                            weight_target)  # fmt: skip
            if isinstance(opt, DiagonalGaussNewton):
                residuals.append(photo_residuals(radiance, batch.target, spp, problem.tonemap, scale))
        loss = photo
        reg = torch.zeros((), device=problem.device)
        cons: torch.Tensor | None = None
        if anchor is not None:
            n = anchor.points.shape[0]
            idx = torch.randint(0, n, (min(config.reg_points, n),), generator=g, device=problem.device)
            if config.lambda_reg > 0:  # the default (consistency term alone) skips this decoder pass
                reg = regulariser(params.gbuffer, anchor, idx)
                loss = photo + config.lambda_reg * reg
            if config.lambda_consistency > 0:  # drawn after idx, so runs without it keep their random numbers
                other = torch.randint(0, n, idx.shape, generator=g, device=problem.device)
                cons_args = (params.gbuffer, anchor, idx, other, config.consistency_sigma, config.consistency_of,
                             config.consistency_rho_value, config.consistency_latent_value)
                cons = consistency(*cons_args)
                loss = loss + config.lambda_consistency * cons
                if isinstance(opt, DiagonalGaussNewton):
                    residuals += [r * config.lambda_consistency**0.5 for r in consistency_residuals(*cons_args)]
        smooth: torch.Tensor | None = None
        if origin is not None:
            smooth = params.texel_variation(origin)
            loss = loss + config.lambda_smooth * smooth
        opt.zero_grad(set_to_none=True)
        loss.backward(retain_graph=bool(residuals))
        if isinstance(opt, DiagonalGaussNewton):
            probe = sign_probe(residuals, curvature_generator(config, step, problem.device))
            opt.fold_curvature(torch.autograd.grad(probe, [params.tensor], allow_unused=True))
            del probe, residuals
        if (factor := config.coarse_at(step)) > 1:
            params.coarsen_gradient(factor)
        opt.step()
        params.project()
        if exposure is not None:
            exposure.project()
        step += 1
        if average is not None:
            average.update(step, params.tensor)
        mse = float(mse_t)
        row = {"step": float(step), "loss": float(loss.detach()), "photo": mse, "reg": float(reg.detach()),
               "psnr": 10 * math.log10(1 / max(mse, 1e-12)), "lr": lr}  # fmt: skip
        if cons is not None:
            row["consistency"] = float(cons.detach())
        if smooth is not None:
            row["smooth"] = float(smooth.detach())
        if exposure is not None:  # the largest fitted exposure correction so far, in stops (|log2 s_f|)
            row["exposure_stops_max"] = float(exposure.scale().detach().log2().abs().max())
        history.append(row)
        if progress is not None:
            progress(step, config.steps, row)
        if checkpoint is not None and config.checkpoint_every and step % config.checkpoint_every == 0:
            _save_checkpoint(checkpoint, config, step, params, opt, history,
                             None if cached is None else cached.tensor_at_build, exposure,
                             None if average is None else average.mean, cv_state)  # fmt: skip
    if average is not None and average.mean is not None:  # the result is the tail's mean iterate
        with torch.no_grad():
            params.tensor.copy_(average.mean)
        params.project()
    if checkpoint is not None:
        _save_checkpoint(checkpoint, config, step, params, opt, history,
                         None if cached is None else cached.tensor_at_build, exposure,
                         None if average is None else average.mean, cv_state)  # fmt: skip
    return TTOResult(params, history, step, True, time.perf_counter() - t0, problem.mesh,
                     None if exposure is None else exposure.values())  # fmt: skip
