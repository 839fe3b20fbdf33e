"""The neural start chosen by appearance (tto/appearance_start.py): its score of a candidate without the render's
noise, and the cells' choice of a family prototype where the photos show one, not where they show the start."""

from __future__ import annotations

import math

import pytest
import torch
from tto_fixtures import Example, load_example

from neumatex_core.materials.prior import FAMILIES
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.tto.appearance_start import (
    RENDER_SPP,
    StartAt,
    StartField,
    appearance_start,
    candidate_errors,
    family_prototypes,
    observed_pixels,
)
from neumatex_core.tto.data import PhotoSet

VIEWS = (0, 4, 8, 12, 17, 19)


@pytest.fixture(scope="module")
def example() -> Example:
    return load_example()


RHO = torch.tensor([0.55, 0.35, 0.25])


def uniform(latent: torch.Tensor) -> StartAt:
    """A start with rho_d RHO and `latent` [D] all over."""
    return lambda q: (RHO.expand(q.shape[0], 3).clone(), latent.expand(q.shape[0], -1).clone())


def test_candidate_error_takes_the_renders_noise_out(example):
    """`candidate_errors` on photos rendered at 256 spp: the material that made them scores zero within 4 standard
    errors (over pixels), where the plain squared error of the same 16-sample renders does not; a prototype of
    another family scores clearly above zero."""
    basis = example.basis
    prototypes = family_prototypes(basis)
    truth = prototypes[FAMILIES.index("dusty")]
    photos = _photos_of(example, truth, views=(0, 8), spp=256)
    start_at = uniform(truth)
    scene = Scene(example.mesh, example.envmap, StartField(basis, start_at))
    idx, _ = observed_pixels(scene, photos, n_pixels=2048)
    tonemap = example.capture.tonemap
    own = candidate_errors(scene, photos, idx, tonemap, 3, 5)
    scene.material = StartField(basis, start_at, prototypes[FAMILIES.index("metal")])
    other = candidate_errors(scene, photos, idx, tonemap, 3, 5)
    se = float(own.std()) / math.sqrt(len(own))
    assert abs(float(own.mean())) < 4 * se, (float(own.mean()), se)
    assert float(other.mean()) > 10 * se + 4 * float(other.std()) / math.sqrt(len(other)), float(other.mean())
    g = torch.Generator().manual_seed(5)
    rays = photos.rays(idx, RENDER_SPP, g)
    tracer = PathTracer(PathTracerConfig(max_bounces=3, spp=RENDER_SPP))
    with torch.no_grad():
        scene.material = StartField(basis, start_at)
        plain = tracer.render_rays(scene, rays.origins, rays.directions, g).reshape(-1, RENDER_SPP, 3).mean(1)
    l2 = ((example.capture.tonemap.apply(plain) - rays.target) ** 2).mean(-1)
    assert float(l2.mean()) > 8 * se, (float(l2.mean()), se)


def _photos_of(example: Example, latent: torch.Tensor, views: tuple[int, ...] = VIEWS, spp: int = 32) -> PhotoSet:
    """The example's `views` rendered (3 bounces, spp samples) with rho_d RHO and `latent` all over."""
    scene = Scene(example.mesh, example.envmap, StartField(example.basis, uniform(latent)))
    tracer = PathTracer(PathTracerConfig(max_bounces=3, spp=spp))
    cams = [example.photos.cameras[v] for v in views]
    tonemap = example.capture.tonemap
    with torch.no_grad():
        images = [tonemap.apply(tracer.render(scene, cam, seed=v)).numpy() for cam, v in zip(cams, views, strict=True)]
    return PhotoSet(images, cams, example.mesh, [example.capture.load_mask(v) for v in views])


@pytest.mark.parametrize("shown", ["dusty", "plastic"])
def test_cells_take_the_family_the_photos_show_and_keep_a_start_they_show(example, shown):
    """Photos of a dusty teapot, and a start that is the plastic prototype (a PBR solution's kind): most observed
    cells take a prototype, the start's latents at surface points move at least halfway (in squared error) to the
    truth, the base colour stays the start's, and the photos' error falls. Photos of the plastic start itself: fewer
    than a quarter of the cells leave it, and fewer than a quarter of the points."""
    basis = example.basis
    prototypes = family_prototypes(basis)
    start_latent, truth = prototypes[FAMILIES.index("plastic")], prototypes[FAMILIES.index(shown)]
    photos = _photos_of(example, truth)
    points, _ = example.mesh.sample_surface(4096, seed=3)

    start_at = uniform(start_latent)
    rho, latent = start_at(points)
    new_rho, new_latent, record = appearance_start(basis, points, rho, latent, start_at, example.mesh,
                                                   example.envmap, photos, example.capture.tonemap)  # fmt: skip
    error = float(((new_latent - truth) ** 2).mean())
    start_error = float(((latent - truth) ** 2).mean())
    taken = record["appearance_cells_taken"] / record["appearance_cells"]
    assert torch.equal(new_rho, rho)
    if shown == "dusty":
        assert taken > 0.5, record
        assert error < 0.5 * start_error, (error, start_error)
        assert record["appearance_error"] < record["appearance_error_pbr"], record
    else:
        assert taken < 0.25, record
        moved = (new_latent != latent).any(-1).float().mean()
        assert float(moved) < 0.25, (float(moved), record)
