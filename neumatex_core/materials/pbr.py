"""PBR material: Lambert diffuse + one GGX lobe with the Disney / UE4 metallic-roughness mapping.

f = (1 - metallic) base_color / pi + D G F / (4 cos_i cos_o), with alpha = roughness^2 and
F = Schlick(F0, dot(wo, h)) (UE4's form), F0 = lerp(dielectric_f0, base_color, metallic). This is the material of the
NVDiffRecMC++ baseline and of the LMRM PBR head. (dielectric_f0 = 0 gives a pure Lambertian surface for
metallic = 0; metallic = 1 with white base colour gives F = 1, a white GGX conductor.)
"""

from __future__ import annotations

import torch

from neumatex_core.materials import albedo_tables
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
        """[N, 3] directional albedo at viewer directions wo [N, 3]: the Lambertian part plus this GGX lobe's own
        tabulated albedo (`albedo_tables`' spec_a / spec_b, exact for the separable Smith G up to ~1e-3; linear in
        F0 as UE4's Schlick is), the same tables the layered material's specular lobe uses. Karis' analytic fit
        of the split-sum LUT, used here before (assets/pbr_fit.split_sum_albedo), underrates this lobe's conductors
        by 0.07-0.14 at mid roughness."""
        mu = wo[:, 2].clamp(0.0, 1.0)
        spec_a = albedo_tables.lookup("spec_a", mu, self.roughness).unsqueeze(-1)
        spec_b = albedo_tables.lookup("spec_b", mu, self.roughness).unsqueeze(-1)
        grazing = (50.0 * self.f0[:, 1:2]).clamp(0.0, 1.0)  # as schlick_fresnel
        return self.diffuse_albedo + self.f0 * spec_a + grazing * spec_b

    def select(self, index: torch.Tensor) -> PBRMaterial:
        return PBRMaterial(self.base_color[index], self.roughness[index], self.metallic[index], self.dielectric_f0)
