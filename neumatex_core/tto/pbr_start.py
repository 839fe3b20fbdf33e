"""Neural TTO that starts where PBR ends (init="pbr"; docs/design-notes.md, "neural from PBR").

    result = solve(config, mesh, envmap, photos, tonemap, prediction, basis, checkpoint_dir=work / "tto")

`solve` runs any TTO variant. With init="pbr" it runs two phases: the PBR baseline's TTO (the LMRM's PBR head and
triplane, no anchor, `config.pbr_steps` steps, checkpoint `checkpoint_pbr.pt`), then the neural TTO from that
solution: the neural triplane's planes are fitted (the material decoder frozen) so that its G-buffers equal the PBR
field's base colour, roughness and metallic expressed in the basis (`materials/pbr_to_neural.py`) at area-uniform
surface points, then (`config.pbr_bsdf_fit_steps` > 0) refined so that its BSDF itself matches PBR's
(`refine_to_pbr_bsdf`: the encoder's conversion is only as good as the encoder, and it loses coloured conductors),
and the neural TTO goes on from there (`config.steps` steps, checkpoint `checkpoint.pt`). So the neural material
begins at the PBR fit (up to the basis's and the fit's error, which the history records as `start_mse`) and the
photos pull it towards the lobes PBR lacks.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np
import torch

from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.device import runs_side_by_side, side_by_side, torch_threads
from neumatex_core.fields.fit import fit_on_points
from neumatex_core.geometry.camera import Camera
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.lmrm.inference import LMRMPrediction
from neumatex_core.materials.basis_training import log_target, uniform_hemisphere
from neumatex_core.materials.neural_basis import NeuralBasis, NeuralMaterial, load_basis
from neumatex_core.materials.pbr import PBRMaterial
from neumatex_core.materials.pbr_to_neural import pbr_to_neural
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.tto.appearance_start import StartAt, appearance_start
from neumatex_core.tto.baked_light import light_following
from neumatex_core.tto.config import UNIFORM_RHO_VALUE, TTOConfig
from neumatex_core.tto.data import PhotoSet
from neumatex_core.tto.lmrm_start import lmrm_blend, lmrm_share
from neumatex_core.tto.loss import Anchor, photometric_loss
from neumatex_core.tto.optimise import Progress, Truth, TTOResult, build_problem, optimise
from neumatex_core.tto.params import NeuralTriplane, Parametrisation, PBRTriplane

FIT_POINTS = 1 << 15  # area samples the start is fitted on
# The start fit's schedule when no config is given: TTOConfig's defaults, written once there.
FIT_STEPS: int = TTOConfig.pbr_fit_steps
FIT_LR: float = TTOConfig.pbr_fit_lr
FIT_BATCH: int = TTOConfig.pbr_fit_batch
BSDF_FIT_BATCH = 4096  # surface points per step of `refine_to_pbr_bsdf`, one (wi, wo) pair each
BSDF_FIT_LR = 0.02
VALIDATION_RAYS = 1 << 16  # rays per chunk of that render
VALIDATION_NEIGHBOUR_DEG = 30.0  # a held-out photo needs a fitted one within this angle (the orbit's step is 21)


def fit_planes(neural: NeuralTriplane, points: torch.Tensor, rho_d: torch.Tensor, latent: torch.Tensor, seed: int = 0,
               steps: int = FIT_STEPS, lr: float = FIT_LR, batch: int = FIT_BATCH) -> float:
    """Fit the planes of `neural` (in place; its decoder stays as it is) to G-buffers rho_d [P, 3], latent [P, 6]
    at surface points [P, 3] (`steps` Adam steps of `batch` points drawn with replacement, at `lr` cosine-decayed
    to 0); returns the final mean squared error on (rho_d, (latent + 1) / 2), the G-buffer
    metric's scale. The decoder is not fitted even where TTO fine-tunes it: at this fit's learning rate it saturated
    (benchmark object 6: start error 0.08 instead of 1e-3, PathTrace 5.8 dB; docs/design-notes.md item 39), and a
    start made with the frozen decoder is the same whether or not TTO fine-tunes it afterwards."""
    want = torch.cat([rho_d, (latent + 1) / 2], dim=-1).detach()

    def error(idx: torch.Tensor | None = None) -> torch.Tensor:
        p, w = (points, want) if idx is None else (points[idx], want[idx])
        got = neural.gbuffer(p, None)
        return ((torch.cat([got[:, :3], (got[:, 3:] + 1) / 2], dim=-1) - w) ** 2).mean()

    with frozen(neural.decoder):
        fit_on_points([neural.tensor], error, points.shape[0], steps, lr, batch, seed, points.device)
    with torch.no_grad():
        return float(error())


@contextmanager
def frozen(module: torch.nn.Module | None) -> Iterator[None]:
    """Within the block the trainable weights of `module` (None: nothing to do) get no gradient; after it they are
    trainable again. For fits that step the planes alone under a decoder the TTO fine-tunes (TTOConfig.train_decoder):
    its weights' gradients would be computed for nothing, a quarter of `fit_planes`'s time; the planes' gradients
    are the same bit for bit (docs/design-notes.md item 43)."""
    trainable = [] if module is None else [w for w in module.parameters() if w.requires_grad]
    for w in trainable:
        w.requires_grad_(False)
    try:
        yield
    finally:
        for w in trainable:
            w.requires_grad_(True)


def fit_start_to_pbr(neural: NeuralTriplane, pbr: PBRTriplane, mesh: Mesh, basis: NeuralBasis, seed: int = 0,
                     steps: int = FIT_STEPS, bsdf_steps: int = 0, lr: float = FIT_LR,
                     batch: int = FIT_BATCH, adjust: Adjust | None = None) -> float:
    """Fit the planes of `neural` to the PBR field `pbr` expressed in the basis (`fit_planes` at area samples), then
    (bsdf_steps > 0) refine them at the same samples so the BSDFs match (`refine_to_pbr_bsdf`); returns the
    G-buffer fit's error. adjust: changes the start's (rho_d, latent) at the samples before the fit, given them, the
    samples [P, 3] and the PBR start at any points (`pbr_start_at`), e.g. `appearance_start`."""
    points, _ = mesh.sample_surface(FIT_POINTS, seed=seed)
    points = points.to(neural.tensor.device)
    start_at = partial(pbr_start_at, pbr, basis)
    rho, latent = start_at(points)
    if adjust is not None:
        rho, latent = adjust(points, rho, latent, start_at)
    error = fit_planes(neural, points, rho, latent, seed, steps, lr, batch)
    if bsdf_steps > 0:
        with torch.no_grad():
            values = pbr.gbuffer(points, None)
        refine_to_pbr_bsdf(neural, basis, points, values, seed, bsdf_steps)
    return error


def pbr_start_at(pbr: PBRTriplane, basis: NeuralBasis, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(rho_d [P, 3], latent [P, D]): the PBR field `pbr` at points [P, 3] expressed in `basis` (`pbr_to_neural`)."""
    with torch.no_grad():
        v = pbr.gbuffer(points, None)
        return pbr_to_neural(basis, v[:, :3], v[:, 3], v[:, 4])


# (points [P, 3], rho_d [P, 3], latent [P, D], the PBR start at any points) -> the start's (rho_d, latent) there
Adjust = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, StartAt], tuple[torch.Tensor, torch.Tensor]]


def refine_to_pbr_bsdf(neural: NeuralTriplane, basis: NeuralBasis, points: torch.Tensor, pbr_values: torch.Tensor,
                       seed: int = 0, steps: int = 300) -> float:
    """Refine the planes of `neural` (in place; its decoder stays as it is, as in `fit_planes`) so that its BSDF
    equals the PBR material's at surface points [P, 3], whose PBR G-buffers are pbr_values [P, 5] (base colour,
    roughness, metallic; `PBRTriplane.gbuffer`): the loss the basis is trained with (materials/basis_training.py: L1 of
    log(f cos_i + EPS), relative error on peaks and tails alike) between the neural material's whole f (diffuse and
    f_neu) and PBR's; wo uniform on the hemisphere, wi half from PBR's importance sampler (its specular peak), half
    uniform; fresh directions every step. Returns the last step's loss (mean log-L1)."""
    device = points.device
    want = pbr_values.detach()
    opt = torch.optim.Adam([neural.tensor], lr=BSDF_FIT_LR)
    g = torch.Generator().manual_seed(seed + 1)  # directions are drawn on the CPU, like the basis's training
    loss = torch.zeros(())
    with frozen(neural.decoder):
        for step in range(steps):
            for group in opt.param_groups:
                group["lr"] = BSDF_FIT_LR * 0.5 * (1 + math.cos(math.pi * step / steps))
            idx = torch.randint(0, points.shape[0], (BSDF_FIT_BATCH,), generator=g).to(device)
            v = want[idx]
            target = PBRMaterial(v[:, :3], v[:, 3], v[:, 4])
            n = idx.shape[0]
            wo = uniform_hemisphere(n, g).to(device)
            u_lobe, u_dir = torch.rand(n, generator=g).to(device), torch.rand(n, 2, generator=g).to(device)
            wi_peak, _ = target.sample(wo, u_lobe, u_dir)
            wi_uniform = uniform_hemisphere(n, g).to(device)
            use_peak = (torch.rand(n, generator=g) < 0.5).to(device).unsqueeze(-1) & (wi_peak[:, 2:3] > 1e-4)
            wi = torch.where(use_peak, wi_peak, wi_uniform)
            got = neural.gbuffer(points[idx], None)
            material = NeuralMaterial(basis, got[:, :3], got[:, 3:])
            cos_i = wi[:, 2]
            with torch.no_grad():
                log_want = log_target(target.eval(wi, wo), cos_i)
            loss = (log_target(material.eval(wi, wo), cos_i) - log_want).abs().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    return float(loss.detach())


def solve(config: TTOConfig, mesh: Mesh, envmap: EnvironmentMap, photos: PhotoSet, tonemap: Tonemap,
          prediction: LMRMPrediction, basis: NeuralBasis, anchor_available: bool = True, truth: Truth | None = None,
          progress: Progress | None = None, should_stop: Callable[[], bool] | None = None,
          checkpoint_dir: Path | None = None) -> TTOResult:
    """Run the TTO variant `config` (see the module docstring); stopped and resumed like `optimise`."""
    checkpoint = partial(_checkpoint, checkpoint_dir)
    if config.init != "pbr":
        problem = build_problem(config, mesh, envmap, photos, tonemap, prediction, basis, anchor_available, truth)
        return optimise(problem, config, progress, should_stop, checkpoint("checkpoint.pt"))
    if config.select_anchor or config.select_uniform:
        return _solve_selecting(config, mesh, envmap, photos, tonemap, prediction, basis, anchor_available, truth,
                                progress, should_stop, checkpoint_dir)  # fmt: skip
    total = config.total_steps()
    first = _pbr_phase(config, mesh, envmap, photos, tonemap, prediction, basis, anchor_available,
                       _offset(progress, 0, total, 0.0), should_stop, checkpoint("checkpoint_pbr.pt"))
    if not first.finished:
        return first
    start = neural_start(config, first, mesh, envmap, photos, None, tonemap, prediction, basis, anchor_available)
    result = _neural_phase(config, first, mesh, envmap, photos, tonemap, prediction, start.basis, anchor_available,
                           truth, _offset(progress, config.pbr_steps, total, 1.0), should_stop,
                           checkpoint("checkpoint.pt"), start)  # fmt: skip
    result.selection = {**result.selection, **start.record}
    result.basis = start.basis if start.switched else None
    result.pbr_solution = first.params
    return result


def _checkpoint(checkpoint_dir: Path | None, name: str) -> Path | None:
    """The checkpoint file `name` in `checkpoint_dir`, or None (no checkpoints) when there is no folder."""
    return None if checkpoint_dir is None else Path(checkpoint_dir) / name


def _offset(progress: Progress | None, offset: int, total: int, phase: float) -> Progress | None:
    """A phase's progress reported as steps of the whole TTO (`total`), its rows tagged with `phase`."""
    return None if progress is None else (lambda s, _n, row: progress(offset + s, total, {**row, "phase": phase}))


class _JointReports:
    """The progress and should_stop callbacks of phases that may run side by side (`side_by_side`): each phase's
    steps count towards the whole TTO's (`total`) after `offset`, so the bar moves on as either advances, and the
    caller's callbacks are never entered by two threads at once. Rows are tagged phase 1 (the choice's)."""

    def __init__(self, progress: Progress | None, should_stop: Callable[[], bool] | None, offset: int, total: int,
                 count: int) -> None:
        self._progress, self._should_stop, self.offset, self.total = progress, should_stop, offset, total
        self._done = [0] * count
        self._lock = threading.Lock()

    def progress_of(self, k: int) -> Progress | None:
        """Phase k's progress callback (None without the caller's)."""
        report = self._progress
        if report is None:
            return None

        def step(s: int, _n: int, row: dict[str, float]) -> None:
            with self._lock:
                self._done[k] = s
                report(self.offset + sum(self._done), self.total, {**row, "phase": 1.0})
        return step

    def stop_check(self) -> Callable[[], bool] | None:
        """The caller's should_stop, one thread at a time (None without one)."""
        ask = self._should_stop
        if ask is None:
            return None

        def stop() -> bool:
            with self._lock:
                return ask()
        return stop


def _pbr_phase(config: TTOConfig, mesh: Mesh, envmap: EnvironmentMap, photos: PhotoSet, tonemap: Tonemap,
               prediction: LMRMPrediction, basis: NeuralBasis, anchor_available: bool, progress: Progress | None,
               should_stop: Callable[[], bool] | None, checkpoint: Path | None) -> TTOResult:
    """Phase one: the PBR baseline's TTO from the LMRM's PBR head, `config.pbr_steps` steps."""
    # The phases start from the LMRM's structure (its PBR head; its triplane, refitted below). config.basis only
    # named the basis the caller loaded (`basis`), so the phases drop it: LMRM-shaped starts are theirs by design.
    # The schedule's settling, the smoothness term and Adam's settings are the neural phase's: the PBR phase is the
    # baseline's own TTO.
    pbr_config = replace(config, material="pbr", init="lmrm", reg="none", steps=config.pbr_steps, basis="",
                         select_anchor=False, select_uniform=False, select_basis="", alternative_basis="",
                         select_lmrm_start=False, settle_fraction=0.0, lambda_smooth=0.0, coarse_factor=1,
                         optimizer="adam", control_variate="off", lr_warmup=0,
                         adam_beta1=TTOConfig.adam_beta1, adam_beta2=TTOConfig.adam_beta2, adam_eps=TTOConfig.adam_eps)
    pbr_problem = build_problem(pbr_config, mesh, envmap, photos, tonemap, prediction, basis, anchor_available)
    return optimise(pbr_problem, pbr_config, progress, should_stop, checkpoint)


def _neural_phase(config: TTOConfig, first: TTOResult, mesh: Mesh, envmap: EnvironmentMap, photos: PhotoSet,
                  tonemap: Tonemap, prediction: LMRMPrediction, basis: NeuralBasis, anchor_available: bool,
                  truth: Truth | None, progress: Progress | None, should_stop: Callable[[], bool] | None,
                  checkpoint: Path | None, start: BasisStart, resume: TTOResult | None = None) -> TTOResult:
    """Phase two: the neural triplane from `start`, the PBR solution `first` fitted in `basis` (`neural_start`),
    then `config.steps` steps of neural TTO (anchored to that start with weight
    config.lambda_reg when reg is "start"). The history holds both phases. With `resume` (an earlier neural phase
    from the same start: the choice's candidate, config.select_continue) the steps go on from its planes and its
    decoder, still anchored to `start`, and the history holds `resume`'s rows between the two."""
    # reg "start" is this function's anchor (set on the problem below), not one build_problem makes
    other_basis = start.switched or bool(config.basis)
    neural_config = replace(config, init="lmrm", basis="", reg="none" if config.reg == "start" else config.reg,
                            lr=config.lr * config.neural_lr_scale, select_anchor=False,
                            select_uniform=False, select_basis="", alternative_basis="", select_lmrm_start=False,
                            train_decoder=config.train_decoder and (config.decoder_in_other_basis or not other_basis))
    problem = build_problem(neural_config, mesh, envmap, photos, tonemap, prediction, basis, anchor_available, truth)
    assert isinstance(problem.params, NeuralTriplane) and isinstance(first.params, PBRTriplane)
    if problem.exposure is not None and first.exposure is not None:  # the photos' exposures go on from phase one
        problem.exposure.start_at(first.exposure)
    with torch.no_grad():  # the fitted planes (the decoder is not fitted: `fit_planes`)
        problem.params.tensor.copy_(start.planes)
    start_mse = start.mse
    if config.reg == "start" and (config.lambda_reg > 0 or config.lambda_consistency > 0):  # weight 1: the start
        points, uv = problem.mesh.sample_surface(config.reg_pool, seed=config.seed)
        points = points.to(problem.params.tensor.device)
        with torch.no_grad():
            target = problem.params.gbuffer(points, None)
        weight = torch.ones_like(target)
        if config.lmrm_start_anchor:  # held where the start is the LMRM's (tto/lmrm_start.py)
            weight = lmrm_share(prediction, basis, points, config.lmrm_start_var, target.shape[1] - 3)
        problem.anchor = Anchor(points, None if uv is None else uv.to(points.device), target, weight)
    earlier: list[dict[str, float]] = []
    if resume is not None:  # after the anchor: that stays the start's G-buffer
        assert isinstance(resume.params, NeuralTriplane)
        with torch.no_grad():
            problem.params.tensor.copy_(resume.params.tensor)
            trained, tuned = problem.params.trained_decoder(), resume.params.trained_decoder()
            if trained is not None and tuned is not None:
                trained.load_state_dict(tuned.state_dict())
        earlier = [row for row in resume.history if row.get("phase") == 1.0]
    second = optimise(problem, neural_config, progress, should_stop, checkpoint)
    second.history = [*({**row, "phase": 0.0} for row in first.history), *earlier,
                      *({**row, "phase": 1.0, "start_mse": start_mse} for row in second.history)]
    return second


def validation_frames(cameras: Sequence[Camera], k: int, centre: np.ndarray,
                      neighbour_deg: float = VALIDATION_NEIGHBOUR_DEG) -> list[int]:
    """Up to k photo indices (sorted) held out by `select_anchor` / `select_uniform`: spread over the capture
    (every (count / k)-th photo, from the middle of the first stride; a slot that fails moves on to the next
    index), each seen from within neighbour_deg of it by a photo that stays in the fit (directions from `centre`
    [3], the object's centre, to the cameras). So the held-out photos test how the fit reproduces surface it saw
    from nearby, not how either result extrapolates to surface no fitted photo shows: the preset views' bottom view
    (-Y) sees the underside alone, and holding it out made that extrapolation, where the anchor always wins, decide
    the choice (docs/design-notes.md, item 32). ValueError when no photo has such a neighbour, or fewer than k + 1
    photos."""
    count = len(cameras)
    if count <= k:
        raise ValueError(f"TTO select_anchor / select_uniform holds out {k} photos to choose, but the capture has "
                         f"only {count}; lower validation_photos or turn the choice off")
    dirs = np.stack([c.position - centre for c in cameras])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True).clip(1e-12)
    near = dirs @ dirs.T >= math.cos(math.radians(neighbour_deg))  # [F, F] within the angle (itself included)
    held: list[int] = []
    for base in spread_frames(count, k):
        for step in range(count):
            f = (base + step) % count
            trial = held + [f]
            fit = np.ones(count, dtype=bool)
            fit[trial] = False
            if f not in held and all(near[h, fit].any() for h in trial):
                held = trial
                break
    if not held:
        raise ValueError(f"TTO select_anchor / select_uniform needs held-out photos seen from within "
                         f"{neighbour_deg:g} degrees by another photo, and none of the capture's {count} is; turn "
                         "the choice off")
    return sorted(held)


def photo_psnr(params: Parametrisation, mesh: Mesh, envmap: EnvironmentMap, photos: PhotoSet, tonemap: Tonemap,
               config: TTOConfig, seed: int) -> float:
    """Clean PSNR (dB, display values) of the material `params` against `photos`, rendered at every
    config.validation_stride-th foreground pixel (config.validation_spp path samples each, the photos' given
    exposures): -10 log10 of the mean product of the errors of the two halves of each pixel's samples
    (`photometric_loss` "decorrelated"), so our render's Monte Carlo noise, which at these sample counts is larger
    than the difference between two materials, drops out. Deterministic in seed: two materials scored with one seed
    share their pixels' jitter and light samples (common random numbers)."""
    device = photos.device
    scene = Scene(mesh, envmap, params.field(), device=device)
    spp = config.validation_spp
    tracer = PathTracer(PathTracerConfig(max_bounces=config.max_bounces, rr_depth=max(config.max_bounces, 1), spp=spp))
    g = torch.Generator(device=device).manual_seed(seed)
    pixels = torch.arange(0, photos.size, config.validation_stride, device=device)
    chunk = max(1, VALIDATION_RAYS // spp)
    total = 0.0
    with torch.no_grad():
        for idx in pixels.split(chunk):
            rays = photos.rays(idx, spp, g)
            radiance = tracer.render_rays(scene, rays.origins, rays.directions, g)
            product, _ = photometric_loss(radiance, rays.target, spp, tonemap, rays.exposure, "decorrelated")
            total += float(product) * idx.shape[0]
    return 10 * math.log10(1 / max(total / pixels.shape[0], 1e-12))


def spread_frames(count: int, k: int) -> list[int]:
    """Up to k photo indices (sorted) spread over a capture of `count`: every (count / k)-th, from the middle of the
    first stride."""
    return sorted({int((slot + 0.5) * count / k) for slot in range(min(k, count))})


@dataclass
class BasisStart:
    """The neural phase's start that `choose_basis` chose: the planes fitted to the PBR solution in `basis`, their
    G-buffer error `mse` (`fit_start_to_pbr`), whether `basis` is config.alternative_basis (`switched`) and the
    scores that chose it (`record`, dB: basis_pbr_psnr, basis_start_psnr, basis_alternative_psnr when the
    alternative was tried, basis_switched 0 or 1; with config.appearance_start also the chosen start's own record,
    `FittedStart.record`)."""

    basis: NeuralBasis
    planes: torch.Tensor
    mse: float
    switched: bool
    record: dict[str, float]


def alternative_wins(pbr_psnr: float, own: float, other: float | None, margin: float) -> bool | None:
    """The rule of `choose_basis` on photo PSNRs (dB) of the PBR solution, its start in the configured basis and in
    the alternative (None: not made): the alternative is taken only where the configured basis's start loses more
    than `margin` to PBR and the alternative's beats it by more than `margin`; None when that needs `other`."""
    if pbr_psnr - own <= margin:
        return False
    return None if other is None else other - own > margin


@dataclass
class FittedStart:
    """`fit_start`'s result: the neural triplane `params` fitted to the PBR solution, on `mesh` (None: the
    caller's), with G-buffer error `mse` (`fit_start_to_pbr`) and `record` (config.appearance_start's,
    `appearance_start`, and config.lmrm_start_var's, `lmrm_blend`; else empty)."""

    params: NeuralTriplane
    mesh: Mesh | None
    mse: float
    record: dict[str, float]


def fit_start(config: TTOConfig, first: TTOResult, mesh: Mesh, envmap: EnvironmentMap, photos: PhotoSet,
              tonemap: Tonemap, prediction: LMRMPrediction, basis: NeuralBasis,
              anchor_available: bool) -> FittedStart:
    """The PBR solution `first` expressed in `basis`: the neural phase's problem (`_neural_phase`: the same planes to
    start from, the same fit), its planes fitted by `fit_start_to_pbr`; with config.appearance_start, the cells
    that a family prototype reproduces better on `photos` start there (`appearance_start`); with
    config.lmrm_start_var, the start is then blended with the LMRM's prediction (`lmrm_blend`)."""
    neural_config = replace(config, init="lmrm", basis="", reg="none", select_anchor=False, select_uniform=False,
                            select_basis="", alternative_basis="", select_lmrm_start=False)
    problem = build_problem(neural_config, mesh, envmap, photos, tonemap, prediction, basis, anchor_available)
    assert isinstance(problem.params, NeuralTriplane) and isinstance(first.params, PBRTriplane)
    record: dict[str, float] = {}
    adjust: Adjust | None = None
    if config.appearance_start or config.lmrm_start_var > 0:
        def adjust(points: torch.Tensor, rho: torch.Tensor, latent: torch.Tensor,
                   start_at: StartAt) -> tuple[torch.Tensor, torch.Tensor]:
            if config.appearance_start:
                rho, latent, made = appearance_start(basis, points, rho, latent, start_at, mesh, envmap, photos,
                                                     tonemap, config.max_bounces, config.seed)  # fmt: skip
                record.update(made)
            if config.lmrm_start_var > 0:
                rho, latent, made = lmrm_blend(prediction, basis, points, rho, latent, config.lmrm_start_var)
                record.update(made)
            return rho, latent
    mse = fit_start_to_pbr(problem.params, first.params, problem.mesh, basis, config.seed, config.pbr_fit_steps,
                           config.pbr_bsdf_fit_steps, config.pbr_fit_lr, config.pbr_fit_batch, adjust)
    return FittedStart(problem.params, problem.mesh, mse, record)


def choose_basis(config: TTOConfig, first: TTOResult, mesh: Mesh, envmap: EnvironmentMap, photos: PhotoSet,
                 scoring: PhotoSet | None, tonemap: Tonemap, prediction: LMRMPrediction, basis: NeuralBasis,
                 anchor_available: bool) -> BasisStart | None:
    """config.alternative_basis: the basis the neural phase starts in. The PBR solution `first` (fitted on `photos`)
    is expressed in `basis` (`fit_start_to_pbr`) and both are scored on the photos `scoring` (`photo_psnr`, one
    seed; None: config.validation_photos of `photos` spread over the capture). The start fits no photo, so photos
    the PBR phase fitted are fair here. When the start loses more than
    config.basis_margin_db to PBR, the basis cannot hold the PBR solution (the default basis turns a coloured metal
    grey: Cycles metals 7 dB below PBR), so the start is also made in the alternative basis, which is taken when it
    scores better than the start in `basis` by more than basis_margin_db. None without an alternative (or when it
    is `basis`): `neural_start` then fits the start in `basis` alone."""
    if not config.alternative_basis:
        return None
    device = str(first.params.tensor.device)
    alternative = load_basis(device, config.alternative_basis)
    if alternative.basis_id == basis.basis_id:
        return None
    scored = photos.subset(spread_frames(photos.count, config.validation_photos)) if scoring is None else scoring

    def start_in(candidate: NeuralBasis) -> tuple[torch.Tensor, float, float, dict[str, float]]:
        made = fit_start(config, first, mesh, envmap, photos, tonemap, prediction, candidate, anchor_available)
        score = photo_psnr(made.params, made.mesh or mesh, envmap, scored, tonemap, config, config.seed + 1)
        return made.params.tensor.detach().clone(), made.mse, score, made.record

    pbr_psnr = photo_psnr(first.params, first.mesh or mesh, envmap, scored, tonemap, config, config.seed + 1)
    # Where two tasks run side by side (two torch threads or more on the CPU) the start in the alternative is made
    # beside the start in `basis` before it is known to be needed. Where it is needed (the demo's coated teapot, the
    # Cycles metals, 9 of 16 benchmark objects) that saved 12-28 s of the demo's TTO; where it is not, the start in
    # `basis` takes about 2 / 1.77 times as long as alone (two tasks on two threads: docs/design-notes.md items 44
    # and 47). Each start is the same as made alone on one thread.
    beside: tuple[torch.Tensor, float, float, dict[str, float]] | None = None
    if runs_side_by_side(2, first.params.tensor.device):
        (planes, mse, own, made), beside = side_by_side([partial(start_in, basis), partial(start_in, alternative)],
                                                        first.params.tensor.device)  # fmt: skip
    else:
        planes, mse, own, made = start_in(basis)
    record = {"basis_pbr_psnr": pbr_psnr, "basis_start_psnr": own}
    chosen = BasisStart(basis, planes, mse, False, record)
    if alternative_wins(pbr_psnr, own, None, config.basis_margin_db) is None:  # the configured basis loses to PBR
        other_planes, other_mse, other, other_made = beside if beside is not None else start_in(alternative)
        record["basis_alternative_psnr"] = other
        if alternative_wins(pbr_psnr, own, other, config.basis_margin_db):
            chosen, made = BasisStart(alternative, other_planes, other_mse, True, record), other_made
    record.update(made)  # the chosen start's own record (config.appearance_start's; else empty)
    record["basis_switched"] = float(chosen.switched)
    return chosen


def neural_start(config: TTOConfig, first: TTOResult, mesh: Mesh, envmap: EnvironmentMap, photos: PhotoSet,
                 scoring: PhotoSet | None, tonemap: Tonemap, prediction: LMRMPrediction, basis: NeuralBasis,
                 anchor_available: bool) -> BasisStart:
    """The neural phase's start, fitted once per PBR solution `first`: `choose_basis`'s, or without an alternative
    basis the solution fitted in `basis` (`fit_start`; an empty record)."""
    chosen = choose_basis(config, first, mesh, envmap, photos, scoring, tonemap, prediction, basis, anchor_available)
    if chosen is not None:
        return chosen
    made = fit_start(config, first, mesh, envmap, photos, tonemap, prediction, basis, anchor_available)
    return BasisStart(basis, made.params.tensor.detach().clone(), made.mse, False, made.record)


@dataclass(frozen=True)
class Choice:
    """One of the choices `_solve_selecting` makes between two candidate configs made from the config (select flags
    off): `candidates` builds them, the more constrained first; the first is kept unless the second reproduces the
    held-out photos better by more than select_margin_db (a freer fit must earn its freedom on photos it did not
    fit). `names` label them in checkpoints and the selection record, whose `kept_key` is 1 when the first was kept."""

    names: tuple[str, str]
    candidates: Callable[[TTOConfig], tuple[TTOConfig, TTOConfig]]
    kept_key: str
    fallback: int  # the candidate run when the capture has no photos to hold out (validation_frames refuses)


CHOICES = {
    # the anchor to the start's values (config.lambda_reg), or none; without held-out photos the anchored one
    "select_anchor": Choice(("anchored", "free"), lambda c: (c, replace(c, lambda_reg=0.0)), "anchor_kept", 0),
    # one uniform material (the base colours' values compared too), or the consistency term as configured; without
    # held-out photos textured, which costs a uniform object less than uniform costs a textured one
    "select_uniform": Choice(("uniform", "textured"),
                             lambda c: (replace(c, consistency_rho_value=UNIFORM_RHO_VALUE), c), "uniform_kept", 1),
}


def in_select_basis(config: TTOConfig) -> TTOConfig:
    """config run in its config.select_basis (`TTOConfig.select_basis`): that basis alone, no alternative, the
    decoder fine-tuned there; the choice's switches as configured (the plain TTO of that basis)."""
    return replace(config, basis=config.select_basis, select_basis="", alternative_basis="",
                   decoder_in_other_basis=True)


@dataclass
class _Candidates:
    """One basis's side of the choice: its candidate configs (`Choice.candidates`), its start, its candidates'
    results and held-out scores, the one its rule keeps and that one's score."""

    configs: tuple[TTOConfig, TTOConfig]
    start: BasisStart
    runs: list[tuple[TTOResult, float]]
    kept: int
    score: float


def _solve_selecting(config: TTOConfig, mesh: Mesh, envmap: EnvironmentMap, photos: PhotoSet, tonemap: Tonemap,
                     prediction: LMRMPrediction, basis: NeuralBasis, anchor_available: bool, truth: Truth | None,
                     progress: Progress | None, should_stop: Callable[[], bool] | None,
                     checkpoint_dir: Path | None) -> TTOResult:
    """config.select_anchor (the anchor to the start, config.lambda_reg, or none) or config.select_uniform (one
    uniform material: the consistency term with the base colours' values too, or the term as configured; `CHOICES`).
    First the choice: both phases on all photos but `validation_frames`, the neural phase with either candidate
    (config.select_steps() steps), each result scored on the held-out photos (`photo_psnr`, one seed for both); the
    first (more constrained) candidate stays unless the second gains more than config.select_margin_db. With
    config.select_basis the same two candidates also run in that basis (`in_select_basis`, from the same PBR
    solution), which is taken when its kept candidate beats the configured basis's by more than select_margin_db;
    with config.select_lmrm_start each basis's two also run from the LMRM's start (`TTOConfig.lmrm_started`), each
    such side taken when its kept candidate beats the side taken so far by more than select_margin_db (item 98).
    Then the TTO with that choice on every photo, so the result is exactly what the plain TTO with the chosen config
    gives (the held-out photos cost the result nothing: leaving 4 of 23 views out cost a Cycles coat 0.6 dB); or, with
    config.select_reuse_start, its neural phase alone on every photo from the start the choice made (the held-out
    photos then reach the result through the neural phase only; docs/design-notes.md item 40), and with
    config.select_continue only its remaining steps, from the chosen candidate (item 45). Its `selection`
    records the scores and the choice. A capture with no photos to hold out gets the choice's fallback candidate
    (`Choice.fallback`; its selection's validation_photos is 0) in the configured basis."""
    checkpoint = partial(_checkpoint, checkpoint_dir)
    switch = "select_anchor" if config.select_anchor else "select_uniform"
    choice = CHOICES[switch]
    plain = replace(config, select_anchor=False, select_uniform=False, select_basis="", select_lmrm_start=False)
    candidates = choice.candidates(plain)
    total = config.run_steps()
    try:
        held_out = validation_frames(photos.cameras, config.validation_photos, mesh.bounding_sphere()[0])
    except ValueError:  # too few photos, or none with a neighbour: no choice to make, the fallback's plain TTO
        held_out = []
    chosen, selection = choice.fallback, {choice.kept_key: float(choice.fallback == 0), "validation_photos": 0.0}
    start: BasisStart | None = None
    first: TTOResult | None = None
    runs: list[tuple[TTOResult, float]] = []  # the chosen basis's candidates' results and scores
    fit = [i for i in range(photos.count) if i not in held_out]
    if held_out:
        fit_photos, held_photos = photos.subset(fit), photos.subset(held_out)
        first = _pbr_phase(candidates[0], mesh, envmap, fit_photos, tonemap, prediction, basis, anchor_available,
                           _offset(progress, 0, total, 0.0), should_stop, checkpoint("select_pbr.pt"))
        if not first.finished:
            return first
        steps = config.select_steps()
        pbr_solution = first  # as set here (the closure below does not see it narrowed)

        def candidates_in(configs: tuple[TTOConfig, TTOConfig], made: BasisStart, offset: int,
                          suffix: str) -> _Candidates | TTOResult:
            """Both candidates from the start `made`, side by side, scored on the held-out photos; the stopped
            candidate's result when one was stopped."""
            reports = _JointReports(progress, should_stop, offset, total, len(configs))

            def candidate_score(k: int) -> tuple[TTOResult, float]:
                """Candidate k's neural phase on the fitted photos and its score on the held-out ones (nan: stopped)."""
                result = _neural_phase(replace(configs[k], steps=steps), pbr_solution, mesh, envmap, fit_photos,
                                       tonemap, prediction, made.basis, anchor_available, truth,
                                       reports.progress_of(k), reports.stop_check(),
                                       checkpoint(f"select_{choice.names[k]}{suffix}.pt"), made)  # fmt: skip
                if not result.finished:
                    return result, math.nan
                return result, photo_psnr(result.params, result.mesh or mesh, envmap, held_photos, tonemap, config,
                                          config.seed + 1)  # fmt: skip

            # the candidates share no state they write (each has its own problem, planes, decoder copy, checkpoint)
            done = side_by_side([partial(candidate_score, k) for k in range(len(configs))],
                                pbr_solution.params.tensor.device)
            for result, _ in done:
                if not result.finished:
                    return result
            kept = 0 if done[1][1] <= done[0][1] + config.select_margin_db else 1
            return _Candidates(configs, made, done, kept, done[kept][1])

        def scores_of(side: _Candidates, prefix: str = "") -> dict[str, float]:
            """A side's held-out scores and which it kept, as the selection records them: validation_psnr_<name>
            and kept_key for the configured basis, each key after `prefix` for the other."""
            scored = prefix or "validation_"
            return {f"{scored}psnr_{choice.names[0]}": side.runs[0][1], f"{scored}psnr_{choice.names[1]}":
                    side.runs[1][1], f"{prefix}{choice.kept_key}": float(side.kept == 0)}  # fmt: skip

        # the basis is chosen once, here, for both candidates and the TTO that follows
        start = neural_start(config, first, mesh, envmap, fit_photos, held_photos, tonemap, prediction, basis,
                             anchor_available)  # fmt: skip
        own = candidates_in(candidates, start, config.pbr_steps, "")
        if isinstance(own, TTOResult):
            return own
        side, chosen = own, own.kept
        selection = {**scores_of(own), "validation_photos": float(len(held_out))}
        if switch == "select_uniform":  # evidence of light painted into the textured base colour (recorded only;
            # one thread, so it is the same bits whether the candidates ran side by side or not)
            (uniform, _), (textured, _) = own.runs
            with torch_threads(1):
                selection.update(light_following(lambda q: textured.params.gbuffer(q, None),
                                                 lambda q: uniform.params.gbuffer(q, None), textured.mesh or mesh,
                                                 envmap, first.params.tensor.device, seed=config.seed))
        selection.update(start.record)
        # the other sides, in order: the other basis from the same PBR solution (select_basis), then each basis from
        # the LMRM's start (select_lmrm_start); each is taken where its kept candidate beats the side taken so far
        # (config of the side, its basis, record prefix, checkpoint suffix)
        others: list[tuple[TTOConfig, NeuralBasis, str, str]] = []
        in_other = replace(in_select_basis(config), select_anchor=False, select_uniform=False, select_lmrm_start=False)
        other_basis = load_basis(str(first.params.tensor.device), config.select_basis) if config.select_basis else None
        if other_basis is not None:
            others.append((in_other, other_basis, "select_basis_", "_other"))
        if config.select_lmrm_start:
            others.append((plain.lmrm_started(), basis, "select_lmrm_", "_lmrm"))
            if other_basis is not None:
                others.append((in_other.lmrm_started(), other_basis, "select_basis_lmrm_", "_other_lmrm"))
        for k, (side_config, side_basis, prefix, suffix) in enumerate(others, start=1):
            side_start = neural_start(side_config, first, mesh, envmap, fit_photos, held_photos, tonemap, prediction,
                                      side_basis, anchor_available)  # fmt: skip
            made = candidates_in(choice.candidates(side_config), side_start, config.pbr_steps + 2 * k * steps, suffix)
            if isinstance(made, TTOResult):
                return made
            taken = made.score > side.score + config.select_margin_db
            selection.update({**scores_of(made, prefix), f"{prefix}taken": float(taken),
                              **{f"{prefix}{key}": v for key, v in side_start.record.items()}})
            if taken:
                side, chosen = made, made.kept
        runs, start = side.runs, side.start
        candidates = side.configs
    final_config, final_basis = candidates[chosen], basis
    if start is not None:
        final_config = replace(final_config, alternative_basis="",
                               basis=start.basis.basis_id if start.switched else final_config.basis)
        final_basis = start.basis
    if first is not None and start is not None and config.select_reuse_start:  # the neural phase, from the start
        resume = runs[chosen][0] if config.select_continue else None
        if resume is not None:  # the chosen candidate's remaining steps
            final_config = replace(final_config, steps=config.continue_steps(),
                                   lr=final_config.lr * config.select_continue_lr)
        fitted = (first if resume is None else resume).exposure
        if fitted is not None:  # the held-out photos' exposures start at 1 (the fitted ones' geometric mean)
            scales = [1.0] * photos.count
            for k, f in enumerate(fit):
                scales[f] = fitted[k]
            first = replace(first, exposure=scales)
        final = _neural_phase(final_config, first, mesh, envmap, photos, tonemap, prediction, final_basis,
                              anchor_available, truth, _offset(progress, total - final_config.steps, total, 2.0),
                              should_stop, checkpoint("checkpoint.pt"), start, resume)  # fmt: skip
    else:
        final = solve(final_config, mesh, envmap, photos, tonemap, prediction, final_basis, anchor_available, truth,
                      _offset(progress, total - config.total_steps(), total, 2.0), should_stop,
                      checkpoint_dir)  # fmt: skip
    final.selection = selection
    final.basis = final_basis if final_basis.basis_id != basis.basis_id else final.basis
    if first is not None and start is not None and config.select_reuse_start:
        final.pbr_solution = first.params  # else the plain `solve` above set its own
    return final
