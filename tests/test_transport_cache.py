"""The cached light transport (render/transport_cache.py) against the path tracer, which stays the reference.

Scene: a smooth torus (concave: light bounces between its sides) in 24 x 24 pixels of preset view 1, under a 64 x 32
map of sky 0.5 (bluer above) and a 2 x 2-texel sun of 200. For each case, K = 24 independent renders of each
estimator (4 camera rays per pixel; the cache with 4 incident directions per hit); the image total over covered
pixels, averaged over the K renders, must agree within 4 combined standard errors (false alarm 6e-5 for a normal
statistic), and per pixel no more than 1% of the z-scores may pass 4. Removing the cosine factor from the cache's
weights (a plain bug) moves the total by far more than that: the test of the test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from neumatex_core.geometry.camera import preset_views
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.field import MaterialField, UniformPBR
from neumatex_core.materials.neural_basis import NeuralMaterial, load_basis
from neumatex_core.render import PathTracer, PathTracerConfig, Scene
from neumatex_core.render.transport_cache import TransportCache, TransportCacheConfig

pytestmark = pytest.mark.usefixtures("one_thread")
RES, SPP, RENDERS, DIRECTIONS = 24, 4, 24, 4


class UniformNeural(MaterialField):
    def __init__(self, rho: tuple[float, float, float], latent: list[float]) -> None:
        self.rho, self.latent = torch.tensor(rho), torch.tensor(latent)

    def at(self, si):  # noqa: ANN001, ANN201
        n = si.position.shape[0]
        return NeuralMaterial(load_basis(), self.rho.expand(n, 3), self.latent.expand(n, 6))


def scene_for(field: MaterialField) -> Scene:
    t = trimesh.creation.torus(0.6, 0.3, 48, 24)
    mesh = Mesh(np.asarray(t.vertices, np.float32), np.asarray(t.faces, np.int64)).with_smooth_normals()
    texels = np.full((32, 64, 3), 0.5, np.float32)
    texels[:16, :, 2] += 1.0
    texels[7:9, 31:33] = 200.0
    return Scene(mesh, EnvironmentMap(texels), field)


def renders(scene: Scene, bounces: int, cached: bool, no_cosine: bool = False) -> torch.Tensor:
    """[RENDERS, covered pixels, 3] independent renders of preset view 1."""
    cam = preset_views(RES)[1]
    mask = render_gbuffer(scene.mesh, cam).mask.reshape(-1)
    tracer = PathTracer(PathTracerConfig(max_bounces=bounces, rr_depth=bounces, spp=SPP))
    out = []
    for seed in range(RENDERS):
        if not cached:
            out.append(tracer.render(scene, cam, seed=seed).reshape(-1, 3)[mask])
            continue
        g = torch.Generator().manual_seed(10_000 + seed)
        o, d, pix = cam.generate_rays(spp=SPP, generator=g)
        cache = TransportCache.build(scene, o, d, g, TransportCacheConfig(directions=DIRECTIONS,
                                                                          indirect_bounces=bounces - 1))
        if no_cosine:
            cache.weight = cache.weight / cache.wi[..., 2:].clamp_min(1e-3)
            cache.lambert_weight = cache.weight.sum(1) / math.pi
        with torch.no_grad():
            radiance = cache.radiance(scene.material)
        out.append((torch.zeros(RES * RES, 3).index_add(0, pix, radiance) / SPP)[mask])
    return torch.stack(out)


def agree(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    """(|difference of the mean totals| in combined standard errors, share of pixels with |z| > 4)."""
    ta, tb = a.sum((1, 2)), b.sum((1, 2))
    z_total = abs(float(ta.mean() - tb.mean())) / math.sqrt(float(ta.var() + tb.var()) / RENDERS)
    z_pixel = (a.mean(0) - b.mean(0)) / torch.sqrt((a.var(0) + b.var(0)) / RENDERS + 1e-12)
    return z_total, float((z_pixel.abs() > 4).float().mean())


@pytest.mark.parametrize("bounces", [1, 3])
@pytest.mark.parametrize("material", ["pbr", "neural"])
def test_cached_transport_has_the_path_tracers_expectation(material: str, bounces: int) -> None:
    field = (UniformPBR((0.7, 0.4, 0.2), 0.3, 0.5) if material == "pbr"
             else UniformNeural((0.6, 0.3, 0.2), [0.3, -0.2, 0.5, 0.1, -0.4, 0.2]))
    scene = scene_for(field)
    z_total, share = agree(renders(scene, bounces, cached=False), renders(scene, bounces, cached=True))
    assert z_total < 4, f"{material}, {bounces} bounces: totals differ by {z_total:.1f} standard errors"
    assert share <= 0.01, f"{material}, {bounces} bounces: {share:.1%} of pixels beyond 4 sigma"


def test_a_wrong_cache_weight_is_caught() -> None:
    scene = scene_for(UniformPBR((0.7, 0.4, 0.2), 0.3, 0.5))
    z_total, _ = agree(renders(scene, 1, cached=False), renders(scene, 1, cached=True, no_cosine=True))
    assert z_total > 8


def test_cached_radiance_is_differentiable_in_the_material() -> None:
    rough = torch.tensor(0.4, requires_grad=True)
    field = UniformPBR((0.7, 0.4, 0.2), rough, 0.5)
    scene = scene_for(field)
    cam = preset_views(RES)[1]
    g = torch.Generator().manual_seed(0)
    o, d, _ = cam.generate_rays(spp=1, generator=g)
    cache = TransportCache.build(scene, o, d, g, TransportCacheConfig(directions=8, indirect_bounces=0))
    cache.radiance(field).sum().backward()
    assert rough.grad is not None and torch.isfinite(rough.grad) and rough.grad.abs() > 0
