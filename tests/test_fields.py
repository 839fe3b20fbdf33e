"""Material fields: triplane sampling conventions, decoder ranges and ids, UV lookups, and gradients from a render
reaching the triplane and the UV textures (what TTO optimises)."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import torch

from neumatex_core.fields import (
    MaterialDecoder,
    PBRDecoder,
    PBRTextureField,
    Triplane,
    TriplaneMaterialField,
    UncertaintyDecoder,
    UVTextureField,
    module_id,
    sample_uv,
)
from neumatex_core.fields.fit import fit_triplane
from neumatex_core.geometry.mesh import Mesh, icosphere
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.field import MaterialField
from neumatex_core.materials.neural_basis import load_basis
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.render.views import sphere_camera

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def basis():
    return load_basis()


def test_triplane_reads_each_plane_at_its_own_coordinates():
    tp = Triplane(channels=2, resolution=4, init_std=0.0)
    with torch.no_grad():
        cols = torch.arange(4.0).view(1, 4).expand(4, 4)  # value = column index (first coordinate)
        rows = torch.arange(4.0).view(4, 1).expand(4, 4)  # value = row index (second coordinate)
        for k in range(3):
            tp.planes[k, 0] = cols + 10 * k
            tp.planes[k, 1] = rows + 10 * k
    # texel centres of a 4-texel axis over [-1, 1] (align_corners=False) are at -0.75, -0.25, 0.25, 0.75
    p = torch.tensor([[-0.75, 0.25, 0.75]])  # x -> col 0, y -> index 2, z -> index 3
    f = tp.features(p)
    assert f.shape == (1, 6)
    # XY: (x, y) -> (col 0, row 2); YZ: (y, z) -> (col 2, row 3); XZ: (x, z) -> (col 0, row 3)
    assert torch.allclose(f[0], torch.tensor([0.0, 2.0, 12.0, 13.0, 20.0, 23.0]))
    # outside the cube reads the border texels
    assert torch.allclose(tp.features(torch.tensor([[-5.0, 0.25, 0.75]])), f)


def test_triplane_from_planes_copies_and_checks_shape():
    planes = torch.randn(3, 5, 8, 8)
    tp = Triplane.from_planes(planes)
    assert tp.feature_dim == 15 and tp.resolution == 8 and torch.equal(tp.planes.data, planes)
    with pytest.raises(ValueError, match=r"\[3, C, R, R\]"):
        Triplane.from_planes(torch.randn(2, 5, 8, 8))


def test_decoders_ranges_shapes_and_ids():
    torch.manual_seed(0)
    feats = torch.randn(256, 24) * 5
    rho, lat = MaterialDecoder(24)(feats)
    assert rho.shape == (256, 3) and lat.shape == (256, 6)
    assert rho.min() >= 0 and rho.max() <= 1 and lat.min() >= -1 and lat.max() <= 1
    assert UncertaintyDecoder(24)(feats).shape == (256, 9)
    with torch.no_grad():
        base, rough, metal = PBRDecoder(24)(feats)
    assert base.shape == (256, 3) and rough.shape == metal.shape == (256,)
    assert all(float(t.min()) >= 0 and float(t.max()) <= 1 for t in (base, rough, metal))
    dec = MaterialDecoder(24)
    same = MaterialDecoder(**dec.architecture())
    same.load_state_dict(dec.state_dict())
    assert module_id(dec) == module_id(same) and module_id(dec).startswith("material-")
    with torch.no_grad():
        same.net[0].bias[0] += 1e-6
    assert module_id(dec) != module_id(same)


def test_a_material_decoder_is_resized_for_a_basis_of_another_latent_size():
    """`with_latent_dim`: rho_d and the first latent numbers are the decoder's own, the added ones come from a fixed
    seed (the same copy every time: the PBR start is fitted through one and the TTO reads another), the shrunk copy
    keeps the first ones, and the record's architecture rebuilds it (docs/design-notes.md item 78)."""
    torch.manual_seed(0)
    feats = torch.randn(64, 24)
    dec = MaterialDecoder(24)
    rho, lat = dec(feats)
    wide, again = dec.with_latent_dim(16), dec.with_latent_dim(16)
    rho_w, lat_w = wide(feats)

    def same(a: torch.Tensor, b: torch.Tensor) -> bool:  # up to float rounding: a wider output layer's matmul may
        # sum in another order on some CPUs (about 6e-8 on AMD EPYC, 0 elsewhere)
        return torch.allclose(a, b, rtol=0.0, atol=1e-6)
    assert lat_w.shape == (64, 16) and same(rho_w, rho) and same(lat_w[:, :6], lat)
    other_seed = dec.with_latent_dim(16, seed=1)(feats)[1]
    assert torch.equal(lat_w, again(feats)[1]) and not torch.equal(lat_w[:, 6:], other_seed[:, 6:])
    assert lat_w[:, 6:].std() > 0.05  # the added rows are a fresh layer's, not silent: the fit can move them
    assert same(dec.with_latent_dim(4)(feats)[1], lat[:, :4])
    rebuilt = MaterialDecoder(**wide.architecture())
    rebuilt.load_state_dict(wide.state_dict())
    assert wide.architecture()["latent_dim"] == 16 and "latent_dim" not in dec.architecture()
    assert module_id(rebuilt) == module_id(wide)


def test_resized_decoder_copies_made_in_threads_are_the_same():
    """The TTO's candidates make their decoder copies side by side (`side_by_side`): every copy made in threads is
    the one made alone, and the added rows are a fresh nn.Linear's after torch.manual_seed(seed), as they were when
    the copy seeded torch's global generator (which, shared by the threads, gave about a third of the copies other
    rows and changed the demo's choice of material from one run to the next)."""
    torch.manual_seed(0)
    dec = MaterialDecoder(24)
    alone = dec.with_latent_dim(16).state_dict()
    torch.manual_seed(0)
    fresh = torch.nn.Linear(dec.hidden, 3 + 16).state_dict()
    last = f"net.{len(dec.net) - 1}.weight"
    assert torch.equal(alone[last][9:], fresh["weight"][9:])

    def copy_matches(_: int) -> bool:
        made = dec.with_latent_dim(16).state_dict()
        return all(torch.equal(made[k], v) for k, v in alone.items())

    with ThreadPoolExecutor(4) as pool:
        matches = list(pool.map(copy_matches, range(200)))
    assert all(matches), f"{matches.count(False)} of 200 copies made in threads differ"


def test_sample_uv_convention():
    tex = torch.arange(2 * 4 * 1, dtype=torch.float32).view(2, 4, 1)  # rows 0..1, cols 0..3
    # texel (i, j) centre: u = (j + 0.5) / 4, v = 1 - (i + 0.5) / 2 (row 0 is the top, v up)
    uv = torch.tensor([[0.125, 0.75], [0.875, 0.25], [0.5, 0.75]])
    out = sample_uv(tex, uv)[:, 0]
    assert torch.allclose(out, torch.tensor([0.0, 7.0, 1.5]))


def _scene_gradient(field: MaterialField, mesh: Mesh, params: list[torch.Tensor]) -> list[torch.Tensor]:
    env = EnvironmentMap.constant((1.0, 0.9, 0.8), height=8)
    scene = Scene(mesh, env, field)
    cam = sphere_camera(12)
    gen = torch.Generator().manual_seed(0)
    o, d, _ = cam.generate_rays(spp=1, generator=gen)
    tracer = PathTracer(PathTracerConfig(max_bounces=2, spp=1))
    radiance = tracer.render_rays(scene, o, d, gen)
    radiance.mean().backward()
    return [p.grad for p in params]


def _uv_sphere() -> Mesh:
    sphere = icosphere(2)
    v = sphere.vertices
    uv = np.stack([0.5 + np.arctan2(v[:, 0], v[:, 2]) / (2 * np.pi), 0.5 + np.arcsin(np.clip(v[:, 1], -1, 1)) / np.pi],
                  axis=1).astype(np.float32)  # fmt: skip
    return Mesh(v, sphere.faces, sphere.vertex_normals, uv)


def test_gradients_reach_the_triplane(basis):
    tp = Triplane(4, 8, generator=torch.Generator().manual_seed(1))
    field = TriplaneMaterialField(tp, MaterialDecoder(tp.feature_dim), basis)
    (grad,) = _scene_gradient(field, icosphere(2), [tp.planes])
    assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0
    # only texels near the surface of the unit sphere are read: some plane texels get no gradient
    assert (grad.abs().sum(1) > 0).float().mean() < 1


def test_gradients_reach_uv_textures(basis):
    mesh = _uv_sphere()
    tex = torch.full((8, 8, 9), 0.5).requires_grad_(True)
    (grad,) = _scene_gradient(UVTextureField(tex, basis), mesh, [tex])
    assert grad is not None and torch.isfinite(grad).all() and grad[..., :3].abs().sum() > 0
    assert grad[..., 3:].abs().sum() > 0  # latents too
    pbr = torch.tensor([0.6, 0.5, 0.4, 0.5, 0.2]).repeat(8, 8, 1).requires_grad_(True)
    (grad,) = _scene_gradient(PBRTextureField(pbr), mesh, [pbr])
    assert grad is not None and torch.isfinite(grad).all() and (grad.abs().sum((0, 1)) > 0).all()


def test_uv_field_needs_uvs(basis):
    field = UVTextureField(torch.zeros(4, 4, 9), basis)
    with pytest.raises(ValueError, match="texture coordinates"):
        _scene_gradient(field, icosphere(1), [])
    with pytest.raises(ValueError, match=r"\[H, W, 9\]"):
        UVTextureField(torch.zeros(4, 4, 3), basis)


def test_fit_triplane_distils_a_known_material(basis):
    mesh = icosphere(2)
    points = mesh.sample_surface(4000, seed=0)[0]

    def target(p):
        s = (p[:, 1:2] > 0).float()
        return torch.tensor([0.8, 0.2, 0.1]) * s + 0.3 * (1 - s), torch.tanh(p[:, :1].expand(-1, 6) * 2)

    field, mse = fit_triplane(points, target, basis, channels=4, resolution=16, steps=150, batch=2048)
    assert mse < 2e-3  # the G-buffer PSNR on (rho_d, (l + 1) / 2) is above 27 dB after a few seconds
    assert not field.triplane.planes.requires_grad
