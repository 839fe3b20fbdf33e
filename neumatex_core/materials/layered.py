"""Analytic layered material: dust, fuzz, clear coat, specular GGX + haze and scatter over a Lambertian base.

This is our stand-in for the procedural materials behind the paper's neural basis (docs/architecture.md section 3, paper
eq. 1): f(wi, wo) = T rho_d / pi + f_spec(wi, wo), with 22 parameters per point (`PARAMETER_NAMES`, each in
[0, 1], mapped to physical ranges below) and the Lambertian base colour rho_d [N, 3] kept separate.

Layers, top to bottom, each a lobe with directional albedo E(wo) (tabulated in `albedo_tables`):

| layer   | lobe                                                  | reflects (RGB) | passes down (RGB)           |
|---------|-------------------------------------------------------|----------------|-----------------------------|
| dust    | (1 + k wi.wo)_+ / pi, normalised to albedo 1           | c a            | 1 - c                       |
| fuzz    | Charlie sheen (roughness 0.1..1), albedo clamped <= 1 | w_f col E_f    | 1 - w_f E_f                 |
| coat    | GGX, exact dielectric Fresnel (IOR 1.3..2)            | w_c E_c        | (1 - w_c E_c) tint^(w_c/mu_t) |
| spec    | GGX + wider GGX haze, UE4 Schlick with F0 (RGB)       | E_s            | 1 - E_s                     |
| scatter | HG single-scattering slab lobe, normalised to albedo 1 | w_s            | 1 - w_s                     |
| base    | Lambert rho_d / pi                                    | T rho_d        |                             |

Energy by albedo scaling: a layer's lobe and everything beneath it are weighted by the product of the "passes
down" factors of the layers above, all evaluated at wo (the viewer-side, known direction). Each factor is
1 - (what the layer reflects or absorbs), so the directional albedo telescopes:
albedo(wo) = sum_layers above(wo) * reflects(wo) + T(wo) rho_d, which is exactly 1 for a non-absorbing
material (white tints / colours, dust albedo 1, rho_d = 1) and <= 1 otherwise, up to the tables' error (~1e-3).
The price is reciprocity: f(wi, wo) != f(wo, wi) in general (as with Kulla & Conty's albedo scaling).

Directions: T and R are functions of wo. The paper writes T(omega_i) and uses R(omega_i) to choose between the
diffuse and specular lobes when sampling, so its omega_i is the known, viewer-side direction: our wo.

Parameter map (p = the normalised entry):
dust_coverage c = p; dust_backscatter k = 3p; dust_albedo a = p (grey);
fuzz_weight w_f = p; fuzz_roughness = 0.1 + 0.9p; fuzz_color_{r,g,b} = p;
coat_weight w_c = p; coat_roughness r_c = p (alpha = r_c^2); coat_ior = 1.3 + 0.7p;
coat_tint_{r,g,b} = p (transmittance through the coat at normal incidence);
spec_roughness r_s = p (alpha = r_s^2); spec_f0_{r,g,b} = p (UE4 Schlick, f0 = 0 switches the lobe off);
haze_weight h = p (share of the specular energy in the haze lobe); haze_spread: haze roughness r_s + p (1 - r_s);
scatter_weight w_s = p; scatter_anisotropy g = 1.2p - 0.6 (HG; > 0 forward, towards grazing, < 0 back).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from neumatex_core.materials import albedo_tables as tables
from neumatex_core.materials.base import Material, cosine_pdf, cosine_sample, luminance
from neumatex_core.materials.microfacet import ggx_eval, ggx_pdf_visible, ggx_sample_visible, schlick_fresnel

PARAMETER_NAMES: tuple[str, ...] = (
    "dust_coverage", "dust_backscatter", "dust_albedo",
    "fuzz_weight", "fuzz_roughness", "fuzz_color_r", "fuzz_color_g", "fuzz_color_b",
    "coat_weight", "coat_roughness", "coat_ior", "coat_tint_r", "coat_tint_g", "coat_tint_b",
    "spec_roughness", "spec_f0_r", "spec_f0_g", "spec_f0_b",
    "haze_weight", "haze_spread",
    "scatter_weight", "scatter_anisotropy",
)  # fmt: skip
N_PARAMS = len(PARAMETER_NAMES)
assert N_PARAMS == 22
INDEX = {name: i for i, name in enumerate(PARAMETER_NAMES)}

# Sampling mixture components, in this order.
LOBES = ("cosine", "uniform", "coat", "spec", "haze")
P_COSINE_MIN = 0.1  # the cosine component keeps this share, so every direction where f > 0 has pdf > 0


@dataclass
class _Stack:
    """Per-point layer weights at wo (all [N] or [N, 3]); see the module docstring's table."""

    dust_scale: torch.Tensor  # [N] c a / E_dust_raw(wo): multiplies the raw dust lobe
    dust_k: torch.Tensor  # [N]
    fuzz_scale: torch.Tensor  # [N, 3] above * w_f col / max(E_f, 1): multiplies the sheen lobe
    fuzz_r: torch.Tensor  # [N]
    coat_scale: torch.Tensor  # [N, 3] above * w_c: multiplies the coat GGX lobe (with Fresnel)
    coat_alpha: torch.Tensor  # [N]
    coat_eta: torch.Tensor  # [N]
    spec_scale: torch.Tensor  # [N, 3] above: multiplies F (spec lobe + haze lobe)
    spec_alpha: torch.Tensor  # [N]
    haze_alpha: torch.Tensor  # [N]
    haze_weight: torch.Tensor  # [N]
    f0: torch.Tensor  # [N, 3]
    scatter_scale: torch.Tensor  # [N, 3] above * w_s / E_scatter_raw(wo)
    scatter_g: torch.Tensor  # [N]
    transmission: torch.Tensor  # [N, 3] T(wo): what reaches the Lambertian base
    reflected: torch.Tensor  # [N, 3] directional albedo of f_spec at wo
    lobe_energy: torch.Tensor  # [N, 5] reflected energy per sampling component (LOBES), base excluded


class LayeredMaterial(Material):
    """The layered material at N points.

    params: [N, 22] in [0, 1] (order `PARAMETER_NAMES`); base_color: [N, 3] Lambertian rho_d in [0, 1].
    Both may require grad; everything is differentiable in them (sampling and pdfs are detached).
    """

    def __init__(self, params: torch.Tensor, base_color: torch.Tensor) -> None:
        if params.shape[-1] != N_PARAMS or params.dim() != 2:
            raise ValueError(f"params must be [N, {N_PARAMS}], got {tuple(params.shape)}")
        if base_color.shape != (params.shape[0], 3):
            raise ValueError(f"base_color must be [N, 3], got {tuple(base_color.shape)}")
        self.params = params
        self.base_color = base_color

    def p(self, name: str) -> torch.Tensor:
        """[N] normalised parameter `name` (an RGB parameter's channels are `name_r`, `name_g`, `name_b`)."""
        return self.params[:, INDEX[name]]

    def rgb(self, name: str) -> torch.Tensor:
        """[N, 3] the three channels `name_r`, `name_g`, `name_b`."""
        i = INDEX[name + "_r"]
        return self.params[:, i:i + 3]

    def _stack(self, wo: torch.Tensor) -> _Stack:
        """Layer weights at wo [N, 3]; differentiable in the parameters."""
        mu = wo[:, 2].clamp(0.0, 1.0).to(self.params.dtype)
        one = torch.ones_like(mu)

        # Dust: coverage c intercepts, reflects a of it with a normalised back-scattering lobe.
        c, a, pk = self.p("dust_coverage"), self.p("dust_albedo"), self.p("dust_backscatter")
        dust_refl = (c * a).unsqueeze(-1).expand(-1, 3)
        above = (1 - c).unsqueeze(-1).expand(-1, 3)

        # Fuzz: Charlie sheen; its albedo can exceed 1 at grazing angles (Neubelt's V), so clamp it.
        w_f, pr = self.p("fuzz_weight"), self.p("fuzz_roughness")
        e_f = tables.lookup("fuzz", mu, pr)
        norm_f = 1 / torch.maximum(e_f, one)
        fuzz_refl = above * (w_f * e_f * norm_f).unsqueeze(-1) * self.rgb("fuzz_color")
        fuzz_scale = above * (w_f * norm_f).unsqueeze(-1) * self.rgb("fuzz_color")
        above = above * (1 - w_f * e_f * norm_f).unsqueeze(-1)

        # Clear coat: dielectric GGX; the light it lets through is absorbed by the tint along the refracted path.
        w_c, r_c, q = self.p("coat_weight"), self.p("coat_roughness"), self.p("coat_ior")
        eta = tables.coat_ior(q)
        e_c = tables.lookup("coat", mu, r_c, q)
        coat_scale = above * w_c.unsqueeze(-1)
        coat_refl = coat_scale * e_c.unsqueeze(-1)
        path = (w_c / tables.refracted_cos(mu, eta).clamp_min(1e-3)).unsqueeze(-1)
        tint = torch.exp(path * torch.log(self.rgb("coat_tint").clamp_min(1e-3)))
        above = above * (1 - w_c * e_c).unsqueeze(-1) * tint

        # Specular GGX + haze (a second, wider GGX lobe sharing F0).
        r_s, h, spread = self.p("spec_roughness"), self.p("haze_weight"), self.p("haze_spread")
        r_h = r_s + spread * (1 - r_s)
        f0 = self.rgb("spec_f0")
        grazing = (50.0 * f0[:, 1:2]).clamp(0.0, 1.0)
        e_spec = f0 * tables.lookup("spec_a", mu, r_s).unsqueeze(-1) + grazing * tables.lookup(
            "spec_b", mu, r_s).unsqueeze(-1)
        e_haze = f0 * tables.lookup("spec_a", mu, r_h).unsqueeze(-1) + grazing * tables.lookup(
            "spec_b", mu, r_h).unsqueeze(-1)
        hh = h.unsqueeze(-1)
        spec_albedo = (1 - hh) * e_spec + hh * e_haze
        spec_scale = above
        spec_refl = above * (1 - hh) * e_spec
        haze_refl = above * hh * e_haze
        above = above * (1 - spec_albedo)

        # Scatter: a soft, white, sub-surface-like lobe normalised to albedo 1.
        w_s, pg = self.p("scatter_weight"), self.p("scatter_anisotropy")
        scatter_refl = above * w_s.unsqueeze(-1)
        scatter_scale = scatter_refl / tables.lookup("scatter", mu, pg).unsqueeze(-1)
        transmission = above * (1 - w_s).unsqueeze(-1)

        dust_scale = c * a / tables.lookup("dust", mu, pk)
        reflected = dust_refl + fuzz_refl + coat_refl + spec_refl + haze_refl + scatter_refl
        lobe_energy = torch.stack(
            [luminance(dust_refl + scatter_refl), luminance(fuzz_refl), luminance(coat_refl),
             luminance(spec_refl), luminance(haze_refl)], dim=-1)  # fmt: skip
        return _Stack(
            dust_scale=dust_scale, dust_k=tables.dust_k(pk),
            fuzz_scale=fuzz_scale, fuzz_r=tables.fuzz_roughness(pr),
            coat_scale=coat_scale, coat_alpha=tables.ggx_alpha(r_c), coat_eta=eta,
            spec_scale=spec_scale, spec_alpha=tables.ggx_alpha(r_s), haze_alpha=tables.ggx_alpha(r_h),
            haze_weight=h, f0=f0,
            scatter_scale=scatter_scale, scatter_g=tables.scatter_g(pg),
            transmission=transmission, reflected=reflected, lobe_energy=lobe_energy,
        )  # fmt: skip

    def components(self, wi: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(f_spec [N, 3] (1/sr, no cosine), T(wo) [N, 3] in [0, 1], R(wo) [N] in [0, 1]) of eq. 1.

        f_spec is the sum of all non-diffuse lobes after layering, zero when wi or wo is below the surface;
        T the transmission albedo reaching the Lambertian base; R the luminance of f_spec's directional albedo
        (the integral of f_spec cos(theta_i) over wi), for choosing between diffuse and specular sampling.
        """
        s = self._stack(wo)
        above = ((wi[:, 2] > 0) & (wo[:, 2] > 0)).unsqueeze(-1)
        dust = (s.dust_scale * tables.dust_lobe_raw(wi, wo, s.dust_k)).unsqueeze(-1)
        fuzz = s.fuzz_scale * tables.sheen_lobe(wi, wo, s.fuzz_r).unsqueeze(-1)
        ggx_c, cos_oh = ggx_eval(wi, wo, s.coat_alpha)
        coat = s.coat_scale * (ggx_c * tables.fresnel_dielectric(cos_oh, s.coat_eta)).unsqueeze(-1)
        ggx_s, _ = ggx_eval(wi, wo, s.spec_alpha)
        ggx_h, _ = ggx_eval(wi, wo, s.haze_alpha)
        lobes = (1 - s.haze_weight) * ggx_s + s.haze_weight * ggx_h
        spec = s.spec_scale * schlick_fresnel(s.f0, cos_oh) * lobes.unsqueeze(-1)
        scatter = s.scatter_scale * tables.scatter_lobe_raw(wi, wo, s.scatter_g).unsqueeze(-1)
        f_spec = dust + fuzz + coat + spec + scatter
        f_spec = torch.where(above, f_spec, torch.zeros_like(f_spec))
        return f_spec, s.transmission, luminance(s.reflected)

    def eval(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """f = T(wo) rho_d / pi + f_spec(wi, wo) [N, 3] (eq. 1), zero below the surface."""
        f_spec, transmission, _ = self.components(wi, wo)
        above = ((wi[:, 2] > 0) & (wo[:, 2] > 0)).unsqueeze(-1)
        diffuse = torch.where(above, transmission * self.base_color / math.pi, torch.zeros_like(f_spec))
        return diffuse + f_spec

    def lobe_probabilities(self, wo: torch.Tensor) -> torch.Tensor:
        """[N, 5] probabilities of the sampling components (`LOBES`), detached.

        Proportional to each component's reflected energy at wo (the cosine component takes the base, dust and
        scatter), blended with P_COSINE_MIN of pure cosine sampling so that no lobe is ever unreachable.
        """
        with torch.no_grad():
            s = self._stack(wo)
            energy = s.lobe_energy.clone()
            energy[:, 0] = energy[:, 0] + luminance(s.transmission * self.base_color)
            energy = energy.clamp_min(0.0)
            total = energy.sum(-1, keepdim=True)
            cosine_only = torch.zeros_like(energy)
            cosine_only[:, 0] = 1
            share = torch.where(total > 0, energy / total.clamp_min(1e-12), cosine_only)
            return (1 - P_COSINE_MIN) * share + P_COSINE_MIN * cosine_only

    def _alphas(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        r_s = self.p("spec_roughness").detach()
        r_h = r_s + self.p("haze_spread").detach() * (1 - r_s)
        return tables.ggx_alpha(self.p("coat_roughness").detach()), tables.ggx_alpha(r_s), tables.ggx_alpha(r_h)

    def sample(self, wo: torch.Tensor, u_lobe: torch.Tensor, u_dir: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mixture sampling (detached): a component chosen by u_lobe [N] with `lobe_probabilities`, a direction
        from it with u_dir [N, 2]; returns wi [N, 3] and the exact mixture pdf [N] (0 for wi below the surface)."""
        with torch.no_grad():
            probs = self.lobe_probabilities(wo).to(wo.dtype)
            a_c, a_s, a_h = (a.to(wo.dtype) for a in self._alphas())
            z = u_dir[:, 0]
            phi = 2 * math.pi * u_dir[:, 1]
            rad = torch.sqrt((1 - z * z).clamp_min(0.0))
            uniform = torch.stack([rad * torch.cos(phi), rad * torch.sin(phi), z], dim=-1)
            candidates = torch.stack(
                [cosine_sample(u_dir), uniform, ggx_sample_visible(wo, a_c, u_dir),
                 ggx_sample_visible(wo, a_s, u_dir), ggx_sample_visible(wo, a_h, u_dir)], dim=1)  # fmt: skip
            cdf = probs.cumsum(-1)
            choice = (u_lobe.unsqueeze(-1) >= cdf[:, :-1]).sum(-1)
            wi = candidates[torch.arange(wo.shape[0], device=wo.device), choice]
            return wi, self.pdf(wi, wo)

    def pdf(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """Solid-angle pdf [N] of `sample`: sum over components of probability * component pdf; detached."""
        with torch.no_grad():
            probs = self.lobe_probabilities(wo).to(wo.dtype)
            a_c, a_s, a_h = (a.to(wo.dtype) for a in self._alphas())
            valid = (wi[:, 2] > 0) & (wo[:, 2] > 0)
            pdfs = torch.stack(
                [cosine_pdf(wi), torch.full_like(wi[:, 2], 1 / (2 * math.pi)), ggx_pdf_visible(wi, wo, a_c),
                 ggx_pdf_visible(wi, wo, a_s), ggx_pdf_visible(wi, wo, a_h)], dim=-1)  # fmt: skip
            pdf = (probs * pdfs).sum(-1)
            return torch.where(valid, pdf, torch.zeros_like(pdf))

    def albedo(self, wo: torch.Tensor) -> torch.Tensor:
        """Directional albedo [N, 3] = R_rgb(wo) + T(wo) rho_d from the tables (exact up to table error)."""
        s = self._stack(wo)
        value = s.reflected + s.transmission * self.base_color
        return torch.where((wo[:, 2] > 0).unsqueeze(-1), value, torch.zeros_like(value))

    def select(self, index: torch.Tensor) -> LayeredMaterial:
        return LayeredMaterial(self.params[index], self.base_color[index])
