"""Our torch path tracer agrees with Mitsuba 3 on shared scenes, within Monte Carlo noise.

Both renderers draw B independent batches of each image; per pixel we get means a, b and standard errors
s_a, s_b from the batch spread. Two statistics, both derived from that noise and nothing else:

- Global bias: D = mean over pixels of (a - b). Pixels are independent, so Var(D) = sum(s_a^2 + s_b^2) / N^2;
  an unbiased pair of renderers gives |D| / SE(D) ~ |N(0, 1)|. We require < 4.5 (false alarm ~7e-6 per test).
- Per-pixel: z = (a - b) / sqrt(s_a^2 + s_b^2). With B = 8 batches each, z is close to Student-t with ~14
  degrees of freedom: P(|z| > 6) ~ 3e-5, so more than 0.5% of pixels beyond 6 means a local disagreement
  (over a 32x32x3 image, ~0.1 such values are expected by chance; 0.5% is 15).

Deliberately wrong renderers (an environment pdf without the sin(theta) Jacobian; MIS weights dropped so light
and BSDF sampling both count fully) must fail the same statistics, so the test can fail.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import ENVMAPS, MESHES

pytest.importorskip("mitsuba", reason="Mitsuba 3 (dev dependency) is the reference renderer")

from mitsuba_reference import render_mitsuba_batches, shading_normal_backfacing_mask  # noqa: E402

from neumatex_core.geometry.camera import preset_views  # noqa: E402
from neumatex_core.geometry.mesh import Mesh, load_mesh  # noqa: E402
from neumatex_core.lighting.envmap import EnvironmentMap  # noqa: E402
from neumatex_core.materials.field import UniformPBR  # noqa: E402
from neumatex_core.render import PathTracer, PathTracerConfig, Scene  # noqa: E402

RES = 32
BATCHES = 8
SPP = 32
GLOBAL_SIGMAS = 4.5
PIXEL_Z = 6.0
PIXEL_FRACTION = 0.005

MATERIALS = {
    # Ours: dielectric_f0 = 0 switches the GGX lobe off (UE4 Fresnel), a pure Lambertian surface.
    "diffuse": (
        UniformPBR((0.8, 0.5, 0.2), 0.5, 0.0, dielectric_f0=0.0),
        {"kind": "diffuse", "base_color": (0.8, 0.5, 0.2)},
    ),
    # Metallic 1 with white base colour: F = 1, a white rough GGX conductor (alpha = 0.5^2).
    "rough_specular": (UniformPBR((1.0, 1.0, 1.0), 0.5, 1.0), {"kind": "conductor", "roughness": 0.5}),
}


@pytest.fixture(scope="module")
def suzanne() -> Mesh:
    return load_mesh(MESHES / "suzanne.obj").normalized()


@pytest.fixture(scope="module")
def courtyard() -> EnvironmentMap:
    return EnvironmentMap.from_file(ENVMAPS / "courtyard.exr")


def render_ours_batches(scene: Scene, camera, bounces: int, tracer: PathTracer | None = None, seed: int = 1000):
    tracer = tracer or PathTracer(PathTracerConfig(max_bounces=bounces, rr_depth=100, spp=SPP))
    batches = np.stack([tracer.render(scene, camera, seed=seed + k).numpy() for k in range(BATCHES)]).astype(np.float64)
    return batches.mean(0), batches.std(0, ddof=1) / math.sqrt(BATCHES)


def agreement(ours: tuple[np.ndarray, np.ndarray], ref: tuple[np.ndarray, np.ndarray], keep: np.ndarray) -> dict:
    """Global bias in standard errors and the fraction of pixel values beyond PIXEL_Z, over `keep` pixels."""
    (a, sa), (b, sb) = ours, ref
    a, sa, b, sb = (x[keep] for x in (a, sa, b, sb))
    var = sa.astype(np.float64) ** 2 + sb.astype(np.float64) ** 2
    diff = a - b
    bias_sigmas = abs(diff.mean()) / (math.sqrt(var.sum()) / diff.size)
    z = diff / np.sqrt(np.maximum(var, 1e-20))
    return {
        "bias_sigmas": float(bias_sigmas),
        "outlier_fraction": float((np.abs(z) > PIXEL_Z).mean()),
        "relative_bias": float(diff.mean() / max(b.mean(), 1e-12)),
    }


def agrees(stats: dict) -> bool:
    return stats["bias_sigmas"] < GLOBAL_SIGMAS and stats["outlier_fraction"] < PIXEL_FRACTION


@pytest.mark.parametrize("bounces", [1, 3])
@pytest.mark.parametrize("material", sorted(MATERIALS))
def test_agrees_with_mitsuba_flat_shading(suzanne: Mesh, courtyard: EnvironmentMap, material: str, bounces: int):
    mesh = suzanne.flat()
    field, mi_material = MATERIALS[material]
    camera = preset_views(RES)[2]
    scene = Scene(mesh, courtyard, field)
    ours = render_ours_batches(scene, camera, bounces)
    ref = render_mitsuba_batches(mesh, courtyard, camera, mi_material, bounces, BATCHES, SPP, seed=7)
    stats = agreement(ours, ref, np.ones((RES, RES), bool))
    assert agrees(stats), stats


def test_agrees_with_mitsuba_smooth_shading(suzanne: Mesh, courtyard: EnvironmentMap):
    """Smooth normals, direct lighting; pixels where the shading normal faces away are excluded (documented
    behaviour difference, see geometry/surface.py and tests/mitsuba_reference.py)."""
    field, mi_material = MATERIALS["rough_specular"]
    camera = preset_views(RES)[5]
    scene = Scene(suzanne, courtyard, field)
    keep = ~shading_normal_backfacing_mask(suzanne, camera)
    ours = render_ours_batches(scene, camera, 1)
    ref = render_mitsuba_batches(suzanne, courtyard, camera, mi_material, 1, BATCHES, SPP, seed=7)
    stats = agreement(ours, ref, keep)
    assert agrees(stats), stats


class EnvmapWithoutJacobian(EnvironmentMap):
    """A classic bug: the light pdf in (u, v) space, forgetting the 1 / (2 pi^2 sin theta) Jacobian."""

    def _pdf_uv(self, uv: torch.Tensor) -> torch.Tensor:
        return super()._pdf_uv(uv) * torch.sin(math.pi * uv[:, 1]) * (2 * math.pi**2)


def test_wrong_pdf_or_missing_mis_weight_fails(suzanne: Mesh, courtyard: EnvironmentMap):
    mesh = suzanne.flat()
    field, mi_material = MATERIALS["diffuse"]
    camera = preset_views(RES)[2]
    ref = render_mitsuba_batches(mesh, courtyard, camera, mi_material, 1, BATCHES, SPP, seed=7)
    keep = np.ones((RES, RES), bool)

    correct = agreement(render_ours_batches(Scene(mesh, courtyard, field), camera, 1), ref, keep)
    assert agrees(correct), correct

    wrong_env = EnvmapWithoutJacobian(courtyard.texels.numpy())
    wrong_pdf = agreement(render_ours_batches(Scene(mesh, wrong_env, field), camera, 1), ref, keep)
    assert not agrees(wrong_pdf), wrong_pdf

    no_mis = PathTracer(PathTracerConfig(max_bounces=1, rr_depth=100, spp=SPP))
    no_mis.mis_weight = lambda pdf_a, pdf_b: torch.ones_like(pdf_a)
    missing_weight = agreement(render_ours_batches(Scene(mesh, courtyard, field), camera, 1, no_mis), ref, keep)
    assert not agrees(missing_weight), missing_weight
