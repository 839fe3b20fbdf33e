"""The asset's PBR fallback chosen on held-out photos: the fit from the neural material, or the TTO's own PBR phase.

    asset = choose_fallback(asset, result.pbr_solution, held_photos, envmap, tonemap, config)

Every asset ships a PBR fallback (GLB / USD, for engines). `assets/pbr_fit.py` fits it to the neural material,
texel by texel, on BSDF values; where the neural material holds what PBR cannot (a metal's hazy second lobe, a
dusty layer), the closest PBR BSDF can render further from the photographs than a PBR material fitted to the
photographs themselves. The TTO's first phase is exactly such a fit (`tto/pbr_start.py`, the PBR baseline's TTO that
the neural phase starts from). Against Blender Cycles' photographs the fit to the neural material beat the PBR
baseline's TTO on coat, sheen and diffuse captures and lost to it by 1-3 dB on every metal; chosen as below, the
fallback beats it on all four (docs/design-notes.md, items 102 and 103).

So both candidates are baked to the asset's fallback textures (8-bit, as the files hold them) and rendered on the
photos that the TTO's choice held out (`validation_frames`), scored clean (`photo_psnr`, one seed for both); the PBR
phase's solution replaces the fit only where it scores higher by more than `margin_db`. The comparison leans towards
the fit: the PBR phase never saw the held-out photos, while the neural material the fit comes from saw them in its
final phase (`TTOConfig.select_reuse_start`).
"""

from __future__ import annotations

import dataclasses

import torch

from neumatex_core.assets.asset import MaterialAsset
from neumatex_core.assets.bake import bake, rasterize_uv
from neumatex_core.assets.pbr_fit import quantize_pbr
from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.fields.uv_textures import PBR_CHANNELS
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.tto.config import TTOConfig
from neumatex_core.tto.data import PhotoSet
from neumatex_core.tto.params import PBRUV, Parametrisation
from neumatex_core.tto.pbr_start import photo_psnr

PBR_PHASE_METHOD = ("the TTO's PBR phase (the PBR baseline's TTO on the photos), baked; chosen on held-out photos over "
                    "the fit to the neural material, whose loss is fit_loss (neumatex_core/tto/fallback_choice.py)")


def bake_pbr_solution(asset: MaterialAsset, solution: Parametrisation) -> torch.Tensor:
    """The PBR field `solution` (a PBR triplane: [N, 5] base colour, roughness, metallic at points) baked at the
    asset's texels: a fallback texture [R, R, 5], rounded to what 8-bit files hold (`quantize_pbr`)."""
    samples = rasterize_uv(asset.mesh, asset.texture_resolution)
    device = asset.pbr_texture.device
    texture = bake(samples, lambda p: solution.gbuffer(p.to(solution.tensor.device), None).to(device),
                   PBR_CHANNELS, device=device)  # fmt: skip
    return quantize_pbr(texture)


def fallback_score(texture: torch.Tensor, asset: MaterialAsset, photos: PhotoSet, envmap: EnvironmentMap,
                   tonemap: Tonemap, config: TTOConfig) -> float:
    """Clean PSNR (dB) of the fallback texture [R, R, 5] on the asset's mesh against `photos` (`photo_psnr` with
    the TTO's validation settings and the choice's seed, so two textures share their samples)."""
    return photo_psnr(PBRUV(texture), asset.mesh, envmap, photos, tonemap, config, config.seed + 1)


def choose_fallback(asset: MaterialAsset, solution: Parametrisation, held_out: PhotoSet, envmap: EnvironmentMap,
                    tonemap: Tonemap, config: TTOConfig, margin_db: float = 0.0) -> MaterialAsset:
    """The asset with the better of its fitted fallback and the PBR phase's `solution` baked, as scored on the
    held-out photos (`held_out`, on the asset's mesh: the TTO's normalised frame); the scores and the choice go to
    its metrics (fallback_psnr_fit, fallback_psnr_pbr_phase: dB; fallback_from_pbr_phase: 1 or 0) and the PBR
    phase's to its `pbr_method` (`pbr_fit_loss` stays the fit's, the candidate it was chosen over)."""
    candidate = bake_pbr_solution(asset, solution)
    fit = fallback_score(asset.pbr_texture, asset, held_out, envmap, tonemap, config)
    phase = fallback_score(candidate, asset, held_out, envmap, tonemap, config)
    taken = phase > fit + margin_db
    metrics = {**asset.metrics, "fallback_psnr_fit": fit, "fallback_psnr_pbr_phase": phase,
               "fallback_from_pbr_phase": float(taken)}  # fmt: skip
    if not taken:
        return dataclasses.replace(asset, metrics=metrics)
    return dataclasses.replace(asset, pbr_texture=candidate, pbr_method=PBR_PHASE_METHOD, metrics=metrics)
