"""Whether a material's base colour follows the capture's light (docs/design-notes.md item 75).

Under one lighting a diffuse photo shows base colour x irradiance, so a base colour free to vary over the surface
(the "textured" candidate of `select_uniform`) can paint the capture's light into itself: brighter where the map
lights the surface more. Held-out photos under the same map cannot see that (the light is the same in every view);
relit under another map it is wrong. The renderer knows the irradiance (the mesh and the map are given), so the part
of the textured candidate's base colour that the uniform candidate does not have can be regressed on it: a slope
near 0 is pattern, a slope near 1 is light baked in (the base colour scales with the irradiance).

`light_following` measures it at surface points; `_solve_selecting` (tto/pbr_start.py) records it in the choice's
selection.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from neumatex_core.geometry.mesh import Mesh
from neumatex_core.geometry.raycast import RayCaster
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.base import luminance

SHADOW_EPS = 1e-4  # ray origin offset along the normal, in scene units (the meshes are about unit size)


def shading(mesh: Mesh, envmap: EnvironmentMap, points: torch.Tensor, normals: torch.Tensor, samples: int = 64,
            seed: int = 0) -> torch.Tensor:
    """[N] luminance of the direct light a white Lambertian surface reflects at points [N, 3] with unit normals
    [N, 3] (irradiance / pi, shadowed by the mesh itself): `samples` directions per point drawn from the map's own
    importance sampling (its sun included), each counted where above the surface and not blocked. Deterministic in
    seed (a private generator: the caller's random numbers are untouched)."""
    g = torch.Generator().manual_seed(seed)
    n = points.shape[0]
    env = envmap.to("cpu")
    directions, pdf, radiance = env.sample(torch.rand(n * samples, 2, generator=g))
    p = points.cpu().repeat_interleave(samples, 0)
    nrm = normals.cpu().repeat_interleave(samples, 0)
    cos = (directions * nrm).sum(-1)
    above = cos > 0
    blocked = torch.zeros_like(above)
    if bool(above.any()):
        blocked[above] = RayCaster(mesh).occluded(p[above] + SHADOW_EPS * nrm[above], directions[above])
    lum = luminance(radiance)
    contrib = torch.where(above & ~blocked, lum * cos.clamp_min(0) / (torch.pi * pdf.clamp_min(1e-12)),
                          torch.zeros_like(lum))
    return contrib.view(n, samples).mean(1)


def light_following(textured: Callable[[torch.Tensor], torch.Tensor], uniform: Callable[[torch.Tensor], torch.Tensor],
                    mesh: Mesh, envmap: EnvironmentMap, device: torch.device, points: int = 4096,
                    seed: int = 0) -> dict[str, float]:
    """How the textured candidate's base colour differs from the uniform one's along the capture's light.

    textured / uniform: G-buffers [N, 9] (rho_d first) of the two candidates at points [N, 3] on `device`. With y
    the log luminance ratio of their base colours and x the log shading (`shading`) at `points` surface points
    (`Mesh.sample_surface_normals`), over the points the map lights at all: `light_slope` cov(x, y) / var(x) (1:
    the textured base colour's extra variation scales with the light; 0: none of it does), `light_correlation`
    corr(x, y), and `texture_spread` std(y), how far the textured base colour departs from the uniform one at all
    (log units)."""
    p, nrm = mesh.sample_surface_normals(points, seed)
    s = shading(mesh, envmap, p, nrm, seed=seed)
    device_points = p.to(device)
    with torch.no_grad():
        y = (torch.log(luminance(textured(device_points)[:, :3]) + 1e-3)
             - torch.log(luminance(uniform(device_points)[:, :3]) + 1e-3)).double().cpu()
    lit = s > 1e-4 * float(s.max().clamp_min(1e-12))
    x = torch.log(s[lit].double())
    y = y[lit]
    if x.numel() < 16 or float(x.std()) < 1e-6:
        spread = float(y.std(unbiased=False)) if y.numel() > 1 else 0.0
        return {"light_slope": 0.0, "light_correlation": 0.0, "texture_spread": spread}
    xc, yc = x - x.mean(), y - y.mean()
    cov = float((xc * yc).mean())
    return {"light_slope": cov / float((xc * xc).mean()),
            "light_correlation": cov / max(float(xc.std(unbiased=False) * yc.std(unbiased=False)), 1e-12),
            "texture_spread": float(y.std(unbiased=False))}

