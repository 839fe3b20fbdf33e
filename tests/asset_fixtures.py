"""A small triplane material asset for tests: a shared mesh with two materials of the prior blended over it."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from neumatex_core.assets import MaterialAsset, asset_from_triplane
from neumatex_core.assets.pbr_fit import PBRFitConfig
from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.eval.metrics import psnr
from neumatex_core.fields.fit import fit_triplane
from neumatex_core.geometry.camera import Camera, preset_views
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.neural_basis import NeuralBasis
from neumatex_core.materials.prior import sample_base_color, sample_parameters
from neumatex_core.render.path_tracer import PathTracerConfig

# Material comparisons: direct lighting by next-event estimation only, so two materials on the same mesh with the
# same seed see the same light samples (design note 10) and the difference of their images is the material's.
COMPARE = PathTracerConfig(spp=16, max_bounces=1, strategy="light", hide_background=True)


def blended_target(basis: NeuralBasis, families: tuple[str, str], seed: int = 0):
    """target(points) -> (rho_d, latent): two draws of the prior (one per family) blended by a smooth pattern."""
    g = torch.Generator().manual_seed(seed)
    params = torch.cat([sample_parameters(f, 1, g) for f in families])
    colors = torch.cat([sample_base_color(f, 1, g) for f in families])
    with torch.no_grad():
        latents = basis.encode(params.to(next(basis.parameters()).device)).cpu()

    def target(p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s = torch.sigmoid(4 * torch.sin(3 * p[:, 0] + 1) * torch.cos(2.5 * p[:, 1])).unsqueeze(-1)
        return colors[0] * s + colors[1] * (1 - s), latents[0] * s + latents[1] * (1 - s)

    return target


def make_asset(mesh: Mesh, basis: NeuralBasis, name: str = "test-object", resolution: int = 128,
               families: tuple[str, str] = ("plastic", "coated"), seed: int = 0, steps: int = 150,
               pbr: PBRFitConfig | None = None) -> MaterialAsset:
    points = mesh.sample_surface(6000, seed=seed)[0]
    field, mse = fit_triplane(points, blended_target(basis, families, seed), basis, channels=8, resolution=32,
                              steps=steps, batch=2048, seed=seed)
    return asset_from_triplane(name, mesh, field, resolution=resolution, pbr=pbr,
                               provenance={"source": "tests", "families": list(families)},
                               metrics={"distil_mse": mse})  # fmt: skip


def views(resolution: int, indices: Sequence[int] = (0, 6, 12)) -> list[Camera]:
    presets = preset_views(resolution)
    return [presets[i] for i in indices]


def render_psnr(a: list[torch.Tensor], b: list[torch.Tensor], mesh: Mesh, cameras: list[Camera]) -> float:
    """PSNR after the default tonemap over the covered pixels of all views together."""
    tm = Tonemap().apply
    masks = [render_gbuffer(mesh, c).mask for c in cameras]
    x = torch.cat([tm(img)[m] for img, m in zip(a, masks, strict=True)])
    y = torch.cat([tm(img)[m] for img, m in zip(b, masks, strict=True)])
    return psnr(x.unsqueeze(0), y.unsqueeze(0))


def studio(shared_envmaps) -> EnvironmentMap:
    return EnvironmentMap.from_file(shared_envmaps / "studio.exr")
