"""What TTO optimises: one learnable tensor and the material field it defines (one class per variant).

- `NeuralTriplane`: the triplane planes [3, C, R, R] read by the frozen material decoder -> NeuralMaterial (ours);
- `NeuralUV`: a texture [R, R, 9] (rho_d in [0, 1], latent in [-1, 1]) on an xatlas unwrap (UV ablation);
- `PBRTriplane`: the triplane read by the LMRM's frozen PBR head -> PBRMaterial (NVDiffRecMC++ baseline);
- `PBRUV`: a texture [R, R, 5] (base colour, roughness, metallic in [0, 1]) on an xatlas unwrap.

Each gives `tensor` (the field's own leaf), `decoder` (the triplane variants' decoder, or None), `field()` (for the
path tracer), `gbuffer(points, uv)` (the values the anchor compares: [N, 9] (rho_d, latent) or [N, 5] PBR),
`project()` (keeps texture values in range) and `texel_variation(origin)` (the smoothness term). With
TTOConfig.train_decoder the triplane variants get a private copy of their decoder whose weights Adam fine-tunes with
the planes (docs/design-notes.md, "TTO fine-tunes the decoder").
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch

from neumatex_core.fields.decoders import MaterialDecoder, PBRDecoder
from neumatex_core.fields.neural_field import TriplaneMaterialField
from neumatex_core.fields.triplane import Triplane, coarse_projection, neighbour_variation
from neumatex_core.fields.uv_textures import PBRTextureField, UVTextureField, sample_uv
from neumatex_core.geometry.surface import SurfaceInteraction
from neumatex_core.materials.field import MaterialField
from neumatex_core.materials.neural_basis import NeuralBasis
from neumatex_core.materials.pbr import PBRMaterial

ROUGHNESS_MIN = 0.02  # PBR textures: roughness is kept above this (a mirror has no usable gradient)


class PBRTriplaneField(MaterialField):
    """Triplane + PBR head: base colour, roughness, metallic at each hit -> PBRMaterial."""

    kind = "pbr_triplane"

    def __init__(self, triplane: Triplane, decoder: PBRDecoder) -> None:
        self.triplane, self.decoder = triplane, decoder

    def values(self, points: torch.Tensor) -> torch.Tensor:
        """[N, 5] (base colour, roughness, metallic) at points [N, 3]."""
        base, rough, metal = self.decoder(self.triplane.features(points))
        return torch.cat([base, rough.unsqueeze(-1), metal.unsqueeze(-1)], dim=-1)

    def at(self, si: SurfaceInteraction) -> PBRMaterial:
        v = self.values(si.position)
        return PBRMaterial(v[:, :3], v[:, 3], v[:, 4])


class Parametrisation(ABC):
    """A learnable tensor and the material field it defines."""

    tensor: torch.Tensor
    decoder: torch.nn.Module | None = None
    channel_dim: int = 1  # the tensor's dimension of a texel's channels (a triplane's planes [3, C, R, R])

    @abstractmethod
    def field(self) -> MaterialField: ...

    def decoder_parameters(self) -> list[torch.Tensor]:
        """The decoder weights TTO fine-tunes ([] when the decoder is frozen or there is none)."""
        if self.decoder is None:
            return []
        return [p for p in self.decoder.parameters() if p.requires_grad]

    def trained_decoder(self) -> torch.nn.Module | None:
        """The decoder TTO fine-tunes: this parametrisation's own copy. None where it is frozen (then it is shared,
        e.g. the LMRM's, read by phases that may run side by side, so it is only read) or there is none."""
        return self.decoder if self.decoder_parameters() else None

    @abstractmethod
    def gbuffer(self, points: torch.Tensor, uv: torch.Tensor | None) -> torch.Tensor: ...

    def texel_variation(self, origin: torch.Tensor) -> torch.Tensor:
        """The smoothness term (TTOConfig.lambda_smooth) of the change from `origin` (a tensor of this one's shape):
        the mean squared difference between neighbouring texels of tensor - origin, a scalar (`neighbour_variation`
        of a triplane's planes [3, C, R, R])."""
        return neighbour_variation(self.tensor - origin)

    def coarsen_gradient(self, factor: int) -> None:
        """Replace the tensor's gradient by its part that moves blocks of about factor x factor texels
        (`coarse_projection` of a triplane's planes [3, C, R, R]; TTOConfig.coarse_factor)."""
        if self.tensor.grad is not None:
            self.tensor.grad = coarse_projection(self.tensor.grad, factor)

    def project(self) -> None:  # noqa: B027 - a no-op by default: triplanes have no range to keep
        """Clamp the tensor into its valid range after an optimiser step (no-op for triplanes)."""


class NeuralTriplane(Parametrisation):
    def __init__(self, triplane: Triplane, decoder: MaterialDecoder, basis: NeuralBasis) -> None:
        self.triplane, self.decoder = triplane, decoder
        self.tensor = triplane.planes
        self._field = TriplaneMaterialField(triplane, decoder, basis)

    def field(self) -> TriplaneMaterialField:
        return self._field

    def gbuffer(self, points: torch.Tensor, uv: torch.Tensor | None) -> torch.Tensor:
        """[N, 9]: rho_d [3] in [0, 1], latent [6] in [-1, 1]."""
        return torch.cat(self._field.gbuffer(points), dim=-1)


class _UVTexture(Parametrisation):
    """A texture [H, W, C] optimised in place (a copy of the start); G-buffers are read at the anchor points' uvs."""

    channel_dim = 2

    def __init__(self, texture: torch.Tensor) -> None:
        self.tensor = texture.detach().clone().requires_grad_(True)

    def gbuffer(self, points: torch.Tensor, uv: torch.Tensor | None) -> torch.Tensor:
        if uv is None:
            raise ValueError("the UV-texture field needs the uvs of the anchor points")
        return sample_uv(self.tensor, uv)

    def texel_variation(self, origin: torch.Tensor) -> torch.Tensor:
        return neighbour_variation((self.tensor - origin).permute(2, 0, 1))  # [H, W, C] -> [C, H, W]

    def coarsen_gradient(self, factor: int) -> None:
        if self.tensor.grad is not None:
            self.tensor.grad = coarse_projection(self.tensor.grad.permute(2, 0, 1), factor).permute(1, 2, 0)


class NeuralUV(_UVTexture):
    def __init__(self, texture: torch.Tensor, basis: NeuralBasis) -> None:
        super().__init__(texture)
        self._field = UVTextureField(self.tensor, basis)

    def field(self) -> UVTextureField:
        return self._field

    def project(self) -> None:
        with torch.no_grad():
            self.tensor[..., :3].clamp_(0.0, 1.0)
            self.tensor[..., 3:].clamp_(-1.0, 1.0)


class PBRTriplane(Parametrisation):
    def __init__(self, triplane: Triplane, decoder: PBRDecoder) -> None:
        self.triplane, self.decoder = triplane, decoder
        self.tensor = triplane.planes
        self._field = PBRTriplaneField(triplane, decoder)

    def field(self) -> PBRTriplaneField:
        return self._field

    def gbuffer(self, points: torch.Tensor, uv: torch.Tensor | None) -> torch.Tensor:
        """[N, 5]: base colour, roughness, metallic."""
        return self._field.values(points)


class PBRUV(_UVTexture):
    def __init__(self, texture: torch.Tensor) -> None:
        super().__init__(texture)
        self._field = PBRTextureField(self.tensor)

    def field(self) -> PBRTextureField:
        return self._field

    def project(self) -> None:
        with torch.no_grad():
            self.tensor.clamp_(0.0, 1.0)
            self.tensor[..., 3].clamp_(min=ROUGHNESS_MIN)
