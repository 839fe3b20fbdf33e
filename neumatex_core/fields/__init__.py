"""Material fields over a mesh's surface: triplane and UV-texture fields, and the small decoders that turn
triplane features into material G-buffers (docs/architecture.md sections 1, 5).

- `Triplane` (triplane.py): learnable planes [3, C, R, R] over [-1, 1]^3 -> features [N, 3C];
- `MaterialDecoder`, `UncertaintyDecoder`, `PBRDecoder` (decoders.py): features -> (rho_d, latent),
  9 log-variances, PBR (base colour, roughness, metallic);
- `TriplaneMaterialField` (neural_field.py): triplane + material decoder + neural basis -> NeuralMaterial;
- `UVTextureField`, `PBRTextureField` (uv_textures.py): per-hit UV lookups of [H, W, 3 + K] / [H, W, 5]
  textures (K the basis's latent size);
- `fit_triplane` (fit.py): distil a known per-point material into a triplane (test objects); `fit_on_points`: the
  Adam loop (random batches of surface points, cosine-decayed rate) of the fits to values known at points.
"""

from neumatex_core.fields.decoders import MaterialDecoder, PBRDecoder, UncertaintyDecoder, module_id
from neumatex_core.fields.neural_field import TriplaneMaterialField
from neumatex_core.fields.triplane import Triplane
from neumatex_core.fields.uv_textures import (
    PBR_CHANNELS,
    PBRTextureField,
    UVTextureField,
    material_channels,
    sample_uv,
)

__all__ = [
    "PBR_CHANNELS",
    "MaterialDecoder",
    "PBRDecoder",
    "PBRTextureField",
    "Triplane",
    "TriplaneMaterialField",
    "UVTextureField",
    "UncertaintyDecoder",
    "material_channels",
    "module_id",
    "sample_uv",
]
