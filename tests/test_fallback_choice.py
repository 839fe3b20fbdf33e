"""The asset's PBR fallback chosen on held-out photos (neumatex_core/tto/fallback_choice.py): the TTO's PBR phase
replaces the fit to the neural material only where it renders the photos better, the choice is recorded, and the
asset package keeps how its fallback was made."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from neumatex_core.assets import read_asset, write_asset
from neumatex_core.assets.pbr_fit import METHOD, quantize_pbr
from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.fields.uv_textures import PBRTextureField
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.field import MaterialField
from neumatex_core.materials.neural_basis import load_basis
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.tto.config import TTOConfig
from neumatex_core.tto.data import PhotoSet
from neumatex_core.tto.fallback_choice import PBR_PHASE_METHOD, bake_pbr_solution, choose_fallback
from neumatex_core.tto.params import Parametrisation

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

GOLD = torch.tensor([1.0, 0.78, 0.34, 0.3, 1.0])  # base colour, roughness, metallic: a rough gold
CHALK = torch.tensor([0.5, 0.5, 0.5, 0.9, 0.0])  # a rough grey dielectric


class Uniform(Parametrisation):
    """One PBR material everywhere ([5] base colour, roughness, metallic): a PBR phase's solution, as
    `choose_fallback` reads it (gbuffer at points)."""

    def __init__(self, values: torch.Tensor) -> None:
        self.tensor = values

    def field(self) -> MaterialField:
        raise NotImplementedError

    def gbuffer(self, points: torch.Tensor, uv: torch.Tensor | None) -> torch.Tensor:
        return self.tensor.expand(points.shape[0], -1)


@pytest.fixture(scope="module")
def scene(shared_data):
    """A small asset, the studio map, and photos of its mesh in rough gold from three preset views (64 spp)."""
    from asset_fixtures import make_asset, views

    from neumatex_core.geometry.mesh import load_mesh

    mesh = load_mesh(shared_data / "meshes" / "suzanne.obj").normalized()
    asset = make_asset(mesh, load_basis(), resolution=32, steps=20)
    envmap = EnvironmentMap.from_file(shared_data / "envmaps" / "studio.exr")
    cameras = views(32, (0, 6, 12))
    gold = PBRTextureField(quantize_pbr(GOLD.expand(32, 32, 5)))
    tracer = PathTracer(PathTracerConfig(spp=64, max_bounces=2))
    tonemap = Tonemap()
    images = [tonemap.apply(tracer.render(Scene(asset.mesh, envmap, gold), c, seed=k)).numpy()
              for k, c in enumerate(cameras)]  # fmt: skip
    return asset, envmap, PhotoSet(images, cameras, asset.mesh), tonemap


def test_the_pbr_phase_is_baked_to_the_assets_texels_as_its_files_hold_it(scene):
    asset = scene[0]
    texture = bake_pbr_solution(asset, Uniform(GOLD))
    assert texture.shape == asset.pbr_texture.shape
    assert torch.equal(texture, quantize_pbr(GOLD.expand_as(texture)))


def test_the_fallback_that_renders_the_held_out_photos_better_ships(scene, tmp_path):
    asset, envmap, photos, tonemap = scene
    config = TTOConfig.preset("tiny")
    wrong = dataclasses.replace(asset, pbr_texture=quantize_pbr(CHALK.expand_as(asset.pbr_texture)))
    taken = choose_fallback(wrong, Uniform(GOLD), photos, envmap, tonemap, config)
    assert taken.metrics["fallback_from_pbr_phase"] == 1.0
    assert taken.metrics["fallback_psnr_pbr_phase"] > taken.metrics["fallback_psnr_fit"] + 3
    assert torch.equal(taken.pbr_texture, bake_pbr_solution(asset, Uniform(GOLD)))
    assert taken.pbr_method == PBR_PHASE_METHOD and taken.pbr_fit_loss == wrong.pbr_fit_loss  # the fit's loss
    assert wrong.pbr_method == METHOD and "fallback_from_pbr_phase" not in wrong.metrics  # the input is untouched

    right = dataclasses.replace(asset, pbr_texture=quantize_pbr(GOLD.expand_as(asset.pbr_texture)))
    kept = choose_fallback(right, Uniform(CHALK), photos, envmap, tonemap, config)
    assert kept.metrics["fallback_from_pbr_phase"] == 0.0
    assert torch.equal(kept.pbr_texture, right.pbr_texture) and kept.pbr_method == METHOD
    assert kept.pbr_fit_loss == right.pbr_fit_loss
    # the same two textures score the same whichever side each is on (one seed for both)
    assert kept.metrics["fallback_psnr_fit"] == taken.metrics["fallback_psnr_pbr_phase"]
    # a margin the PBR phase does not clear keeps the fit
    margin = taken.metrics["fallback_psnr_pbr_phase"] - taken.metrics["fallback_psnr_fit"] + 0.01
    assert choose_fallback(wrong, Uniform(GOLD), photos, envmap, tonemap, config, margin).pbr_method == METHOD

    # the package keeps how its fallback was made
    write_asset(taken, tmp_path / "asset")
    again = read_asset(tmp_path / "asset")
    assert again.pbr_method == PBR_PHASE_METHOD and again.pbr_fit_loss == taken.pbr_fit_loss
    assert torch.equal(again.pbr_texture, taken.pbr_texture)
    assert again.metrics["fallback_from_pbr_phase"] == 1.0
