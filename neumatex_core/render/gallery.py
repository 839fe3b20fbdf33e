"""Sphere galleries: one material on the unit sphere under an environment map, analytic next to neural.

`sphere_pair` renders a layered material (analytic) and its neural encoding (basis encoder -> latent, decoded by
the basis) with the same tracer settings; `family_gallery` tiles such pairs for every material family of the prior
under several maps into one labelled image (`neumatex gallery`). The benchmark `bench/basis.py` reuses
`sphere_pair` for its per-family PSNR.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from neumatex_core.geometry.mesh import Mesh, icosphere
from neumatex_core.geometry.surface import SurfaceInteraction
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.field import MaterialField, UniformLayered
from neumatex_core.materials.neural_basis import NeuralBasis, NeuralMaterial
from neumatex_core.materials.prior import FAMILIES, sample_base_color, sample_parameters
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.render.views import sphere_camera


class UniformNeural(MaterialField):
    """One neural material everywhere: base_color [3] rho_d, latent [K] (tensors may require grad)."""

    def __init__(self, basis: NeuralBasis, base_color: torch.Tensor, latent: torch.Tensor) -> None:
        self.basis, self.base_color, self.latent = basis, base_color, latent

    def at(self, si: SurfaceInteraction) -> NeuralMaterial:
        n = si.position.shape[0]
        device = si.position.device
        return NeuralMaterial(self.basis, self.base_color.to(device).expand(n, 3),
                              self.latent.to(device).expand(n, -1))  # fmt: skip


@dataclass
class SphereSettings:
    """Image size (pixels), samples per pixel, seed; spheres are convex, so one bounce is exact.

    strategy "light" (the default here): both materials see the same light samples, so the difference between
    the analytic and the neural image is the BSDF difference, not two independent Monte Carlo noises.
    """

    resolution: int = 96
    spp: int = 64
    seed: int = 0
    strategy: Literal["mis", "light", "bsdf"] = "light"


def sphere_pair(params: torch.Tensor, base_color: torch.Tensor, envmap: EnvironmentMap, basis: NeuralBasis,
                settings: SphereSettings, sphere: Mesh | None = None,
                latent: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(analytic, neural) linear HDR images [H, W, 3] of the unit sphere; background black.

    params [22] normalised layered parameters, base_color [3]. The neural latent [latent_dim] is `latent`, by
    default basis.encode(params).
    """
    device = envmap.device
    sphere = sphere if sphere is not None else icosphere(4)
    with torch.no_grad():
        latent = basis.encode(params.unsqueeze(0).to(device))[0] if latent is None else latent.to(device)
        tracer = PathTracer(PathTracerConfig(max_bounces=1, spp=settings.spp, hide_background=True,
                                          strategy=settings.strategy))
        cam = sphere_camera(settings.resolution)
        images = []
        for field in (UniformLayered(params, base_color), UniformNeural(basis, base_color, latent)):
            scene = Scene(sphere, envmap, field, device=device)
            images.append(tracer.render(scene, cam, seed=settings.seed))
    return images[0], images[1]


def family_materials(per_family: int, seed: int) -> list[tuple[str, torch.Tensor, torch.Tensor]]:
    """(family, params [22], base_color [3]) for `per_family` draws of every family, deterministic in seed."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for family in FAMILIES:
        params = sample_parameters(family, per_family, g)
        colors = sample_base_color(family, per_family, g)
        out += [(family, params[i], colors[i]) for i in range(per_family)]
    return out


def family_gallery(envmaps: Sequence[tuple[str, EnvironmentMap]], basis: NeuralBasis, settings: SphereSettings,
                   tonemap: Callable[[torch.Tensor], torch.Tensor], per_family: int = 1,
                   progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """One labelled display image [H, W, 3] in [0, 1]: a row per material (family), per map an analytic and a
    neural column."""
    materials = family_materials(per_family, settings.seed)
    sphere = icosphere(4)
    tiles: list[list[np.ndarray]] = []
    total, done = len(materials) * len(envmaps), 0
    for _, params, color in materials:
        row = []
        for _, env in envmaps:
            analytic, neural = sphere_pair(params, color, env, basis, settings, sphere)
            row += [tonemap(analytic).cpu().numpy(), tonemap(neural).cpu().numpy()]
            done += 1
            if progress is not None:
                progress(done, total)
        tiles.append(row)
    headers = [f"{name} {kind}" for name, _ in envmaps for kind in ("analytic", "neural")]
    return _labelled_grid(tiles, [m[0] for m in materials], headers)


def _labelled_grid(tiles: list[list[np.ndarray]], row_labels: list[str], col_labels: list[str]) -> np.ndarray:
    """Tiles [rows][cols] of [h, w, 3] images -> one image with a label column and a header row (Pillow text)."""
    from PIL import Image, ImageDraw

    h, w = tiles[0][0].shape[:2]
    pad, left, top = 4, 90, 22
    rows, cols = len(tiles), len(tiles[0])
    canvas = Image.new("RGB", (left + cols * (w + pad) + pad, top + rows * (h + pad) + pad), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for c, label in enumerate(col_labels):
        draw.text((left + pad + c * (w + pad), 5), label, fill=(0, 0, 0))
    for r, row in enumerate(tiles):
        draw.text((6, top + pad + r * (h + pad) + h // 2 - 6), row_labels[r], fill=(0, 0, 0))
        for c, tile in enumerate(row):
            img = Image.fromarray((np.clip(tile, 0, 1) * 255 + 0.5).astype(np.uint8))
            canvas.paste(img, (left + pad + c * (w + pad), top + pad + r * (h + pad)))
    return np.asarray(canvas, dtype=np.float32) / 255.0
