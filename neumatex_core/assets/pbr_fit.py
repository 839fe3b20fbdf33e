"""PBR fallback: the metallic-roughness material (Lambert + GGX, UE4 mapping) closest to a neural material.

The fit compares cosine-weighted BSDFs, y = f(wi, wo) cos_i (the radiance reflected towards wo under a unit light
from wi), on a fixed set of K direction pairs shared by all texels: wo at the elevations VIEW_COS (azimuth 0), wi a
stratified cosine-weighted set of `PBRFitConfig.cosine_directions` directions (N_COSINE; a Fibonacci spiral through
`cosine_sample`), the mirror direction of wo and directions MIRROR_OFFSETS_DEG around it (in and out of the plane of
incidence), where glossy lobes live, and wo itself with directions RETRO_OFFSETS_DEG around it, where dust and fuzz
scatter back. The loss is the mean over pairs and RGB of (log(EPS + y_pbr) - log(EPS + y_neural))^2 (relative
error, as a tonemapped image sees it; EPS keeps near-black values from dominating) plus ALBEDO_WEIGHT times the same
for the directional albedo at the views (PBR: its own, `PBRMaterial.albedo`; neural: T rho_d + R): under an
environment map a surface shows mostly its albedo, and a few direction pairs cannot see all of it (the
back-scattering of dust missed the first version by 2x).

1. Distinct materials: texels' (rho_d, latent) rounded to 1/256 (below what an 8-bit texture resolves) are fitted
   once (at their members' mean), so uniform regions cost one fit.
2. Global search: for fixed roughness r and metallic m, y_pbr is affine in the base colour b (Lambert (1 - m) b / pi,
   Fresnel f0 = 0.04 (1 - m) + m b), y = b A(r, m) + B(r, m). Weighting squared linear differences by
   1 / (EPS + y_neural)^2 (the first-order expansion of the log loss) makes a good b in [0, 1] per channel a
   closed form (a few matrix products for every (r, m) of a GRID_ROUGHNESS (log-spaced) x GRID_METALLIC grid and
   every material); GAUSS_NEWTON steps on the exact loss improve each b (the linearisation underrates a missed
   sharp peak or back-scatter lobe), each grid point is scored by its exact loss, and the best is the start. (The
   affine model takes UE4's grazing factor clamp(50 f0_green) as 1, true for any f0 with green above 0.02; the
   refinement uses the exact BSDF.)
3. Refinement: `steps` Adam steps on the exact loss (base colour, roughness, metallic through sigmoids).
4. The result is quantised to 8 bits as glTF / USD store it (base colour sRGB-encoded, roughness and metallic
   linear), so the in-memory fallback is exactly what the files hold.

What PBR cannot express (sheen, back-scattering dust, a clear coat's second highlight, haze) is what the loss keeps;
bench/assets.py reports it per material family as render PSNR against the neural material.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from neumatex_core.assets.bake import dilate
from neumatex_core.capture.tonemap import srgb_eotf, srgb_oetf
from neumatex_core.materials.base import cosine_sample
from neumatex_core.materials.microfacet import ggx_eval
from neumatex_core.materials.neural_basis import NeuralBasis, NeuralMaterial
from neumatex_core.materials.pbr import DIELECTRIC_F0, PBRMaterial

VIEW_COS = (0.9, 0.6, 0.3)
# Cosine-weighted directions per view. 6 until 2026-12-07: the dozen mirror and retro pairs per view then outweighed
# the hemisphere, and the fallback rendered further from the neural material (bench/assets.py --fit-variants
# cosine_directions=6: design note 101). The synthetic data's PBR targets keep 6 (synth/materials.py).
N_COSINE = 64
MIRROR_OFFSETS_DEG = (5.0, 15.0)
RETRO_OFFSETS_DEG = (12.0, 30.0)
ALBEDO_WEIGHT = 1.0
EPS = 0.02
ROUGH_MIN = 0.05
GRID_ROUGHNESS = 20  # log-spaced: sharp lobes need finer steps
GAUSS_NEWTON = 2
GRID_METALLIC = 3
AlbedoModel = Literal["exact", "split_sum", "none"]
METHOD = ("grid search over roughness x metallic with closed-form base colour, then Adam on the log-space "
          "cosine-weighted BSDF difference over fixed direction pairs (neumatex_core/assets/pbr_fit.py)")


@dataclass(frozen=True)
class PBRFitConfig:
    steps: int = 20  # Adam refinement steps after the grid search (0: grid only)
    lr: float = 0.03
    chunk: int = 2048  # distinct materials per batch (memory ~ chunk x K x a few hundred bytes; no bit of the result)
    cosine_directions: int = N_COSINE  # the cosine-weighted wi per view (`fit_directions`)
    # The PBR side of the albedo term: "exact" (`PBRMaterial.albedo`), "split_sum" (Karis' fit, `split_sum_albedo`;
    # the term until 2026-12-07) or "none" (no albedo term); bench/assets.py --fit-variants compares them.
    albedo: AlbedoModel = "exact"


def fit_directions(cosine: int = N_COSINE) -> tuple[torch.Tensor, torch.Tensor]:
    """(wi [K, 3], wo [K, 3]) local unit directions of the fit with `cosine` cosine-weighted wi per view (see the
    module docstring)."""
    golden = (math.sqrt(5) - 1) / 2
    k = torch.arange(cosine, dtype=torch.float32)
    cos_set = cosine_sample(torch.stack([(k + 0.5) / cosine, ((k + 0.5) * golden) % 1.0], dim=-1))
    wis, wos = [], []
    for c in VIEW_COS:
        theta = math.acos(c)
        extra = [torch.tensor([-math.sin(theta), 0.0, c])]
        for deg in MIRROR_OFFSETS_DEG:
            a = math.radians(deg)
            for th in (theta - a, theta + a):  # in the plane of incidence
                if 0 <= th < math.pi / 2 - 0.05:
                    extra.append(torch.tensor([-math.sin(th), 0.0, math.cos(th)]))
            side = extra[0] * math.cos(a) + torch.tensor([0.0, math.sin(a), 0.0])  # out of the plane
            extra.append(side / side.norm())
        extra.append(torch.tensor([math.sin(theta), 0.0, c]))  # back towards the viewer: dust, fuzz back-scatter
        for deg in RETRO_OFFSETS_DEG:
            a = math.radians(deg)
            for th in (theta - a, theta + a):
                if abs(th) < math.pi / 2 - 0.05:
                    extra.append(torch.tensor([math.sin(th), 0.0, math.cos(th)]))
            side = torch.tensor([math.sin(theta) * math.cos(a), math.sin(a), c * math.cos(a)])  # out of plane
            extra.append(side / side.norm())
        wi = torch.cat([cos_set, torch.stack(extra)])
        wis.append(wi)
        wos.append(torch.tensor([math.sqrt(1 - c * c), 0.0, c]).expand(wi.shape[0], 3))
    return torch.cat(wis).float(), torch.cat(wos).float()


def encode_srgb8(x: torch.Tensor) -> torch.Tensor:
    """Linear [0, 1] -> uint8 sRGB codes."""
    return torch.round(srgb_oetf(x.clamp(0, 1)) * 255).to(torch.uint8)


# Decoding through 256-entry tables: a vectorised pow may round differently from its scalar tail, and the in-memory
# fallback must equal the one read back from its files bit for bit.
_SRGB8 = srgb_eotf(torch.arange(256, dtype=torch.float64) / 255).float()
_LINEAR8 = (torch.arange(256, dtype=torch.float64) / 255).float()


def decode_srgb8(code: torch.Tensor) -> torch.Tensor:
    """uint8 sRGB codes -> linear float32 (the one decoding used for quantising and for reading files)."""
    return _SRGB8.to(code.device)[code.long()]


def encode_linear8(x: torch.Tensor) -> torch.Tensor:
    return torch.round(x.clamp(0, 1) * 255).to(torch.uint8)


def decode_linear8(code: torch.Tensor) -> torch.Tensor:
    return _LINEAR8.to(code.device)[code.long()]


def quantize_pbr(texture: torch.Tensor) -> torch.Tensor:
    """[..., 5] (base colour, roughness, metallic) rounded to what 8-bit files hold."""
    return torch.cat([decode_srgb8(encode_srgb8(texture[..., :3])), decode_linear8(encode_linear8(texture[..., 3:]))],
                     dim=-1)


def _pbr_y(base: torch.Tensor, rough: torch.Tensor, metal: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor
           ) -> torch.Tensor:
    """y = f cos_i [M, K, 3] of PBR parameters [M, 3], [M], [M] at the K pairs."""
    m, k = base.shape[0], wi.shape[0]
    mat = PBRMaterial(base.repeat_interleave(k, 0), rough.repeat_interleave(k, 0), metal.repeat_interleave(k, 0))
    wi_r = wi.repeat(m, 1)
    return (mat.eval(wi_r, wo.repeat(m, 1)) * wi_r[:, 2:3].clamp_min(0)).view(m, k, 3)


def _log_loss(y: torch.Tensor, log_target: torch.Tensor) -> torch.Tensor:
    return ((torch.log(EPS + y) - log_target) ** 2).mean(dim=(1, 2))


def view_directions() -> torch.Tensor:
    """[V, 3] the fit's viewing directions wo (local frame)."""
    return torch.tensor([[math.sqrt(1 - c * c), 0.0, c] for c in VIEW_COS])


def split_sum_albedo(mat: PBRMaterial, wo: torch.Tensor) -> torch.Tensor:
    """[N, 3] Karis' analytic fit of UE4's split-sum environment BRDF (2013) for PBR materials at viewer directions wo
    [N, 3]: the fit's albedo term until 2026-12-07 (`PBRFitConfig.albedo` "split_sum"). It underrates this GGX's
    conductors by 0.07-0.14 at mid roughness (`PBRMaterial.albedo` is exact). With 6 cosine directions per view that
    let the fallback's metals render closer to the neural material; with 64 the exact albedo renders them closer
    (bench/assets.py --fit-variants albedo=split_sum; docs/design-notes.md, item 101)."""
    r = mat.roughness.unsqueeze(-1)
    n_dot_v = wo[:, 2].clamp(0.0, 1.0).unsqueeze(-1)
    c0 = torch.tensor([-1.0, -0.0275, -0.572, 0.022], device=wo.device)
    c1 = torch.tensor([1.0, 0.0425, 1.04, -0.04], device=wo.device)
    rr = r * c0 + c1
    a004 = torch.minimum(rr[:, 0:1] ** 2, torch.exp2(-9.28 * n_dot_v)) * rr[:, 0:1] + rr[:, 1:2]
    scale_a = -1.04 * a004 + rr[:, 2:3]  # the f0 part
    bias_b = 1.04 * a004 + rr[:, 3:4]  # the grazing part
    spec = mat.f0 * scale_a + (50.0 * mat.f0[:, 1:2]).clamp(0.0, 1.0) * bias_b  # as schlick_fresnel
    return mat.diffuse_albedo + spec


def pbr_albedo(p: torch.Tensor, model: AlbedoModel = "exact") -> torch.Tensor:
    """The fit's albedo [M, V, 3] of PBR parameters [M, 5] at the fit's views: `PBRMaterial.albedo`, or with model
    "split_sum" `split_sum_albedo`."""
    wo = view_directions().to(p.device)
    m, v = p.shape[0], wo.shape[0]
    rep = p.repeat_interleave(v, 0)
    mat = PBRMaterial(rep[:, :3], rep[:, 3], rep[:, 4])
    wo_r = wo.repeat(m, 1)
    return (split_sum_albedo(mat, wo_r) if model == "split_sum" else mat.albedo(wo_r)).view(m, v, 3)


def _total_loss(p: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, log_target: torch.Tensor,
                log_albedo: torch.Tensor | None, model: AlbedoModel = "exact") -> torch.Tensor:
    loss = _log_loss(_pbr_y(p[:, :3], p[:, 3], p[:, 4], wi, wo), log_target)
    if log_albedo is not None:
        loss = loss + ALBEDO_WEIGHT * _log_loss(pbr_albedo(p, model), log_albedo)
    return loss


def _affine_grid(wi: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(A [G, K], B [G, K], params [G, 2] = (roughness, metallic)): y = b A + B on the grid (UE4 grazing term 1)."""
    rough = torch.logspace(math.log10(ROUGH_MIN), 0.0, GRID_ROUGHNESS)
    metal = torch.linspace(0.0, 1.0, GRID_METALLIC)
    grid = torch.cartesian_prod(rough, metal)  # [G, 2]
    g, k = grid.shape[0], wi.shape[0]
    alpha = (grid[:, 0] ** 2).repeat_interleave(k)
    spec, cos_oh = ggx_eval(wi.repeat(g, 1), wo.repeat(g, 1), alpha)
    spec, cos_oh = spec.view(g, k), cos_oh.view(g, k)
    fc = (1 - cos_oh).clamp(0, 1) ** 5
    cos_i = wi[:, 2].clamp_min(0).unsqueeze(0)
    m = grid[:, 1:2]
    a = cos_i * ((1 - m) / math.pi + m * (1 - fc) * spec)
    b = cos_i * (DIELECTRIC_F0 * (1 - m) * (1 - fc) + fc) * spec
    return a, b, grid


def _grid_search(target: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, albedo: torch.Tensor | None = None,
                 chunk: int = 128, model: AlbedoModel = "exact") -> torch.Tensor:
    """Start parameters [M, 5] for targets y_neural [M, K, 3] (and albedos [M, V, 3]); step 2 of the module
    docstring. `chunk` materials at a time: at 128 its [chunk, 3, G, K] tensors stay in the CPU's cache (5x faster
    than 1024); each material's search is its own, so the chunk changes no bit of the result."""
    a, b, grid = (x.to(target.device) for x in _affine_grid(wi, wo))
    m, k, _ = target.shape
    w = 1 / (EPS + target) ** 2  # [M, K, 3]
    wt = w.permute(0, 2, 1).reshape(m * 3, k)
    tt = target.permute(0, 2, 1).reshape(m * 3, k)
    s_aa = wt @ (a * a).t()  # [M*3, G]
    s_ar = (wt * tt) @ a.t() - wt @ (a * b).t()  # sum w A (t - B)
    base = (s_ar / s_aa.clamp_min(1e-12)).clamp(0.0, 1.0).view(m, 3, -1)  # [M, 3, G]
    log_t = torch.log(EPS + target).permute(0, 2, 1).unsqueeze(2)  # [M, 3, 1, K]
    if albedo is not None:  # PBR albedo on the grid, affine in a grey base colour b: albedo(0) + b (albedo(1) - ...)
        n_g = grid.shape[0]
        ends = [pbr_albedo(torch.cat([torch.full((n_g, 3), v, device=grid.device), grid], dim=-1), model)[..., 0]
                for v in (0.02, 1.0)]  # [G, V] each; from 0.02 up, UE4's grazing factor is 1 as in `_affine_grid`
        alb_a = (ends[1] - ends[0]) / 0.98
        alb_b = ends[0] - 0.02 * alb_a
        log_alb = torch.log(EPS + albedo).permute(0, 2, 1).unsqueeze(2)  # [M, 3, 1, V]

    def loss_and_step(bc: torch.Tensor, sl: slice) -> tuple[torch.Tensor, torch.Tensor]:
        """Exact loss [c, 3, G] of base colours bc [c, 3, G] and their Gauss-Newton step in log space."""
        y = bc.unsqueeze(-1) * a + b  # [c, 3, G, K]
        r, jac = torch.log(EPS + y) - log_t[sl], a / (EPS + y)
        loss, num, den = (r * r).mean(-1), (r * jac).mean(-1), (jac * jac).mean(-1)
        if albedo is not None:
            ya = (bc.unsqueeze(-1) * alb_a + alb_b).clamp_min(0)
            ra, ja = torch.log(EPS + ya) - log_alb[sl], alb_a / (EPS + ya)
            loss = loss + ALBEDO_WEIGHT * (ra * ra).mean(-1)
            num, den = num + ALBEDO_WEIGHT * (ra * ja).mean(-1), den + ALBEDO_WEIGHT * (ja * ja).mean(-1)
        return loss, num / den.clamp_min(1e-12)

    # The linearised base colour underrates large relative misses (a sharp peak or a back-scatter lobe missed
    # entirely costs (t / t)^2 = 1 there but log(t / EPS)^2 in the log loss): GAUSS_NEWTON steps on the exact loss
    # per grid point, then each grid point is scored by its exact loss.
    loss = torch.empty(m, grid.shape[0], device=target.device)
    for s in range(0, m, chunk):
        sl = slice(s, s + chunk)
        bc = base[sl]
        for _ in range(GAUSS_NEWTON):
            _, step = loss_and_step(bc, sl)
            bc = (bc - step).clamp(0.0, 1.0)
        base[sl] = bc
        loss[sl] = loss_and_step(bc, sl)[0].mean(1)
    best = loss.argmin(-1)
    base_best = base.gather(2, best.view(m, 1, 1).expand(m, 3, 1))[:, :, 0]
    return torch.cat([base_best, grid[best]], dim=-1)


def neural_targets(basis: NeuralBasis, values: torch.Tensor, cosine: int = N_COSINE) -> torch.Tensor:
    """y_neural = f cos_i [M, K, 3] of neural materials values [M, 3 + L] (rho_d, latent [L]) at the fit's K
    pairs (`fit_directions(cosine)`)."""
    wi, wo = (x.to(values.device) for x in fit_directions(cosine))
    m, k = values.shape[0], wi.shape[0]
    with torch.no_grad():
        neural = NeuralMaterial(basis, values[:, :3].repeat_interleave(k, 0), values[:, 3:].repeat_interleave(k, 0))
        wi_r = wi.repeat(m, 1)
        return (neural.eval(wi_r, wo.repeat(m, 1)) * wi_r[:, 2:3].clamp_min(0)).view(m, k, 3)


def neural_albedo(basis: NeuralBasis, values: torch.Tensor) -> torch.Tensor:
    """Directional albedo [M, V, 3] (T rho_d + R, `NeuralMaterial.albedo`) of materials [M, 3 + L] at the fit's
    views."""
    wo = view_directions().to(values.device)
    m, v = values.shape[0], wo.shape[0]
    with torch.no_grad():
        neural = NeuralMaterial(basis, values[:, :3].repeat_interleave(v, 0), values[:, 3:].repeat_interleave(v, 0))
        return neural.albedo(wo.repeat(m, 1)).view(m, v, 3)


def fit_targets(target: torch.Tensor, albedo: torch.Tensor | None = None,
                cfg: PBRFitConfig | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """PBR parameters [M, 5] (base colour, roughness, metallic; 8-bit exact) and their loss [M] for targets
    y [M, K, 3] at the K pairs of `fit_directions` and (optional) directional albedos [M, V, 3] at the views
    (steps 2-4 of the module docstring; cfg.albedo "none" leaves the albedos out)."""
    cfg = cfg or PBRFitConfig()
    model = cfg.albedo
    if model == "none":
        albedo = None
    wi, wo = (x.to(target.device) for x in fit_directions(cfg.cosine_directions))
    if target.shape[1] != wi.shape[0]:
        raise ValueError(f"targets at {target.shape[1]} direction pairs, but the fit with {cfg.cosine_directions} "
                         f"cosine directions has {wi.shape[0]} (make them with the same cosine_directions)")
    with torch.no_grad():
        log_target = torch.log(EPS + target)
        log_albedo = None if albedo is None else torch.log(EPS + albedo)
        start = _grid_search(target, wi, wo, albedo, model=model)
        start_q = quantize_pbr(start)
        start_loss = _total_loss(start_q, wi, wo, log_target, log_albedo, model)
    if cfg.steps <= 0:
        return start_q, start_loss

    def logit(x: torch.Tensor, lo: float = 0.0) -> torch.Tensor:
        y = ((x - lo) / (1 - lo)).clamp(1e-3, 1 - 1e-3)
        return torch.log(y / (1 - y))

    pa = logit(start[:, :3]).requires_grad_(True)
    pb = logit(start[:, 3], ROUGH_MIN).requires_grad_(True)
    pc = logit(start[:, 4]).requires_grad_(True)
    opt = torch.optim.Adam([pa, pb, pc], lr=cfg.lr)

    def params() -> torch.Tensor:
        rough = ROUGH_MIN + (1 - ROUGH_MIN) * torch.sigmoid(pb)
        return torch.cat([torch.sigmoid(pa), rough.unsqueeze(-1), torch.sigmoid(pc).unsqueeze(-1)], dim=-1)

    with torch.enable_grad():  # a fit, whatever the caller's grad mode (e.g. a G-buffer written under no_grad)
        for _ in range(cfg.steps):
            loss = _total_loss(params(), wi, wo, log_target, log_albedo, model)
            opt.zero_grad()
            loss.sum().backward()
            opt.step()
    with torch.no_grad():
        refined = quantize_pbr(params())
        refined_loss = _total_loss(refined, wi, wo, log_target, log_albedo, model)
        better = refined_loss < start_loss
        return (torch.where(better.unsqueeze(-1), refined, start_q), torch.where(better, refined_loss, start_loss))


def fit_neural(basis: NeuralBasis, values: torch.Tensor, cfg: PBRFitConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """`fit_targets` for neural materials values [M, 3 + L] (rho_d, latent [L]): their targets and albedos made at
    cfg's direction set."""
    return fit_targets(neural_targets(basis, values, cfg.cosine_directions), neural_albedo(basis, values), cfg)


def fit_pbr(basis: NeuralBasis, material: torch.Tensor, mask: torch.Tensor | None = None,
            config: PBRFitConfig | None = None) -> tuple[torch.Tensor, float]:
    """(PBR texture [H, W, 5] (base colour, roughness, metallic) quantised to 8 bits, mean log loss over the texels
    in mask [H, W] (all if None)) fitted to a neural material texture [H, W, 3 + L] (rho_d, latent [L]). With a
    mask only the distinct materials of its texels are fitted (the surface's: renders read no other), each as
    without a mask, and the other texels are filled from them as the neural texture's were (`bake.dilate`, then
    quantised): the dilated texels are means of their neighbours, distinct materials each, and fitting them took
    40% of the demo's fit."""
    cfg = config or PBRFitConfig()
    h, w, c = material.shape
    flat = material.reshape(-1, c).detach().float()
    keys = torch.cat([torch.round(flat[:, :3] * 255), torch.round((flat[:, 3:] + 1) * 127.5)], dim=-1)
    uniq, inverse = np.unique(keys.cpu().numpy().astype(np.int16), axis=0, return_inverse=True)
    inverse_t = torch.from_numpy(inverse.reshape(-1)).to(material.device)
    sums = torch.zeros(len(uniq), c, device=material.device).index_add_(0, inverse_t, flat)
    counts = torch.zeros(len(uniq), device=material.device).index_add_(0, inverse_t, torch.ones_like(flat[:, 0]))
    values = sums / counts.unsqueeze(-1)  # each distinct material at all its texels' mean, surface or not
    inside = None if mask is None or not bool(mask.any()) else mask.reshape(-1).to(material.device)
    needed = torch.arange(len(uniq), device=material.device) if inside is None else inverse_t[inside].unique()
    params, losses = [], []
    for s in range(0, needed.shape[0], cfg.chunk):
        p, loss = fit_neural(basis, values[needed[s:s + cfg.chunk]], cfg)
        params.append(p)
        losses.append(loss)
    fitted = torch.zeros(len(uniq), 5, device=material.device)
    fitted_loss = torch.zeros(len(uniq), device=material.device)
    fitted[needed], fitted_loss[needed] = torch.cat(params), torch.cat(losses)
    texture, per_texel = fitted[inverse_t].reshape(h, w, 5), fitted_loss[inverse_t]
    if inside is None:
        return texture, float(per_texel.mean())
    surface = inside.view(h, w)
    filled = quantize_pbr(dilate(texture, surface))
    return torch.where(surface.unsqueeze(-1), texture, filled), float(per_texel[inside].mean())


def pbr_targets(params: torch.Tensor, cosine: int = N_COSINE) -> torch.Tensor:
    """y = f cos_i [M, K, 3] of PBR parameters [M, 5] (base colour, roughness, metallic) at the fit's K pairs
    (`fit_directions(cosine)`)."""
    wi, wo = (x.to(params.device) for x in fit_directions(cosine))
    return _pbr_y(params[:, :3], params[:, 3], params[:, 4], wi, wo)
