"""LMRM training losses (docs/architecture.md section 5): L = w_mat L_mat + w_unc beta-NLL + w_pbr L_pbr
(+ w_family L_family).

- L_mat: mean squared error of the decoded material against the reference, in the metrics' units:
  0.5 (MSE(rho_d) + MSE((l + 1) / 2)), so each half is what PSNR_BaseColor / PSNR_Latents measure.
- beta-NLL (Seitzer et al. 2022), per channel, on the raw G-buffer (rho_d, l) that TTO regularises with:
  stopgrad(sigma^2)^beta * (log sigma^2 + (y - stopgrad(mu))^2 / sigma^2) / 2. The mean is detached, so the
  uncertainty head never pulls the material prediction; beta = 0.5 keeps the weight of hard points from vanishing.
- L_pbr: MSE of the PBR head (base colour, roughness, metallic) against the synthetic PBR fit.
- L_family: cross-entropy of the family head's logits against each point's material family (models with
  `LMRMConfig.family_head`).

Objects weigh alike by default (each object's L_mat is its MSE). `object_weights` instead weights each object's two
MSEs by their inverse, which follows the metric, PSNR averaged over objects (docs/lmrm.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from neumatex_core.lmrm.model import Heads

LOG_VAR_RANGE = (-16.0, 8.0)  # log-variances are clamped to this range inside the NLL (numerical safety)
MSE_FLOOR = 1e-4  # object_weights: an MSE below this (40 dB) weighs as this, so a near-perfect object cannot take over


def beta_nll(mean: torch.Tensor, log_var: torch.Tensor, target: torch.Tensor, beta: float = 0.5) -> torch.Tensor:
    """Per-channel beta-NLL [C] of predictions mean, log_var [N, C] against target [N, C] (mean over N).
    No gradient reaches `mean` (stop-gradient inside); `log_var` gets the beta-weighted NLL gradient."""
    lv = log_var.clamp(*LOG_VAR_RANGE)
    err2 = (target - mean.detach()) ** 2
    nll = 0.5 * (lv + err2 * torch.exp(-lv))
    weight = torch.exp(beta * lv).detach()
    return (weight * nll).mean(0)


def family_accuracy(logits: torch.Tensor, family: torch.Tensor) -> torch.Tensor:
    """Share (scalar) of the N points whose most likely family in logits [N, len(FAMILIES)] is theirs, family [N]."""
    return (logits.argmax(-1) == family).float().mean()


def material_mse(heads: Heads, targets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(MSE(rho_d), MSE((l + 1) / 2)), scalars, of heads at N points against targets [N, 14]: what PSNR_BaseColor and
    PSNR_Latents measure."""
    return ((heads.rho_d - targets[:, :3]) ** 2).mean(), (((heads.latent - targets[:, 3:9]) / 2) ** 2).mean()


def object_weights(mse: torch.Tensor, floor: float = MSE_FLOOR) -> torch.Tensor:
    """Weights [B, K] of B objects' MSEs [B, K] (K terms each): 1 / max(MSE, floor), normalised to mean 1 over the
    objects, no gradient. Sum_b w_b MSE_b then has the gradient of sum_b log MSE_b up to a factor that is the same for
    every object of the batch: training follows mean PSNR over objects (the metric), where the plain mean of the MSEs
    follows the objects with the largest errors."""
    inv = 1.0 / mse.detach().clamp_min(floor)
    return inv / inv.mean(0, keepdim=True)


@dataclass
class LossWeights:
    """Stage weights: stage 1 (PBR pre-training) is (0, 0, 1); stage 2 (neural material) (1, lambda_unc, w_pbr,
    lambda_family)."""

    mat: float
    unc: float
    pbr: float
    family: float = 0.0


def lmrm_loss(heads: Heads, targets: torch.Tensor, w: LossWeights, beta: float = 0.5,
              family: torch.Tensor | None = None, mat_weight: tuple[float, float] = (1.0, 1.0),
              ) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss (scalar) and its parts for heads at N points, targets [N, 14] (rho_d, l, PBR) and the points'
    family [N] (long, index in FAMILIES; needed when the heads have family logits). mat_weight: this object's weights
    of MSE(rho_d) and MSE(latent) in L_mat (`object_weights`). Parts with weight 0 still enter (times 0), so every
    parameter gets a (zero) gradient, as DistributedDataParallel wants."""
    pbr = targets[:, 9:14]
    mse_rho, mse_lat = material_mse(heads, targets)
    l_mat = 0.5 * (mat_weight[0] * mse_rho + mat_weight[1] * mse_lat)
    mean = torch.cat([heads.rho_d, heads.latent], dim=-1)
    nll = beta_nll(mean, heads.log_var, targets[:, :9], beta).mean()
    l_pbr = ((heads.pbr - pbr) ** 2).mean()
    total = w.mat * l_mat + w.unc * nll + w.pbr * l_pbr
    named = [("l_mat", l_mat), ("mse_rho", mse_rho), ("mse_lat", mse_lat), ("nll", nll), ("l_pbr", l_pbr)]
    if heads.family is not None:
        if family is None:
            raise ValueError("the heads have family logits: lmrm_loss needs the points' family")
        l_family = F.cross_entropy(heads.family, family)
        total = total + w.family * l_family
        named += [("l_family", l_family), ("family_accuracy", family_accuracy(heads.family, family))]
    parts = {k: float(v.detach()) for k, v in named}
    return total, parts
