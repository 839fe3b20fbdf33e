"""Material fields: what material a surface point has.

A MaterialField maps surface interactions to a Material holding one row of parameters per point. The
path tracer asks the field at every hit; fields backed by learnable tensors (a uniform material, a triplane,
UV textures) carry the gradients of inverse rendering.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import torch

from neumatex_core.geometry.surface import SurfaceInteraction
from neumatex_core.materials.base import Material
from neumatex_core.materials.layered import LayeredMaterial
from neumatex_core.materials.pbr import DIELECTRIC_F0, PBRMaterial


class MaterialField(ABC):
    """Surface points -> Material."""

    @abstractmethod
    def at(self, si: SurfaceInteraction) -> Material: ...


class UniformPBR(MaterialField):
    """One PBR material everywhere. base_color [3], roughness [], metallic [] (tensors may require grad)."""

    def __init__(self, base_color: torch.Tensor | tuple[float, float, float], roughness: torch.Tensor | float,
                 metallic: torch.Tensor | float, dielectric_f0: float = DIELECTRIC_F0) -> None:
        self.base_color = torch.as_tensor(base_color, dtype=torch.float32)
        self.roughness = torch.as_tensor(roughness, dtype=torch.float32)
        self.metallic = torch.as_tensor(metallic, dtype=torch.float32)
        self.dielectric_f0 = dielectric_f0

    def at(self, si: SurfaceInteraction) -> PBRMaterial:
        n = si.position.shape[0]
        device = si.position.device
        return PBRMaterial(
            self.base_color.to(device).expand(n, 3),
            self.roughness.to(device).expand(n),
            self.metallic.to(device).expand(n),
            self.dielectric_f0,
        )


class UniformLayered(MaterialField):
    """One analytic layered material everywhere: params [22] normalised (`PARAMETER_NAMES`), base_color [3]."""

    def __init__(self, params: torch.Tensor, base_color: torch.Tensor | tuple[float, float, float]) -> None:
        self.params = torch.as_tensor(params, dtype=torch.float32)
        self.base_color = torch.as_tensor(base_color, dtype=torch.float32)

    def at(self, si: SurfaceInteraction) -> LayeredMaterial:
        n = si.position.shape[0]
        device = si.position.device
        return LayeredMaterial(self.params.to(device).expand(n, -1), self.base_color.to(device).expand(n, 3))
