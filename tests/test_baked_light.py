"""tto/baked_light.py: the slope of a textured base colour's extra variation on the capture's light."""

from __future__ import annotations

import torch

from neumatex_core.geometry.mesh import load_mesh
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.tto.baked_light import light_following, shading
from tests.conftest import ENVMAPS, MESHES

N = 2048


def _scene():
    return load_mesh(MESHES / "teapot.obj").normalized(), EnvironmentMap.from_file(ENVMAPS / "courtyard.exr")


def _gbuffer(rho: torch.Tensor):
    """A G-buffer function [N, 9] returning rho [N] as a grey base colour at the N points light_following draws."""
    def gbuffer(points: torch.Tensor) -> torch.Tensor:
        assert points.shape[0] == rho.shape[0]
        return torch.cat([rho[:, None].expand(-1, 3), torch.zeros(rho.shape[0], 6)], dim=1)
    return gbuffer


def test_shading_is_shadowed_and_deterministic():
    mesh, env = _scene()
    points, normals = mesh.sample_surface_normals(N, seed=3)
    assert torch.allclose(normals.norm(dim=1), torch.ones(N), atol=1e-5)
    s = shading(mesh, env, points, normals, seed=3)
    assert torch.equal(s, shading(mesh, env, points, normals, seed=3))
    assert bool((s >= 0).all()) and float(s.mean()) > 0
    # facing up against facing down under an outdoor map: the sky and sun come from above
    up, down = normals[:, 1] > 0.8, normals[:, 1] < -0.8
    assert float(s[up].mean()) > 2 * float(s[down].mean())


def test_light_painted_in_has_slope_one_and_a_pattern_slope_zero():
    mesh, env = _scene()
    points, normals = mesh.sample_surface_normals(N, seed=0)
    s = shading(mesh, env, points, normals, seed=0)
    uniform = torch.full((N,), 0.5)
    # the capture's light painted into the base colour: rho proportional to the shading (the same estimate)
    baked = light_following(_gbuffer(0.5 * s / s.mean()), _gbuffer(uniform), mesh, env, torch.device("cpu"),
                            points=N, seed=0)
    lit = s > 1e-4 * s.max()
    assert float(lit.float().mean()) > 0.5
    # log(rho + 1e-3) bends the slope below 1 only where rho is tiny
    assert 0.9 < baked["light_slope"] <= 1.001 and baked["light_correlation"] > 0.95
    # a pattern that does not know the light: independent random per-point factors, slope 0 within its noise
    pattern = 0.5 * torch.exp(0.3 * torch.randn(N, generator=torch.Generator().manual_seed(1)))
    free = light_following(_gbuffer(pattern), _gbuffer(uniform), mesh, env, torch.device("cpu"), points=N, seed=0)
    x = torch.log(s[lit])
    # slope's standard error: std(y) / (std(x) sqrt(n)), with std(y) = 0.3
    se = 0.3 / (float(x.std()) * float(lit.sum()) ** 0.5)
    assert abs(free["light_slope"]) < 4 * se and abs(free["texture_spread"] - 0.3) < 0.03
    same = light_following(_gbuffer(uniform), _gbuffer(uniform), mesh, env, torch.device("cpu"), points=N, seed=0)
    assert same == {"light_slope": 0.0, "light_correlation": 0.0, "texture_spread": 0.0}
