"""A neural start chosen by appearance, cell by cell, among the material families (docs/design-notes.md, item 86).

    rho, latent, record = appearance_start(basis, points, rho, latent, start_at, mesh, envmap, photos, tonemap)

One descent from a neutral start stops in another family's valley: the appearance of a capture is far from convex in
the latent (bench/latent_starts.py: from the mean latent 14.3 dB of latents, the best of nine family starts 26.8). So
before the neural TTO descends, each cell of a voxel grid over the object gets the start that reproduces the photos
that see it best: its PBR start (the PBR solution expressed in the basis) or one of the family prototypes
(`family_prototypes`) with the PBR start's base colour. Each candidate is rendered by the path tracer at the same
observed pixels with the same random numbers (`candidate_errors`: the product of two half-renders' errors, so the
render's noise drops out and a sharp lobe is not penalised for being noisy), and a cell takes a prototype only where
it lowers the cell's error by `CELL_MARGIN`. A cheaper model of the photos (each pixel's direct light from 64 shared
environment directions, no interreflection) preferred smooth lobes everywhere: its noise on a sharp lobe counted as
error (item 86).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.geometry.surface import SurfaceInteraction
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.field import MaterialField
from neumatex_core.materials.neural_basis import NeuralBasis, NeuralMaterial
from neumatex_core.materials.prior import FAMILIES, sample_parameters
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.tto.data import PhotoSet

OBSERVED_PIXELS = 4096  # photo pixels the cells are compared on
RENDER_SPP = 16  # path samples per observed pixel of each candidate's render (two halves)
GRID = 3  # cells per axis of the object's bounding box
MIN_CELL_PIXELS = 32  # a cell with fewer observed pixels keeps its PBR start
PROTOTYPE_SAMPLES = 256  # prior draws each family's prototype latent is the mean encoding of
CELL_MARGIN = 0.1  # a prototype must lower the cell's squared error by this fraction to replace the PBR start
SATURATED = 0.99  # display value at or above which a pixel is clipped and not observed

StartAt = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]  # points [P, 3] -> (rho_d [P, 3], latent [P, D])


class StartField(MaterialField):
    """The start `start_at` gives at each shading point, with `latent` [D] all over instead of its latent (None: its
    own)."""

    def __init__(self, basis: NeuralBasis, start_at: StartAt, latent: torch.Tensor | None = None) -> None:
        self.basis, self.start_at, self.latent = basis, start_at, latent

    def at(self, si: SurfaceInteraction) -> NeuralMaterial:
        rho, latent = self.start_at(si.position)
        if self.latent is not None:
            latent = self.latent.expand(latent.shape[0], -1)
        return NeuralMaterial(self.basis, rho, latent)


def observed_pixels(scene: Scene, photos: PhotoSet, n_pixels: int = OBSERVED_PIXELS,
                    seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Up to n_pixels unclipped foreground pixels of `photos` (indices [P] into its pixels, drawn without replacement)
    and the surface point [P, 3] that a ray through each one (jittered in the pixel) sees on `scene`'s mesh."""
    g = torch.Generator().manual_seed(seed)
    unclipped = (~(photos.colour >= SATURATED).any(-1)).nonzero()[:, 0].cpu()
    idx = unclipped[torch.randperm(len(unclipped), generator=g)[:n_pixels]].to(photos.device)
    rays = photos.rays(idx, 1, torch.Generator(device=photos.device).manual_seed(seed))
    hits = scene.raycaster.intersect(rays.origins, rays.directions)
    ok = hits.valid
    return idx[ok], rays.origins[ok] + hits.t[ok].unsqueeze(-1) * rays.directions[ok]


def candidate_errors(scene: Scene, photos: PhotoSet, idx: torch.Tensor, tonemap: Tonemap, max_bounces: int,
                     seed: int) -> torch.Tensor:
    """[P] each observed pixel idx's squared error (display values, channels averaged) of `scene`'s render, noise
    taken out: the product of the errors of two independent halves of RENDER_SPP path samples (one seed: two
    materials scored with it share their rays and random numbers)."""
    g = torch.Generator(device=photos.device).manual_seed(seed)
    tracer = PathTracer(PathTracerConfig(max_bounces=max_bounces, rr_depth=max(max_bounces, 1), spp=RENDER_SPP))
    rays = photos.rays(idx, RENDER_SPP, g)
    with torch.no_grad():
        samples = tracer.render_rays(scene, rays.origins, rays.directions, g).reshape(-1, RENDER_SPP, 3)
    half = RENDER_SPP // 2
    scale = rays.exposure.unsqueeze(-1)
    a, b = (tonemap.apply(x.mean(1) * scale) - rays.target for x in (samples[:, :half], samples[:, half:]))
    return (a * b).mean(-1)


def family_prototypes(basis: NeuralBasis, seed: int = 0) -> torch.Tensor:
    """[len(FAMILIES), D]: each family's mean latent in `basis` over PROTOTYPE_SAMPLES draws of the prior."""
    g = torch.Generator().manual_seed(seed)
    device = next(basis.parameters()).device
    with torch.no_grad():
        return torch.stack([basis.encode(sample_parameters(f, PROTOTYPE_SAMPLES, g).to(device)).mean(0)
                            for f in FAMILIES])


def cell_index(points: torch.Tensor, low: torch.Tensor, high: torch.Tensor, grid: int = GRID) -> torch.Tensor:
    """[N] int64: the cell of a grid^3 voxel grid over the box [low, high] that each point [N, 3] lies in."""
    ijk = ((points - low) / (high - low).clamp_min(1e-9) * grid).long().clamp(0, grid - 1)
    return (ijk[:, 0] * grid + ijk[:, 1]) * grid + ijk[:, 2]


def appearance_start(basis: NeuralBasis, points: torch.Tensor, rho: torch.Tensor, latent: torch.Tensor,
                     start_at: StartAt, mesh: Mesh, envmap: EnvironmentMap, photos: PhotoSet, tonemap: Tonemap,
                     max_bounces: int = 3, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
    """The start rho [N, 3], latent [N, D] at surface points [N, 3], given the PBR start there (rho, latent) and
    `start_at` (the PBR start at any points): every cell whose photos a family prototype reproduces better by
    CELL_MARGIN takes its latent (see the module docstring); rho_d stays the PBR start's. Returns them and a record:
    appearance_cells (cells with at least MIN_CELL_PIXELS observed pixels), appearance_cells_taken (those that took a
    prototype; appearance_cells_<family> by family), appearance_error_pbr / appearance_error (the observed pixels'
    mean squared display error, noise taken out, of the PBR start / of each cell's choice)."""
    device = points.device
    scene = Scene(mesh, envmap, StartField(basis, start_at), device=device)  # one BVH; each candidate its material
    idx, seen = observed_pixels(scene, photos, seed=seed)
    low = torch.as_tensor(mesh.vertices.min(0), dtype=torch.float32, device=device)
    high = torch.as_tensor(mesh.vertices.max(0), dtype=torch.float32, device=device)
    cells, cell = torch.unique(cell_index(seen, low, high), return_inverse=True)  # observed cells, renumbered
    c = len(cells)

    def per_cell(x: torch.Tensor) -> torch.Tensor:
        return torch.zeros(c, device=device).index_add_(0, cell, x)

    count = per_cell(torch.ones_like(cell, dtype=torch.float32))
    prototypes = family_prototypes(basis, seed)
    scores = []
    for material in [StartField(basis, start_at)] + [StartField(basis, start_at, p) for p in prototypes]:
        scene.material = material
        scores.append(per_cell(candidate_errors(scene, photos, idx, tonemap, max_bounces, seed + 1)))
    errors = torch.stack(scores) / count.clamp_min(1)  # [1 + F, C]
    best_error, best = errors[1:].min(0)
    taken = (best_error < errors[0] - CELL_MARGIN * errors[0].abs()) & (count >= MIN_CELL_PIXELS)  # [C]
    lookup = torch.full((GRID**3,), -1, dtype=torch.long, device=device)
    lookup[cells] = torch.where(taken, best, -1)
    family = lookup[cell_index(points, low, high)]
    use = family >= 0
    latent = latent.clone()
    latent[use] = prototypes[family[use]]
    weights = count / count.sum()
    record = {"appearance_cells": float((count >= MIN_CELL_PIXELS).sum()), "appearance_cells_taken": float(taken.sum()),
              "appearance_error_pbr": float((errors[0] * weights).sum()),
              "appearance_error": float((torch.where(taken, best_error, errors[0]) * weights).sum())}
    for f, name in enumerate(FAMILIES):
        record[f"appearance_cells_{name}"] = float((taken & (best == f)).sum())
    return rho, latent, record
