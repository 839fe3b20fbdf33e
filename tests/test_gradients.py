"""Autograd gradients of a render with respect to material parameters agree with finite differences.

Scene: suzanne (normalised), 16 x 16 pixels from the first preset view, 2 bounces (no Russian roulette),
courtyard.exr, UniformPBR with base_color [3], roughness and metallic as tensors requiring grad.
Loss: sum of the linear image times a fixed random (normal) weight image. theta = (base_color, roughness,
metallic) = (0.7, 0.5, 0.3, 0.4, 0.3).

Why two tests. The renderer's estimator is "detached" (Zeltner et al. 2021): sample directions, lobe choices
and pdfs are computed from the current parameters but carry no gradient, BSDF values do. With a fixed seed
the image I(theta; xi) is therefore *not* a smooth function of theta: lobe choices (whose probability
depends on base colour and metallic) flip, and GGX directions move with roughness across silhouettes. So
finite differences of one fixed-seed render are not what autograd computes. What autograd computes, per
sample, is the derivative with the samples *and their pdfs* held fixed; its expectation is the derivative of
the expected image, because E[f(theta; x) / p(x; theta0)] = integral f(theta; x) dx for every theta.

1. test_gradient_matches_fd_with_sampling_frozen (exact, per sample): a material field whose materials
   evaluate f at theta but sample and report pdfs at theta0. Its estimator is unbiased for every theta (the
   same integral), it equals the renderer's at theta = theta0, and it is a smooth function of theta with the
   random numbers fixed, so central differences of it must match the autograd gradient for every seed, up to
   FD truncation and float32 rounding (no Monte Carlo error: identical samples on both sides). Tolerance:
   3e-3 of the largest gradient component; the measured worst case is 3e-4 (h = 2e-3). Scaling the
   gradient by 0.99 must be rejected.

2. test_gradient_matches_fd_of_expected_image (statistical, the real renderer): per seed k, g_k (autograd)
   and fd_k = (I(theta + h e_i; xi_k) - I(theta - h e_i; xi_k)) / 2h with common random numbers. Both are
   unbiased for their targets: E[g_k] = d/dtheta E[I], E[fd_k] = central difference of E[I]. Per-seed
   differences d_k = g_k - fd_k are i.i.d.; we require |mean d| < 4 SE(d) (SE from their spread over K = 64
   seeds; ~6e-5 false alarm per component for a normal mean). The FD truncation error is negligible: E[I]
   is a polynomial of degree 2 in base colour and in metallic (f is linear in each, two bounces), where
   central differences are exact, and for roughness (h = 0.05) the truncation, measured on the frozen
   estimator of test 1, averages ~0.1 over seeds (+-0.4 per seed) against an SE of ~1.4. A gradient scaled
   by 0.8 must be rejected by the same statistic (on the blue channel, where the lobe choice barely
   depends on the parameter and the SE is ~0.3% of the gradient).
"""

from __future__ import annotations

import math

import pytest
import torch
from conftest import ENVMAPS, MESHES

from neumatex_core.geometry.camera import preset_views
from neumatex_core.geometry.mesh import load_mesh
from neumatex_core.geometry.surface import SurfaceInteraction
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.field import MaterialField, UniformPBR
from neumatex_core.materials.pbr import PBRMaterial
from neumatex_core.render import PathTracer, PathTracerConfig, Scene

RES = 16
SPP = 16
THETA0 = (0.7, 0.5, 0.3, 0.4, 0.3)  # base colour r, g, b, roughness, metallic
NAMES = ("base_r", "base_g", "base_b", "roughness", "metallic")


class FrozenSamplingMaterial(PBRMaterial):
    """Evaluates f with its own parameters but samples, and reports pdfs, as `reference` does."""

    def __init__(self, material: PBRMaterial, reference: PBRMaterial) -> None:
        super().__init__(material.base_color, material.roughness, material.metallic, material.dielectric_f0)
        self.reference = reference

    def sample(self, wo, u_lobe, u_dir):
        return self.reference.sample(wo, u_lobe, u_dir)

    def pdf(self, wi, wo):
        return self.reference.pdf(wi, wo)

    def select(self, index):
        return FrozenSamplingMaterial(super().select(index), self.reference.select(index))


class FrozenSamplingField(MaterialField):
    def __init__(self, field: UniformPBR, reference: UniformPBR) -> None:
        self.field, self.reference = field, reference

    def at(self, si: SurfaceInteraction) -> PBRMaterial:
        return FrozenSamplingMaterial(self.field.at(si), self.reference.at(si))


@pytest.fixture(scope="module")
def scene_parts():
    mesh = load_mesh(MESHES / "suzanne.obj").normalized()
    env = EnvironmentMap.from_file(ENVMAPS / "courtyard.exr")
    camera = preset_views(RES)[0]
    weight = torch.randn(RES, RES, 3, generator=torch.Generator().manual_seed(0))
    return mesh, env, camera, weight


TRACER = PathTracer(PathTracerConfig(max_bounces=2, rr_depth=100, spp=SPP))


def make_field(theta: torch.Tensor, grad: bool) -> tuple[UniformPBR, tuple[torch.Tensor, ...]]:
    base = theta[:3].float().clone().requires_grad_(grad)
    rough = theta[3].float().clone().requires_grad_(grad)
    metal = theta[4].float().clone().requires_grad_(grad)
    return UniformPBR(base, rough, metal), (base, rough, metal)


def loss(parts, theta: torch.Tensor, seed: int, frozen: bool, grad: bool = False):
    """The loss (float) and, with grad, the autograd gradient [5] (float64) and the parameter tensors."""
    mesh, env, camera, weight = parts
    field, params = make_field(theta, grad)
    if frozen:
        field = FrozenSamplingField(field, make_field(torch.tensor(THETA0, dtype=torch.float64), False)[0])
    with torch.set_grad_enabled(grad):
        value = (TRACER.render(Scene(mesh, env, field), camera, seed=seed) * weight).sum()
    if not grad:
        return float(value)
    value.backward()
    base, rough, metal = params
    return float(value.detach()), torch.cat([base.grad, rough.grad[None], metal.grad[None]]).double(), params


def central_differences(parts, seed: int, steps: tuple[float, ...], frozen: bool) -> torch.Tensor:
    theta0 = torch.tensor(THETA0, dtype=torch.float64)
    fd = torch.zeros(5, dtype=torch.float64)
    for i, h in enumerate(steps):
        e = torch.zeros(5, dtype=torch.float64)
        e[i] = h
        fd[i] = (loss(parts, theta0 + e, seed, frozen) - loss(parts, theta0 - e, seed, frozen)) / (2 * h)
    return fd


def test_backward_populates_material_grads_only(scene_parts) -> None:
    _, env, _, _ = scene_parts
    _, g, params = loss(scene_parts, torch.tensor(THETA0, dtype=torch.float64), 0, frozen=False, grad=True)
    for p in params:
        assert p.grad is not None and torch.isfinite(p.grad).all() and (p.grad != 0).all()
    assert torch.isfinite(g).all()
    # Lighting and geometry are fixed: the map's texels are plain tensors and receive nothing.
    assert not env.texels.requires_grad and env.texels.grad is None


def test_gradient_matches_fd_with_sampling_frozen(scene_parts) -> None:
    theta0 = torch.tensor(THETA0, dtype=torch.float64)
    truncation = []
    for seed in range(4):
        _, g, _ = loss(scene_parts, theta0, seed, frozen=True, grad=True)
        fd = central_differences(scene_parts, seed, (2e-3,) * 5, frozen=True)
        tol = 3e-3 * float(g.abs().max())
        assert float((g - fd).abs().max()) < tol, (seed, g, fd)
        assert float((0.99 * g - fd).abs().max()) > tol  # a 1% wrong gradient is caught
        # Truncation of the roughness step used by the statistical test (h = 0.05), same samples.
        fd_rough = central_differences(scene_parts, seed, (1.0, 1.0, 1.0, 0.05, 1.0), frozen=True)[3]
        truncation.append(float(fd_rough - g[3]))
    # Per seed it is +-0.4 (measured); what biases test 2 is its mean, which must stay far below that
    # test's SE (~1.4 for roughness): < 0.3.
    assert abs(sum(truncation) / len(truncation)) < 0.3, truncation


def test_gradient_matches_fd_of_expected_image(scene_parts) -> None:
    theta0 = torch.tensor(THETA0, dtype=torch.float64)
    seeds = 64
    diffs, diffs_scaled, grads = [], [], []
    for seed in range(1000, 1000 + seeds):
        _, g, _ = loss(scene_parts, theta0, seed, frozen=False, grad=True)
        fd = central_differences(scene_parts, seed, (0.01, 0.01, 0.01, 0.05, 0.05), frozen=False)
        diffs.append(g - fd)
        diffs_scaled.append(0.8 * g - fd)
        grads.append(g)
    d = torch.stack(diffs)
    z = d.mean(0) / (d.std(0) / math.sqrt(seeds))
    assert (z.abs() < 4).all(), dict(zip(NAMES, z.tolist(), strict=True))
    ds = torch.stack(diffs_scaled)
    z_scaled = ds.mean(0) / (ds.std(0) / math.sqrt(seeds))
    assert float(z_scaled[2].abs()) > 4, z_scaled
    # The gradient is informative, not noise: the mean autograd gradient is many SE from zero for every
    # parameter except roughness (small at this point: |g| ~ 2 against a per-seed spread of ~8).
    gs = torch.stack(grads)
    zg = gs.mean(0) / (gs.std(0) / math.sqrt(seeds))
    assert (zg[[0, 1, 2, 4]].abs() > 10).all(), zg
