"""Training the neural basis on the analytic layered material (`neumatex train-basis`).

Three stages, each drawing fresh samples every step (the analytic material is cheap, so there is no dataset):

1. `bsdf`: encoder + decoder jointly. Loss: L1 between log(f cos_i + EPS) of the decoder and of the analytic
   f_spec, so the lobe peaks and tails both count (relative error) while values far below what a render can see
   (EPS) do not. Options added for basis v2 (docs/design-notes.md, "basis v2"): `aux_weight` > 0 trains the
   auxiliary network in this stage too, so the latent must also carry what T_neu needs (v1's latent did not: an
   aux network retrained on it stayed at T MAE 0.10 on clear coats, the largest error of coated spheres);
   `chroma_weight` adds the L1 of the log-chromaticity (log f_c minus its channel mean), which pushes the
   specular colour into the latent (v1's latent let a conductor's F0 hue be decoded only to 0.07 MAE: gold came
   out grey); `init` starts from a trained basis instead of random weights. `render_weight` > 0 adds `render_terms`,
   the error in the units a render integrates (docs/design-notes.md item 33): the batch comes in groups of
   `render_group` direction pairs sharing one parameter set and one wo, so each group estimates its directional
   albedo.
2. `aux`: the auxiliary network (T_neu, R_neu) against the analytic T(wo) and R(wo); encoder and decoder frozen.
3. `sampler`: the sampling network, by maximum likelihood of directions distributed like lum(f_neu) cos_i (the
   frozen decoder): wi drawn from the analytic material's sampler with weights lum(f_neu cos_i) / pdf, loss the
   weighted negative log of the mixture pdf (a KL divergence up to a constant).

Samples: parameters from the family prior (families equally likely) or uniform in [0, 1]^22 (`uniform_share`,
1/4 in v1, for coverage of the latent space that optimisation may wander into); wo uniform on the hemisphere; wi
half from the analytic material's importance sampler (the peaks), half uniform (the tails); with `mirror_share` > 0
that share is redrawn in a narrow cone around wo's mirror direction.

Deterministic: step k of a stage draws from a generator seeded by (seed, stage, k), so an interrupted run that is
resumed from its checkpoint ends with the same weights as an uninterrupted one (same device and thread count).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from neumatex_core.config import option
from neumatex_core.materials.base import luminance
from neumatex_core.materials.layered import INDEX, N_PARAMS, LayeredMaterial
from neumatex_core.materials.microfacet import ggx_pdf_visible, ggx_sample_visible
from neumatex_core.materials.neural_basis import LATENT_DIM, BasisArchitecture, NeuralBasis
from neumatex_core.materials.prior import FAMILIES, ROUGHNESS_MIN, sample_parameters

MIRROR_ALPHA = 0.02  # GGX width of `draw_batch`'s mirror-cone directions (the prior's sharpest lobe has 0.01)
EPS = 1e-3  # f cos below this (1/sr) is invisible next to any diffuse base; log-space loss floor
STAGES = ("bsdf", "aux", "sampler")
STAGE_SEED = {"bsdf": 1, "aux": 2, "sampler": 3, "heldout": 4}


@dataclass
class TrainBasisConfig:
    """Training schedule of the neural basis."""

    out: str = option("runs/basis", "folder for checkpoints, the trained weights and their record")
    seed: int = option(0, "random seed (training is deterministic given seed, device and thread count)")
    batch: int = option(8192, "samples (parameter set, wi, wo) per step")
    steps_bsdf: int = option(20000, "steps of encoder + decoder training")
    steps_aux: int = option(4000, "steps of auxiliary-network training")
    steps_sampler: int = option(4000, "steps of sampling-network training")
    lr: float = option(2e-3, "peak Adam learning rate (cosine decay to 1% of it)")
    checkpoint_every: int = option(500, "steps between checkpoints")
    heldout: int = option(10000, "held-out parameter sets for the final metrics")
    version: str = option("v1", "basis version label (part of the basis id)")
    uniform_share: float = option(0.25, "share of parameter sets drawn uniformly instead of from the family prior")
    mixture_weight: float = option(1.0, "the prior's mixture family is drawn this many times as often as each other "
                                   "family (its colour errors are the basis's worst: docs/design-notes.md item 78)")
    aux_weight: float = option(0.0, "weight of the T/R loss in the bsdf stage (0: the aux network trains alone)")
    chroma_weight: float = option(0.0, "weight of the log-chromaticity L1 in the bsdf stage")
    render_weight: float = option(0.0, "weight of the render-unit term (importance-weighted linear error and "
                                  "directional-albedo error, relative to the albedo) in the bsdf stage")
    render_group: int = option(16, "direction pairs per (parameter set, wo) group when render_weight > 0")
    render_base: float = option(0.5, "grey base colour through which T enters the render term (0: f_spec alone)")
    mirror_share: float = option(0.0, "share of training directions drawn in a narrow GGX cone (alpha MIRROR_ALPHA) "
                                 "around wo's mirror direction, where a spurious spike would otherwise go unseen")
    init: str = option("", "start from these basis weights (.safetensors) instead of random ones (a smaller latent "
                       "is widened: `grow_latent`)")
    latent_dim: int = option(LATENT_DIM, "latent size (the paper's 6; other sizes are for experiments: the rest of "
                             "the pipeline is built for 6)")
    aux_width: int = option(64, "width of the auxiliary (T, R) network's three hidden layers; an --init basis of "
                            "another width gets a fresh auxiliary network (docs/design-notes.md item 77)")
    install: bool = option(False, "also copy the trained weights into the package (neumatex_core/materials/data)")
    device: str = option("auto", "torch device: auto, cpu or cuda")


def _generator(seed: int, stage: str, step: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed * 1_000_003 + STAGE_SEED[stage] * 100_000_007 + step)


def draw_parameters(n: int, g: torch.Generator, uniform_share: float = 0.25,
                    mixture_weight: float = 1.0) -> torch.Tensor:
    """[n, 22]: a share `uniform_share` uniform in [0, 1] (roughness floored), the rest from the family prior
    (families equally likely but the mixture, which has `mixture_weight` times the share of each other), shuffled."""
    n_uniform = int(n * uniform_share)
    weights = [mixture_weight if f == "mixture" else 1.0 for f in FAMILIES]
    counts = [math.ceil((n - n_uniform) * w / sum(weights)) for w in weights]
    prior = torch.cat([sample_parameters(f, k, g) for f, k in zip(FAMILIES, counts, strict=True)])[: n - n_uniform]
    uniform = torch.rand(n_uniform, N_PARAMS, generator=g)
    for name in ("coat_roughness", "spec_roughness"):  # the prior's floor: no near-mirror lobes (see prior)
        uniform[:, INDEX[name]] = ROUGHNESS_MIN + (1 - ROUGHNESS_MIN) * uniform[:, INDEX[name]]
    params = torch.cat([prior, uniform])
    return params[torch.randperm(n, generator=g)]


def uniform_hemisphere(n: int, g: torch.Generator) -> torch.Tensor:
    """[n, 3] uniformly distributed directions with z > 0."""
    u = torch.rand(n, 2, generator=g)
    z = u[:, 0].clamp_min(1e-4)
    r = torch.sqrt(1 - z * z)
    phi = 2 * math.pi * u[:, 1]
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


@dataclass
class Batch:
    params: torch.Tensor  # [N, 22]
    wi: torch.Tensor  # [N, 3]
    wo: torch.Tensor  # [N, 3]
    pdf_analytic: torch.Tensor  # [N] the analytic sampler's pdf of wi (mixture with the uniform half)
    f_spec: torch.Tensor  # [N, 3]
    transmission: torch.Tensor  # [N, 3]
    reflected: torch.Tensor  # [N]


def draw_batch(n: int, g: torch.Generator, params: torch.Tensor | None = None, uniform_share: float = 0.25,
               device: torch.device | None = None, group: int = 1, mirror_share: float = 0.0,
               mixture_weight: float = 1.0) -> Batch:
    """Training samples on `device` (default CPU): see the module docstring.

    The random numbers come from `g` on the CPU in a fixed order, so a batch depends on (g, n, group) and not on
    the device; the analytic material is evaluated on `device` (on a GPU that is most of a step's work).
    params: [n // group, 22] to use instead of `draw_parameters` (e.g. one family's, for per-family metrics).
    group: consecutive runs of `group` samples share one parameter set and one wo (n must be a multiple).
    mirror_share: that share of wi is redrawn from a GGX lobe of width MIRROR_ALPHA around wo's mirror direction
    (the pdf includes it); its random numbers come last, so a batch without it is unchanged."""
    if n % group:
        raise ValueError(f"batch {n} is not a multiple of the group size {group}")
    dev = torch.device("cpu") if device is None else device
    sets = n // group
    params = (draw_parameters(sets, g, uniform_share, mixture_weight) if params is None else params).to(dev)
    wo = uniform_hemisphere(sets, g).to(dev)
    if group > 1:
        params, wo = params.repeat_interleave(group, 0), wo.repeat_interleave(group, 0)
    u_lobe, u_dir = torch.rand(n, generator=g).to(dev), torch.rand(n, 2, generator=g).to(dev)
    wi_uni = uniform_hemisphere(n, g).to(dev)
    use_imp = (torch.rand(n, generator=g) < 0.5).to(dev)
    material = LayeredMaterial(params, torch.zeros(n, 3, device=dev))  # no base: sampling follows f_spec's lobes
    wi_imp, _ = material.sample(wo, u_lobe, u_dir)
    wi = torch.where(use_imp.unsqueeze(-1), wi_imp, wi_uni)
    ok = wi[:, 2] > 1e-4
    wi = torch.where(ok.unsqueeze(-1), wi, wi_uni)
    if mirror_share > 0:
        alpha = torch.full((n,), MIRROR_ALPHA, device=dev)
        u_m, use_m = torch.rand(n, 2, generator=g).to(dev), (torch.rand(n, generator=g) < mirror_share).to(dev)
        wi_m = ggx_sample_visible(wo, alpha, u_m)
        wi = torch.where((use_m & (wi_m[:, 2] > 1e-4)).unsqueeze(-1), wi_m, wi)
    pdf = 0.5 * material.pdf(wi, wo) + 0.5 / (2 * math.pi)
    if mirror_share > 0:
        pdf = (1 - mirror_share) * pdf + mirror_share * ggx_pdf_visible(wi, wo, alpha)
    with torch.no_grad():
        f_spec, transmission, reflected = material.components(wi, wo)
    return Batch(params, wi, wo, pdf, f_spec, transmission, reflected)


def log_target(f: torch.Tensor, cos_i: torch.Tensor) -> torch.Tensor:
    return torch.log(f * cos_i.unsqueeze(-1) + EPS)


def bsdf_loss(basis: NeuralBasis, b: Batch, aux_weight: float = 0.0, chroma_weight: float = 0.0,
              latent: torch.Tensor | None = None, render_weight: float = 0.0, group: int = 1,
              render_base: float = 0.5) -> torch.Tensor:
    """Log-L1 of f cos_i (+ aux_weight x `aux_terms`, + chroma_weight x the log-chromaticity L1, + render_weight x
    `render_terms` over groups of `group`), at `latent` [n, latent_dim] (default: basis.encode(b.params))."""
    latent = basis.encode(b.params) if latent is None else latent
    f = torch.exp(basis.log_bsdf(latent, b.wi, b.wo).clamp(max=12.0))
    cos_i = b.wi[:, 2]
    log_f, log_t = log_target(f, cos_i), log_target(b.f_spec, cos_i)
    loss = (log_f - log_t).abs().mean()
    if chroma_weight > 0:
        chroma = (log_f - log_f.mean(-1, keepdim=True)) - (log_t - log_t.mean(-1, keepdim=True))
        loss = loss + chroma_weight * chroma.abs().mean()
    if aux_weight > 0:
        loss = loss + aux_weight * aux_terms(basis, latent, b)
    if render_weight > 0:
        t, _ = basis.transmission_reflectance(latent, b.wo)
        loss = loss + render_weight * render_terms(f, t, b, group, render_base)
    return loss


ALBEDO_FLOOR = 0.05  # the render terms are relative to the group's albedo luminance plus this


def render_terms(f: torch.Tensor, transmission: torch.Tensor, b: Batch, group: int, base: float = 0.5) -> torch.Tensor:
    """The error a render integrates, per group of `group` samples sharing a parameter set and wo (`draw_batch`).

    f: [n, 3] the decoded BSDF (1/sr) at the batch's directions; transmission: [n, 3] the decoded T(wo). With
    w = cos_i / pdf the importance weight of the batch's own wi (half analytic-sampled, half uniform: w is
    bounded), mean_k(f w) is the group's directional albedo of f_spec (linear RGB) and T(wo) rho_d that of the
    base (eq. 1), here under a grey base rho_d = `base` (0: f_spec alone): the light a white sky reflects.
    Returns the mean over groups and channels of (mean_k |f - f_spec| w + |albedo_neu - albedo| + rho_d |T_neu -
    T|) / (lum(albedo) + ALBEDO_FLOOR): the lobe's shape in linear units (where the log-L1 weighs a dim tail like
    the peak), the colour and level of the whole (a hue lost in a lobe or in the coat's T, design note 30),
    relative to the albedo, so that a dark material's error counts as a tonemapped render sees it."""
    w = (b.wi[:, 2] / b.pdf_analytic.clamp_min(1e-8)).unsqueeze(-1)
    d = ((f - b.f_spec) * w).view(-1, group, 3)
    d_base = base * (transmission - b.transmission).view(-1, group, 3).mean(1)  # T(wo): one wo per group
    albedo = (b.f_spec * w).view(-1, group, 3).mean(1) + base * b.transmission.view(-1, group, 3).mean(1)
    scale = (luminance(albedo) + ALBEDO_FLOOR).unsqueeze(-1)
    return ((d.abs().mean(1) + (d.mean(1) + d_base).abs() + d_base.abs()) / scale).mean()


def aux_terms(basis: NeuralBasis, latent: torch.Tensor, b: Batch) -> torch.Tensor:
    """Mean |T_neu - T| + mean |R_neu - R| at the batch's wo."""
    t, r = basis.transmission_reflectance(latent, b.wo)
    return (t - b.transmission).abs().mean() + (r - b.reflected).abs().mean()


def aux_loss(basis: NeuralBasis, b: Batch) -> torch.Tensor:
    with torch.no_grad():
        latent = basis.encode(b.params)
    return aux_terms(basis, latent, b)


def sampler_loss(basis: NeuralBasis, b: Batch) -> torch.Tensor:
    from neumatex_core.materials.base import cosine_pdf

    with torch.no_grad():
        latent = basis.encode(b.params)
        weight = luminance(basis.bsdf(latent, b.wi, b.wo)) * b.wi[:, 2] / b.pdf_analytic.clamp_min(1e-8)
        weight = weight / weight.sum().clamp_min(1e-12)
    probs, alphas = basis.lobes(latent, b.wo)
    pdfs = torch.stack([cosine_pdf(b.wi), ggx_pdf_visible(b.wi, b.wo, alphas[:, 0]),
                        ggx_pdf_visible(b.wi, b.wo, alphas[:, 1])], dim=-1)  # fmt: skip
    q = (probs * pdfs).sum(-1)
    return -(weight * torch.log(q + 1e-6)).sum()


def stage_loss(cfg: TrainBasisConfig, stage: str, basis: NeuralBasis, b: Batch) -> torch.Tensor:
    if stage == "bsdf":
        return bsdf_loss(basis, b, cfg.aux_weight, cfg.chroma_weight, render_weight=cfg.render_weight,
                         group=_group(cfg), render_base=cfg.render_base)
    return aux_loss(basis, b) if stage == "aux" else sampler_loss(basis, b)


def _group(cfg: TrainBasisConfig) -> int:
    return cfg.render_group if cfg.render_weight > 0 else 1


def stage_parameters(basis: NeuralBasis, stage: str, aux_weight: float = 0.0) -> list[torch.nn.Parameter]:
    if stage == "bsdf":
        joint = list(basis.aux.parameters()) if aux_weight > 0 else []
        return [*basis.encoder.parameters(), *basis.decoder.parameters(), *joint]
    if stage == "aux":
        return list(basis.aux.parameters())
    return list(basis.sampler.parameters())


@torch.no_grad()
def heldout_metrics(basis: NeuralBasis, n: int, seed: int, device: torch.device) -> dict[str, float]:
    """Decoder and auxiliary errors on n held-out parameter sets (4 direction pairs each, half importance-sampled).

    bsdf_median_rel_error: median over samples and channels of |f_neu - f| / (f + EPS / cos_i), i.e. relative
    error where f cos_i is visible; bsdf_log_l1: the training loss; t_mae / r_mae: mean absolute errors.
    """
    g = _generator(seed, "heldout", 0)
    rel, log_l1, t_err, r_err = [], [], [], []
    for _ in range(4):
        b = draw_batch(n, g, device=device)
        latent = basis.encode(b.params)
        f = basis.bsdf(latent, b.wi, b.wo)
        cos_i = b.wi[:, 2].unsqueeze(-1)
        rel.append(((f - b.f_spec).abs() / (b.f_spec + EPS / cos_i)).flatten())
        log_l1.append((log_target(f, b.wi[:, 2]) - log_target(b.f_spec, b.wi[:, 2])).abs().flatten())
        t, r = basis.transmission_reflectance(latent, b.wo)
        t_err.append((t - b.transmission).abs().flatten())
        r_err.append((r - b.reflected).abs())
    return {
        "bsdf_median_rel_error": float(torch.cat(rel).median()),
        "bsdf_log_l1": float(torch.cat(log_l1).mean()),
        "t_mae": float(torch.cat(t_err).mean()),
        "r_mae": float(torch.cat(r_err).mean()),
        "heldout_parameter_sets": float(n),
    }


def training_step(cfg: TrainBasisConfig, stage: str, step: int, basis: NeuralBasis, opt: torch.optim.Optimizer,
                  lr: float, device: torch.device) -> torch.Tensor:
    """One optimiser step of `stage` on step `step`'s batch at learning rate `lr`; returns the loss (with grad)."""
    b = draw_batch(cfg.batch, _generator(cfg.seed, stage, step), uniform_share=cfg.uniform_share, device=device,
                   group=_group(cfg) if stage == "bsdf" else 1,
                   mirror_share=cfg.mirror_share if stage == "bsdf" else 0.0, mixture_weight=cfg.mixture_weight)
    loss = stage_loss(cfg, stage, basis, b)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    for group in opt.param_groups:
        group["lr"] = lr
    opt.step()
    return loss


def grow_latent(state: dict[str, torch.Tensor], target: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Basis weights `state` widened to the latent size of `target` (a fresh basis's state dict, same hidden
    widths), so a larger latent starts from a trained basis instead of from scratch (docs/design-notes.md item 31).

    The new latent entries get `target`'s freshly initialised encoder rows and zero input columns in the decoder,
    aux and sampler networks: the widened basis evaluates exactly as `state` does, and training can only add what
    the extra numbers carry. A `state` of the target's size is returned unchanged."""
    encoder_weights = [k for k in state if k.startswith("encoder.") and k.endswith(".weight")]
    enc_out = max(encoder_weights, key=lambda k: int(k.split(".")[1]))  # the output layer
    d_old = state[enc_out].shape[0]
    grown: dict[str, torch.Tensor] = {}
    for key, value in state.items():
        want = target[key]
        if value.shape == want.shape:
            grown[key] = value
        elif key.startswith("encoder."):  # the output layer: one row (or bias entry) per latent number
            w = want.detach().clone()
            w[:d_old] = value
            grown[key] = w
        elif value.dim() == 2 and value.shape[0] == want.shape[0]:  # an input layer: [latent, other features]
            n_new = want.shape[1] - value.shape[1]
            grown[key] = torch.cat([value[:, :d_old], value.new_zeros(value.shape[0], n_new), value[:, d_old:]], 1)
        else:
            raise ValueError(f"{key}: shape {tuple(value.shape)} cannot be widened to {tuple(want.shape)}")
    return grown


def train_basis(
    cfg: TrainBasisConfig, device: torch.device, progress: Callable[[str, int, int, float], None] | None = None
) -> tuple[NeuralBasis, dict[str, object]]:
    """Run (or resume) the three stages; returns the trained basis and its metrics. Writes out/checkpoint.pt."""
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.pt"
    torch.manual_seed(cfg.seed)
    basis = NeuralBasis(architecture(cfg)).to(device)
    if cfg.init:
        from safetensors.torch import load_file

        # same layer widths as the architecture; a smaller latent is widened (design note 31); an auxiliary
        # network of another width starts afresh (design note 77)
        fresh = basis.state_dict()
        state = load_file(cfg.init)
        if state["aux.0.weight"].shape[0] != fresh["aux.0.weight"].shape[0]:
            state = {k: v for k, v in state.items() if not k.startswith("aux.")}
        basis.load_state_dict({**fresh, **grow_latent(state, fresh)})
    history: dict[str, list[float]] = {s: [] for s in STAGES}
    seconds: dict[str, float] = {s: 0.0 for s in STAGES}
    start_stage, start_step, opt_state = 0, 0, None
    if ckpt_path.exists():
        ckpt = torch.load(ckpt_path, map_location=device, weights_only=False)
        if ckpt["config"] != _schedule(cfg):
            raise ValueError(f"{ckpt_path}: checkpoint was made with a different schedule; use another --out")
        basis.load_state_dict(ckpt["model"])
        start_stage, start_step, opt_state = ckpt["stage"], ckpt["step"], ckpt["optimizer"]
        history, seconds = ckpt["history"], ckpt["seconds"]
    steps = {"bsdf": cfg.steps_bsdf, "aux": cfg.steps_aux, "sampler": cfg.steps_sampler}
    for si in range(start_stage, len(STAGES)):
        stage = STAGES[si]
        params = stage_parameters(basis, stage, cfg.aux_weight)
        opt = torch.optim.Adam(params, lr=cfg.lr)
        lr_factor = _cosine_schedule(steps[stage])
        first = 0
        if si == start_stage and opt_state is not None:
            opt.load_state_dict(opt_state)
            first = start_step
        basis.train()
        t0 = time.perf_counter()
        for step in range(first, steps[stage]):
            loss = training_step(cfg, stage, step, basis, opt, cfg.lr * lr_factor(step), device)
            history[stage].append(float(loss.detach()))
            if progress is not None:
                progress(stage, step + 1, steps[stage], history[stage][-1])
            if (step + 1) % cfg.checkpoint_every == 0 or step + 1 == steps[stage]:
                seconds[stage] += time.perf_counter() - t0
                t0 = time.perf_counter()
                done = step + 1 == steps[stage]
                torch.save({"model": basis.state_dict(), "stage": si + 1 if done else si,
                            "step": 0 if done else step + 1, "optimizer": None if done else opt.state_dict(),
                            "history": history, "seconds": seconds, "config": _schedule(cfg)}, ckpt_path)
        opt_state = None
    basis.eval()
    metrics: dict[str, object] = dict(heldout_metrics(basis, cfg.heldout, cfg.seed, device))
    metrics["train_seconds"] = seconds
    metrics["final_loss"] = {s: (sum(h[-100:]) / max(len(h[-100:]), 1)) for s, h in history.items()}
    metrics["config"] = _schedule(cfg)
    torch.save(history, out / "history.pt")
    return basis, metrics


def architecture(cfg: TrainBasisConfig) -> BasisArchitecture:
    """The network sizes `cfg` asks for."""
    return BasisArchitecture(latent_dim=cfg.latent_dim, aux_hidden=[cfg.aux_width] * 3)


def _cosine_schedule(total: int) -> Callable[[int], float]:
    """Learning-rate factor: cosine decay from 1 to 0.01 over `total` steps."""
    return lambda k: 0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * min(k / max(total, 1), 1)))


def _schedule(cfg: TrainBasisConfig) -> dict[str, object]:
    """The parts of the config that determine the weights (a checkpoint must match them to be resumed)."""
    d = asdict(cfg)
    keys = ["seed", "batch", "steps_bsdf", "steps_aux", "steps_sampler", "lr"]
    v1 = TrainBasisConfig()
    # options added after v1 enter the schedule only when set, so v1's record (and checkpoints) keep their meaning
    later = ("uniform_share", "aux_weight", "chroma_weight", "init", "latent_dim", "render_weight", "render_group",
             "render_base", "mirror_share", "aux_width", "mixture_weight")
    keys += [k for k in later if d[k] != getattr(v1, k)]
    return {k: d[k] for k in keys}
