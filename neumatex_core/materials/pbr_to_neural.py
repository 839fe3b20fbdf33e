"""A PBR material expressed in the neural basis: PBR -> analytic layered parameters -> the basis encoder -> latent.

The layered material contains PBR (docs/design-notes.md, "neural from PBR"): its specular GGX layer with roughness
r and RGB F0 is UE4's GGX lobe, and with dust, fuzz, coat, haze and scatter switched off only that layer lies over
the Lambertian base. So a PBR point (base colour b, roughness r, metallic m) maps to

    spec_roughness = r,  spec_f0 = 0.04 (1 - m) + b m,  every other layer weight 0,
    rho_d = b (1 - m) / T(wo_ref)

where T is the basis's transmission albedo under that specular layer (albedo scaling darkens the base by it,
PBR's Lambert term does not), taken at a 45-degree viewer direction and clamped so rho_d stays in [0, 1]. The
latent is the basis encoder of those 22 parameters. This is how the neural TTO starts from a PBR fit.
"""

from __future__ import annotations

import math

import torch

from neumatex_core.materials.layered import INDEX, N_PARAMS
from neumatex_core.materials.neural_basis import NeuralBasis
from neumatex_core.materials.pbr import DIELECTRIC_F0

# parameters of switched-off layers: mid-range values, the rest zero. Not the prior's neutral values
# (materials/prior.py `_neutral`, which the encoder was trained on and the synthetic truth is written with):
# at those the basis renders the start closer to PBR (v1 holds a metal's PBR solution, -0.03 dB against -9.98 on
# benchmark object 1), but the default's TTO ends no better from it (10 objects: PathTrace clean -0.21 +- 0.16,
# Latents -1.30 +- 0.73 dB; docs/design-notes.md item 83)
NEUTRAL = {"scatter_anisotropy": 0.5, "coat_ior": 0.5}


def pbr_layered_params(base_color: torch.Tensor, roughness: torch.Tensor, metallic: torch.Tensor) -> torch.Tensor:
    """[N, 22] normalised layered parameters of PBR points: base_color [N, 3] in [0, 1], roughness, metallic [N]."""
    n = base_color.shape[0]
    params = torch.zeros(n, N_PARAMS, device=base_color.device, dtype=base_color.dtype)
    for name, value in NEUTRAL.items():
        params[:, INDEX[name]] = value
    m = metallic.unsqueeze(-1)
    f0 = DIELECTRIC_F0 * (1 - m) + base_color * m
    params[:, INDEX["spec_roughness"]] = roughness
    params[:, INDEX["spec_f0_r"]:INDEX["spec_f0_b"] + 1] = f0
    return params.clamp(0.0, 1.0)


@torch.no_grad()
def pbr_to_neural(basis: NeuralBasis, base_color: torch.Tensor, roughness: torch.Tensor,
                  metallic: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(rho_d [N, 3] in [0, 1], latent [N, 6] in [-1, 1]) of PBR points (see the module docstring)."""
    latent = basis.encode(pbr_layered_params(base_color, roughness, metallic))
    wo = torch.tensor([math.sqrt(0.5), 0.0, math.sqrt(0.5)], device=latent.device).expand(latent.shape[0], 3)
    transmission, _ = basis.transmission_reflectance(latent, wo)
    diffuse = base_color * (1 - metallic).unsqueeze(-1)
    rho_d = (diffuse / transmission.clamp_min(0.05)).clamp(0.0, 1.0)
    return rho_d, latent
