"""PBR material: Lambert diffuse + one GGX lobe with the Disney / UE4 metallic-roughness mapping.

f = (1 - metallic) base_color / pi + D G F / (4 cos_i cos_o), with alpha = roughness^2 and
F = Schlick(F0, dot(wo, h)) (UE4's form), F0 = lerp(dielectric_f0, base_color, metallic). This is the material of the
NVDiffRecMC++ baseline and of the LMRM PBR head. (dielectric_f0 = 0 gives a pure Lambertian surface for
metallic = 0; metallic = 1 with white base colour gives F = 1, a white GGX conductor.)
"""

from __future__ import annotations

import torch

from neumatex_core.materials.base import Material, cosine_pdf, cosine_sample, luminance
from neumatex_core.materials.microfacet import (
    ALPHA_MIN,
    ggx_eval,
    ggx_pdf_visible,
    ggx_sample_visible,
    schlick_fresnel,
)

DIELECTRIC_F0 = 0.04


class PBRMaterial(Material):
    """Lambert + GGX at N points.

    base_color: [N, 3] linear RGB in [0, 1]; roughness: [N] in [0, 1]; metallic: [N] in [0, 1].
    """

    def __init__(
        self,
        base_color: torch.Tensor,
        roughness: torch.Tensor,
        metallic: torch.Tensor,
        dielectric_f0: float = DIELECTRIC_F0,
    ) -> None:
        self.base_color = base_color
        self.roughness = roughness
        self.metallic = metallic
        self.dielectric_f0 = dielectric_f0

    @property
    def alpha(self) -> torch.Tensor:
        return (self.roughness * self.roughness).clamp_min(ALPHA_MIN)

    @property
    def f0(self) -> torch.Tensor:
        m = self.metallic.unsqueeze(-1)
        return self.dielectric_f0 * (1 - m) + self.base_color * m

    @property
    def diffuse_albedo(self) -> torch.Tensor:
        return self.base_color * (1 - self.metallic).unsqueeze(-1)

    def eval(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        spec, cos_oh = ggx_eval(wi, wo, self.alpha)
        fresnel = schlick_fresnel(self.f0, cos_oh)
        above = ((wi[:, 2] > 0) & (wo[:, 2] > 0)).unsqueeze(-1)
        diffuse = self.diffuse_albedo / torch.pi
        return torch.where(above, diffuse + fresnel * spec.unsqueeze(-1), torch.zeros_like(diffuse))

    def lambert(self, wo: torch.Tensor) -> torch.Tensor:
        above = (wo[:, 2] > 0).unsqueeze(-1)
        return torch.where(above, self.diffuse_albedo, torch.zeros_like(self.diffuse_albedo))

    def eval_glossy(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        spec, cos_oh = ggx_eval(wi, wo, self.alpha)
        fresnel = schlick_fresnel(self.f0, cos_oh)
        above = ((wi[:, 2] > 0) & (wo[:, 2] > 0)).unsqueeze(-1)
        return torch.where(above, fresnel * spec.unsqueeze(-1), torch.zeros_like(fresnel))

    def _spec_probability(self, wo: torch.Tensor) -> torch.Tensor:
        """[N] probability of sampling the GGX lobe: its Fresnel-weighted share of the albedo."""
        with torch.no_grad():
            spec = luminance(schlick_fresnel(self.f0, wo[:, 2].clamp(0.0, 1.0)))
            diff = luminance(self.diffuse_albedo)
            total = spec + diff
            p = torch.where(total > 0, spec / total.clamp_min(1e-12), torch.full_like(total, 0.5))
            # Keep both lobes reachable when both exist, so MIS never misses a lobe.
            both = (spec > 0) & (diff > 0)
            return torch.where(both, p.clamp(0.1, 0.9), p)

    def sample(self, wo: torch.Tensor, u_lobe: torch.Tensor, u_dir: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            alpha = self.alpha.detach()
            p_spec = self._spec_probability(wo)
            spec_dir = ggx_sample_visible(wo, alpha, u_dir)
            diff_dir = cosine_sample(u_dir)
            wi = torch.where((u_lobe < p_spec).unsqueeze(-1), spec_dir, diff_dir)
            return wi, self.pdf(wi, wo)

    def pdf(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            p_spec = self._spec_probability(wo)
            pdf = p_spec * ggx_pdf_visible(wi, wo, self.alpha.detach()) + (1 - p_spec) * cosine_pdf(wi)
            return torch.where((wi[:, 2] > 0) & (wo[:, 2] > 0), pdf, torch.zeros_like(pdf))

    def albedo(self, wo: torch.Tensor) -> torch.Tensor:
        # Karis' analytic fit of the split-sum GGX directional albedo (Unreal Engine 4, 2013).
        r = self.roughness.unsqueeze(-1)
        n_dot_v = wo[:, 2].clamp(0.0, 1.0).unsqueeze(-1)
        c0 = torch.tensor([-1.0, -0.0275, -0.572, 0.022], device=wo.device)
        c1 = torch.tensor([1.0, 0.0425, 1.04, -0.04], device=wo.device)
        rr = r * c0 + c1
        a004 = torch.minimum(rr[:, 0:1] ** 2, torch.exp2(-9.28 * n_dot_v)) * rr[:, 0:1] + rr[:, 1:2]
        ab = (
            a004
            * torch.cat(
                [
                    torch.tensor([-1.04], device=wo.device).expand_as(a004),
                    torch.tensor([1.04], device=wo.device).expand_as(a004),
                ],
                dim=-1,
            )
            + rr[:, 2:4]
        )
        spec = self.f0 * ab[:, 0:1] + (50.0 * self.f0[:, 1:2]).clamp(0.0, 1.0) * ab[:, 1:2]  # as schlick_fresnel
        return self.diffuse_albedo + spec

    def select(self, index: torch.Tensor) -> PBRMaterial:
        return PBRMaterial(self.base_color[index], self.roughness[index], self.metallic[index], self.dielectric_f0)
