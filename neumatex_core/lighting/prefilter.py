"""Pre-filtered environment lighting: what a diffuse or a glossy surface would see, as cheap per-pixel cues.

`PrefilteredLighting(envmap)` convolves the map once with a clamped-cosine kernel (diffuse irradiance over pi)
and with von Mises-Fisher lobes of a few widths (glossy reflections), on a coarse direction grid, and then answers
lookups for any directions. The LMRM reads these next to the photos so that it can tell the material from the
lighting; nothing here is used to render (the path tracer integrates the map exactly).

Kernels, for a unit direction d and a map direction t (solid angle dw_t):
- diffuse:  E(d) / pi = sum_t L(t) max(0, d.t) dw_t / pi  (the radiance of a white Lambertian surface, normal d);
- glossy k: sum_t L(t) exp(kappa_k (d.t - 1)) dw_t / sum_t exp(kappa_k (d.t - 1)) dw_t  (a normalised lobe blur).
"""

from __future__ import annotations

import math

import torch

from neumatex_core.lighting.envmap import EnvironmentMap

KAPPAS = (400.0, 60.0, 10.0)  # lobe sharpness, roughly GGX roughness 0.15, 0.35, 0.65 at the reflection direction


def _grid_directions(envmap: EnvironmentMap, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions [H*2H, 3] at texel centres of an equirect grid and their solid angles [H*2H]."""
    width = 2 * height
    jj, ii = torch.meshgrid(torch.arange(height, device=envmap.device), torch.arange(width, device=envmap.device),
                            indexing="ij")  # fmt: skip
    uv = torch.stack([(ii + 0.5) / width, (jj + 0.5) / height], dim=-1).reshape(-1, 2).float()
    theta = math.pi * uv[:, 1]
    solid_angle = torch.sin(theta) * (2 * math.pi / width) * (math.pi / height)
    return envmap.uv_to_direction(uv), solid_angle


class PrefilteredLighting:
    """Diffuse and glossy convolutions of an environment map on a [grid, 2 grid] direction grid."""

    def __init__(self, envmap: EnvironmentMap, grid: int = 32, source: int = 64) -> None:
        self.envmap = envmap
        self.grid = grid
        src_dirs, src_sa = _grid_directions(envmap, source)
        # Source radiance: the mean of 4x4 lookups per coarse texel, so small bright suns are not missed.
        radiance = torch.zeros_like(src_dirs)
        width = 2 * source
        jj, ii = torch.meshgrid(torch.arange(source, device=envmap.device), torch.arange(width, device=envmap.device),
                                indexing="ij")  # fmt: skip
        for du in (0.125, 0.375, 0.625, 0.875):
            for dv in (0.125, 0.375, 0.625, 0.875):
                uv = torch.stack([(ii + du) / width, (jj + dv) / source], dim=-1).reshape(-1, 2).float()
                radiance += envmap.lookup_uv(uv) / 16
        out_dirs, _ = _grid_directions(envmap, grid)
        cos = out_dirs @ src_dirs.T  # [G, S]
        weighted = radiance * src_sa.unsqueeze(-1)
        maps = [(cos.clamp_min(0) @ weighted) / math.pi]
        for kappa in KAPPAS:
            w = torch.exp(kappa * (cos - 1)) * src_sa
            maps.append((w @ radiance) / w.sum(-1, keepdim=True).clamp_min(1e-30))
        self.maps = [m.reshape(grid, 2 * grid, 3) for m in maps]  # diffuse, then glossy by KAPPAS

    def _lookup(self, index: int, directions: torch.Tensor) -> torch.Tensor:
        uv = self.envmap.direction_to_uv(directions)
        texels = self.maps[index]
        h, w = texels.shape[:2]
        x = (uv[:, 0] * w - 0.5) % w
        y = (uv[:, 1] * h - 0.5).clamp(0, h - 1)
        x0 = x.floor().long() % w
        y0 = y.floor().long().clamp(0, h - 2)
        fx, fy = (x - x.floor()).unsqueeze(-1), (y - y0).clamp(0, 1).unsqueeze(-1)
        x1 = (x0 + 1) % w
        top = texels[y0, x0] * (1 - fx) + texels[y0, x1] * fx
        bottom = texels[y0 + 1, x0] * (1 - fx) + texels[y0 + 1, x1] * fx
        return top * (1 - fy) + bottom * fy

    def diffuse(self, normals: torch.Tensor) -> torch.Tensor:
        """[N, 3] radiance of a white Lambertian surface with unit normals [N, 3] (no occlusion)."""
        return self._lookup(0, normals)

    def glossy(self, directions: torch.Tensor) -> torch.Tensor:
        """[N, len(KAPPAS), 3] blurred radiance around unit directions [N, 3] (e.g. mirror reflections)."""
        return torch.stack([self._lookup(1 + k, directions) for k in range(len(KAPPAS))], dim=1)
