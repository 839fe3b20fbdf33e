"""GGX (Trowbridge-Reitz) microfacet distribution: D, separable Smith G and visible-normal sampling.

Local frame, +Z normal. `alpha` [N] is the GGX width (alpha = roughness^2 in the UE4 mapping). The shadowing
term is the separable Smith form G1(wi) G1(wo), as in Mitsuba 3's `roughconductor`.
"""

from __future__ import annotations

import math

import torch

ALPHA_MIN = 1e-3  # below this the lobe is a near-delta that neither sampling nor float32 handles well


def ggx_d(cos_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Normal distribution D(h) [N] for cos(theta_h) [N]."""
    a2 = alpha * alpha
    c2 = cos_h * cos_h
    denom = c2 * (a2 - 1) + 1
    return torch.where(cos_h > 0, a2 / (math.pi * denom * denom).clamp_min(1e-30), torch.zeros_like(cos_h))


def smith_g1(w: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Smith masking G1(w) [N] for local directions w [N, 3] (h-independent form, w above the surface)."""
    c2 = (w[:, 2] * w[:, 2]).clamp(1e-12, 1.0)
    tan2 = (1 - c2) / c2
    return 2 / (1 + torch.sqrt(1 + alpha * alpha * tan2))


def ggx_eval(wi: torch.Tensor, wo: torch.Tensor, alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """D G / (4 cos_i cos_o) [N] (a Fresnel factor is applied by the caller) and dot(wo, h) [N] for Fresnel."""
    h = wi + wo
    h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cos_i, cos_o = wi[:, 2], wo[:, 2]
    valid = (cos_i > 0) & (cos_o > 0)
    d = ggx_d(h[:, 2], alpha)
    g = smith_g1(wi, alpha) * smith_g1(wo, alpha)
    value = d * g / (4 * cos_i * cos_o).clamp_min(1e-12)
    return torch.where(valid, value, torch.zeros_like(value)), (wo * h).sum(-1).clamp(0.0, 1.0)


def ggx_sample_visible(wo: torch.Tensor, alpha: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Reflected directions wi [N, 3] from visible-normal sampling (Heitz 2018) given wo [N, 3], u [N, 2]."""
    vh = torch.stack([alpha * wo[:, 0], alpha * wo[:, 1], wo[:, 2]], dim=-1)
    vh = vh / vh.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    lensq = vh[:, 0] ** 2 + vh[:, 1] ** 2
    inv = torch.rsqrt(lensq.clamp_min(1e-20))
    t1 = torch.where(
        (lensq > 0).unsqueeze(-1),
        torch.stack([-vh[:, 1] * inv, vh[:, 0] * inv, torch.zeros_like(inv)], dim=-1),
        torch.tensor([1.0, 0.0, 0.0], device=wo.device).expand_as(vh),
    )
    t2 = torch.cross(vh, t1, dim=-1)
    r = torch.sqrt(u[:, 0])
    phi = 2 * math.pi * u[:, 1]
    p1 = r * torch.cos(phi)
    p2 = r * torch.sin(phi)
    s = 0.5 * (1 + vh[:, 2])
    p2 = (1 - s) * torch.sqrt((1 - p1 * p1).clamp_min(0.0)) + s * p2
    nh = t1 * p1[:, None] + t2 * p2[:, None] + vh * torch.sqrt((1 - p1 * p1 - p2 * p2).clamp_min(0.0))[:, None]
    h = torch.stack([alpha * nh[:, 0], alpha * nh[:, 1], nh[:, 2].clamp_min(1e-6)], dim=-1)
    h = h / h.norm(dim=-1, keepdim=True)
    return 2 * (wo * h).sum(-1, keepdim=True) * h - wo


def ggx_pdf_visible(wi: torch.Tensor, wo: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Solid-angle pdf [N] of `ggx_sample_visible`: G1(wo) D(h) / (4 cos_o)."""
    h = wi + wo
    h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cos_o = wo[:, 2]
    valid = (cos_o > 0) & (wi[:, 2] > 0)
    pdf = smith_g1(wo, alpha) * ggx_d(h[:, 2], alpha) / (4 * cos_o).clamp_min(1e-12)
    return torch.where(valid, pdf, torch.zeros_like(pdf))


def schlick_fresnel(f0: torch.Tensor, cos: torch.Tensor) -> torch.Tensor:
    """Schlick's Fresnel [N, 3] for reflectance at normal incidence f0 [N, 3] and cos [N], in Unreal Engine 4's
    form: the grazing term is faded out for f0 below 0.02 (no real material is that dark, UE4 reads it as
    specular occlusion), so f0 = 0 switches the lobe off exactly and f0 = 1 gives F = 1."""
    m = (1 - cos).clamp(0.0, 1.0)
    fc = ((m * m) * (m * m) * m).unsqueeze(-1)
    grazing = (50.0 * f0[..., 1:2]).clamp(0.0, 1.0)
    return grazing * fc + (1 - fc) * f0
