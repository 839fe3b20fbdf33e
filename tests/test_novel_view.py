"""Preset views from arbitrary photos: identity on preset photos, and a diffuse object's radiance carried over."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from neumatex_core.geometry.camera import camera_from_fov, look_at, preset_views
from neumatex_core.geometry.mesh import Mesh, load_mesh
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.field import UniformPBR
from neumatex_core.novel_view import Photo, blend_views
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene

RES = 32


@pytest.fixture(scope="module")
def suzanne(shared_data) -> Mesh:  # type: ignore[no-untyped-def]
    return load_mesh(shared_data / "meshes" / "suzanne.obj").normalized()


def _position_image(mesh: Mesh, cam) -> np.ndarray:  # type: ignore[no-untyped-def]
    """A view-independent 'photo': the world position of what each pixel sees (smooth, exactly known)."""
    from neumatex_core.geometry.gbuffer import render_gbuffer

    gb = render_gbuffer(mesh, cam)
    return (gb.position * 0.5 + 0.5).numpy() * gb.mask.unsqueeze(-1).numpy()


def test_photos_at_the_preset_poses_come_out_unchanged(suzanne: Mesh) -> None:
    cams = preset_views(RES)[:5]
    photos = [Photo(_position_image(suzanne, c), c) for c in cams]
    out = blend_views(suzanne, photos, cams, k=3)
    for v in range(len(cams)):
        ok = out.observed[v]
        assert float(ok.float().mean()) > 0.2
        assert torch.allclose(out.images[v][ok], torch.as_tensor(photos[v].image)[ok], atol=1e-3)


def test_view_independent_content_is_reprojected(suzanne: Mesh) -> None:
    """Photos from 24 random poses of a view-independent signal (the surface position): blended into the preset
    views it matches the truth wherever observed, up to bilinear resampling (a 1/RES-scale error)."""
    g = np.random.default_rng(0)
    photos = []
    for _ in range(24):
        d = g.normal(size=3)
        d /= np.linalg.norm(d)
        cam = camera_from_fov(look_at(3.0 * d, np.zeros(3), np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9
                                      else np.array([1.0, 0.0, 0.0])), 48, 48, 45)  # fmt: skip
        photos.append(Photo(_position_image(suzanne, cam), cam))
    cams = preset_views(RES)[:17:4]
    out = blend_views(suzanne, photos, cams)
    errors = []
    for v, cam in enumerate(cams):
        truth = torch.as_tensor(_position_image(suzanne, cam))
        ok = out.observed[v]
        assert float(ok.float().sum()) > 0.8 * float(out.mask[v].float().sum())
        errors.append((out.images[v][ok] - truth[ok]).abs().median())
    assert float(torch.stack(errors).max()) < 0.02  # 1 - 2 photo pixels of a [0, 1] gradient across ~40 pixels


def test_diffuse_render_is_reprojected_within_noise(suzanne: Mesh) -> None:
    """A Lambertian object under a constant map looks the same from everywhere: blended photos agree with a
    direct render of the preset view within the Monte Carlo noise of both (z-test on the mean difference)."""
    env = EnvironmentMap.constant((1.0, 1.0, 1.0))
    scene = Scene(suzanne, env, UniformPBR((0.6, 0.6, 0.6), 0.8, 0.0, dielectric_f0=0.0))
    tracer = PathTracer(PathTracerConfig(max_bounces=2, spp=64))
    photo_cams = preset_views(48)[:17]
    with torch.no_grad():
        photos = [Photo(tracer.render(scene, c, seed=i).numpy(), c) for i, c in enumerate(photo_cams[::2])]
        target_cam = preset_views(RES)[1]
        direct = tracer.render(scene, target_cam, seed=100)
    out = blend_views(suzanne, photos, [target_cam])
    ok = out.observed[0]
    diff = (out.images[0][ok] - direct[ok]).mean(-1)
    z = float(diff.mean()) / (float(diff.std()) / math.sqrt(diff.numel()))
    assert abs(z) < 4, z
