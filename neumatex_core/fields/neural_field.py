"""The triplane neural material field: surface point -> triplane features -> M_mat -> NeuralMaterial.

    field = TriplaneMaterialField(triplane, MaterialDecoder(triplane.feature_dim), load_basis())
    rho_d, latent = field.gbuffer(points)      # [N, 3] in [0, 1], [N, 6] in [-1, 1]
    material = field.at(si)                    # NeuralMaterial(basis, rho_d, latent) at the hits

The basis is frozen; gradients of a render reach the triplane planes (and the decoder, if it requires grad).
"""

from __future__ import annotations

import torch

from neumatex_core.fields.decoders import MaterialDecoder
from neumatex_core.fields.triplane import Triplane
from neumatex_core.geometry.surface import SurfaceInteraction
from neumatex_core.materials.field import MaterialField
from neumatex_core.materials.neural_basis import NeuralBasis, NeuralMaterial


class TriplaneMaterialField(MaterialField):
    """Triplane + material decoder + neural basis. Points are world positions in [-1, 1]^3."""

    kind = "triplane"

    def __init__(self, triplane: Triplane, decoder: MaterialDecoder, basis: NeuralBasis) -> None:
        if decoder.in_features != triplane.feature_dim:
            raise ValueError(f"decoder takes {decoder.in_features} features, the triplane gives {triplane.feature_dim}")
        self.triplane, self.decoder, self.basis = triplane, decoder, basis

    def gbuffer(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(rho_d [N, 3], latent [N, 6]) at world points [N, 3]."""
        return self.decoder(self.triplane.features(points))

    def at(self, si: SurfaceInteraction) -> NeuralMaterial:
        rho_d, latent = self.gbuffer(si.position)
        return NeuralMaterial(self.basis, rho_d, latent)
