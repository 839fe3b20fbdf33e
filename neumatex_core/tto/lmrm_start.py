"""The neural start blended with the LMRM's prediction by their precisions (docs/design-notes.md, item 96).

    rho, latent, record = lmrm_blend(prediction, basis, points, rho, latent, pbr_var)

The extraction's neural phase starts from the PBR solution expressed in the basis, so what the LMRM knows about the
base colour and the layers under it never reaches the result (item 95: a better LMRM does not move the default's
BaseColor or Latents, while a TTO that starts from it does). Here each channel of the start is the precision-weighted
mean of two estimates, the product of two Gaussians: the PBR start, whose error variance `pbr_var` is one number
(G-buffer units squared), and the LMRM's prediction, whose variance it predicts (exp(log_var), calibrated:
docs/lmrm.md):

    start = (pbr / pbr_var + lmrm / var) / (1 / pbr_var + 1 / var) = pbr + share * (lmrm - pbr),
    share = pbr_var / (pbr_var + var)

Where the LMRM is sure the start takes its value, where it is not the PBR start's. The LMRM predicts the default
basis's latents, so in another basis (another latent space) only the base colour is blended. `lmrm_share` also
weighs the anchor to the start (TTOConfig.lmrm_start_anchor), which then holds only what the LMRM put in.
"""

from __future__ import annotations

import torch

from neumatex_core.lmrm.inference import LMRMPrediction
from neumatex_core.materials.neural_basis import NeuralBasis, load_basis
from neumatex_core.tto.loss import LOG_VAR_MIN


def lmrm_share(prediction: LMRMPrediction, basis: NeuralBasis, points: torch.Tensor, pbr_var: float,
               latent_dim: int) -> torch.Tensor:
    """The LMRM's weight [P, 3 + latent_dim] in the blended start at points [P, 3] (module docstring): pbr_var /
    (pbr_var + its predicted variance) per channel, on the device of `points`; 0 for the latent unless `basis` is the
    default basis, whose latents the LMRM predicts."""
    with torch.no_grad():
        features = prediction.triplane.features(points.to(prediction.triplane.planes.device))
        return _share(prediction.uncertainty_decoder(features), basis, pbr_var, latent_dim).to(points.device)


def _share(log_var: torch.Tensor, basis: NeuralBasis, pbr_var: float, latent_dim: int) -> torch.Tensor:
    """`lmrm_share` from the LMRM's predicted log-variances [P, 3 + its latent size]."""
    var = torch.exp(log_var.clamp_min(LOG_VAR_MIN))
    share = torch.zeros(var.shape[0], 3 + latent_dim, device=var.device)
    share[:, :3] = pbr_var / (pbr_var + var[:, :3])
    if basis.basis_id == load_basis(str(var.device)).basis_id and latent_dim == var.shape[1] - 3:
        share[:, 3:] = pbr_var / (pbr_var + var[:, 3:])
    return share


def lmrm_blend(prediction: LMRMPrediction, basis: NeuralBasis, points: torch.Tensor, rho: torch.Tensor,
               latent: torch.Tensor, pbr_var: float) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
    """The start's (rho_d [P, 3], latent [P, D]) at points [P, 3] blended with the LMRM's prediction there (module
    docstring; the weights `lmrm_share`). The record: the mean weight of the LMRM on the base colour
    (lmrm_start_weight_rho) and on the latent (lmrm_start_weight_latent; 0 where it is not blended)."""
    with torch.no_grad():  # one pass of the LMRM: its values and their variances
        lmrm_rho, lmrm_latent, log_var = prediction.gbuffers(points.to(prediction.triplane.planes.device))
        share = _share(log_var, basis, pbr_var, latent.shape[1]).to(rho.device)
        rho = rho + share[:, :3] * (lmrm_rho.to(rho.device) - rho)
        if latent.shape[1] == lmrm_latent.shape[1]:  # else the share is 0 (another basis's latent space)
            latent = latent + share[:, 3:] * (lmrm_latent.to(latent.device) - latent)
    record = {"lmrm_start_weight_rho": float(share[:, :3].mean()),
              "lmrm_start_weight_latent": float(share[:, 3:].mean())}
    return rho, latent, record
