"""UV-texture material fields: a texture read bilinearly at each hit's texture coordinates.

Texture convention (the OBJ / USD one): uv in [0, 1]^2 with v up; texel row 0 is the top of the image (v = 1),
so texel (i, j) has its centre at u = (j + 0.5) / W, v = 1 - (i + 0.5) / H. Lookups outside [0, 1] read the
border texels. The mesh must carry per-vertex uvs (`Mesh.uvs`, e.g. from `assets.uv_unwrap`); the renderer
interpolates them into `SurfaceInteraction.uv`.

- `UVTextureField`: texture [H, W, 3 + K] = (rho_d [3] in [0, 1], latent [K] in [-1, 1]) -> NeuralMaterial, K the
  basis's latent size (`material_channels`: 9 in the paper's basis);
- `PBRTextureField`: texture [H, W, 5] = (base colour [3], roughness, metallic) -> PBRMaterial.

Gradients flow to the texture tensors (TTO's UV-texture ablation optimises them).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from neumatex_core.geometry.surface import SurfaceInteraction
from neumatex_core.materials.field import MaterialField
from neumatex_core.materials.neural_basis import NeuralBasis, NeuralMaterial
from neumatex_core.materials.pbr import DIELECTRIC_F0, PBRMaterial

PBR_CHANNELS = 5  # base colour (3) + roughness + metallic


def material_channels(basis: NeuralBasis) -> int:
    """Channels of a neural material texture in `basis`: rho_d (3) + its latent size."""
    return 3 + basis.arch.latent_dim


def sample_uv(texture: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of texture [H, W, C] at uv [N, 2] (convention in the module docstring) -> [N, C]."""
    grid = torch.stack([uv[:, 0] * 2 - 1, 1 - uv[:, 1] * 2], dim=-1).to(texture.dtype)
    img = texture.permute(2, 0, 1).unsqueeze(0)  # [1, C, H, W]
    out = F.grid_sample(img, grid.view(1, 1, -1, 2), mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0, :].t()


def _uv(si: SurfaceInteraction) -> torch.Tensor:
    if si.uv is None:
        raise ValueError("a UV-texture material needs a mesh with texture coordinates (Mesh.uvs)")
    return si.uv


def _check(texture: torch.Tensor, channels: int, what: str) -> torch.Tensor:
    if texture.dim() != 3 or texture.shape[-1] != channels:
        raise ValueError(f"{what} texture must be [H, W, {channels}], got {tuple(texture.shape)}")
    return texture


class UVTextureField(MaterialField):
    """Neural material from a [H, W, 3 + K] texture (rho_d, latent) and the frozen basis (latent size K)."""

    kind = "uv_textures"

    def __init__(self, texture: torch.Tensor, basis: NeuralBasis) -> None:
        self.texture = _check(texture, material_channels(basis), "material")
        self.basis = basis

    def gbuffer_uv(self, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(rho_d [N, 3], latent [N, K]) at uv [N, 2]."""
        values = sample_uv(self.texture, uv)
        return values[:, :3], values[:, 3:]

    def at(self, si: SurfaceInteraction) -> NeuralMaterial:
        rho_d, latent = self.gbuffer_uv(_uv(si))
        return NeuralMaterial(self.basis, rho_d, latent)


class PBRTextureField(MaterialField):
    """PBR material (Lambert + GGX, UE4 mapping) from a [H, W, 5] texture (base colour, roughness, metallic)."""

    kind = "pbr_textures"

    def __init__(self, texture: torch.Tensor, dielectric_f0: float = DIELECTRIC_F0) -> None:
        self.texture = _check(texture, PBR_CHANNELS, "PBR")
        self.dielectric_f0 = dielectric_f0

    def at(self, si: SurfaceInteraction) -> PBRMaterial:
        values = sample_uv(self.texture, _uv(si))
        return PBRMaterial(values[:, :3], values[:, 3], values[:, 4], self.dielectric_f0)
