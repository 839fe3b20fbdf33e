"""The Material interface shared by the PBR, analytic layered and neural materials.

A Material instance holds the parameters of N shading points (one row each) and answers four queries in
the local shading frame (+Z is the shading normal). Directions are unit vectors pointing away from the
surface: `wi` towards the light, `wo` towards the viewer.

- eval(wi, wo) -> [N, 3] BSDF value f (1/sr, linear RGB), *without* the cosine factor; zero when either
  direction is below the surface. Differentiable in the material parameters.
- sample(wo, u_lobe, u_dir) -> (wi [N, 3], pdf [N]): detached importance sampling (no gradient).
- pdf(wi, wo) -> [N]: solid-angle pdf of `sample`, exact, detached (MIS weights need it).
- albedo(wo) -> [N, 3]: directional albedo, the integral of f cos over the hemisphere (approximate where
  a closed form does not exist; used for Russian roulette, previews and G-buffers).
- select(index) -> Material: the same material restricted to some points (a bool mask or an index tensor).

Optional split, used by the cached light transport (`render/transport_cache.py`): f = lambert(wo) / pi + glossy(wi,
wo), where `lambert(wo)` [N, 3] is the albedo of the Lambertian part (it may depend on the viewer side, as T(wo)
rho_d does) and `eval_glossy` the rest. The defaults (no Lambertian part, glossy = eval) are always correct; a
material that overrides them lets a cache integrate its diffuse part once per pixel instead of once per sample.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import torch


class Material(ABC):
    """Per-point BSDF parameters for N shading points; see the module docstring for the contract."""

    @abstractmethod
    def eval(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor: ...

    @abstractmethod
    def sample(
        self, wo: torch.Tensor, u_lobe: torch.Tensor, u_dir: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]: ...

    @abstractmethod
    def pdf(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor: ...

    @abstractmethod
    def albedo(self, wo: torch.Tensor) -> torch.Tensor: ...

    @abstractmethod
    def select(self, index: torch.Tensor) -> Material: ...

    def lambert(self, wo: torch.Tensor) -> torch.Tensor:
        """[N, 3] albedo of the Lambertian part of f at viewer directions wo [N, 3] (see the module docstring)."""
        return torch.zeros(wo.shape[0], 3, device=wo.device)

    def eval_glossy(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """[N, 3] f minus its Lambertian part lambert(wo) / pi (1/sr, no cosine; zero below the surface)."""
        return self.eval(wi, wo)


def cosine_sample(u: torch.Tensor) -> torch.Tensor:
    """Cosine-weighted hemisphere directions [N, 3] from u [N, 2] (Malley's method, concentric disk)."""
    a = 2 * u - 1
    zero = (a[:, 0] == 0) & (a[:, 1] == 0)
    use_x = a[:, 0].abs() > a[:, 1].abs()
    r = torch.where(use_x, a[:, 0], a[:, 1])
    safe_ax = torch.where(a[:, 0] == 0, torch.ones_like(a[:, 0]), a[:, 0])
    safe_ay = torch.where(a[:, 1] == 0, torch.ones_like(a[:, 1]), a[:, 1])
    phi = torch.where(use_x, (math.pi / 4) * (a[:, 1] / safe_ax), (math.pi / 2) - (math.pi / 4) * (a[:, 0] / safe_ay))
    r = torch.where(zero, torch.zeros_like(r), r)
    x, y = r * torch.cos(phi), r * torch.sin(phi)
    z = torch.sqrt((1 - x * x - y * y).clamp_min(0.0))
    return torch.stack([x, y, z], dim=-1)


def cosine_pdf(wi: torch.Tensor) -> torch.Tensor:
    """Solid-angle pdf [N] of `cosine_sample` for local directions [N, 3]."""
    return wi[:, 2].clamp_min(0.0) / math.pi


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    """[N, 3] linear RGB -> [N] Rec. 709 luminance."""
    return rgb[..., 0] * 0.2126 + rgb[..., 1] * 0.7152 + rgb[..., 2] * 0.0722
