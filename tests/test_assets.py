"""Material asset packages: bit-exact round trips (folder and zip), clear errors for future versions, missing or
damaged files and foreign bases, standard loaders for the glTF and USD fallbacks, baked textures that render like
the triplane they came from, the PBR fit, and the `neumatex render ASSET` / `neumatex export` commands."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile

import numpy as np
import pytest
import torch
from asset_fixtures import COMPARE, make_asset, render_psnr, views
from capture_fixtures import write_capture
from conftest import ENVMAPS, MESHES

from neumatex_core.assets import FORMAT_VERSION, AssetError, asset_from_textures, read_asset, write_asset
from neumatex_core.assets.bake import rasterize_uv
from neumatex_core.assets.export import export_asset
from neumatex_core.assets.package import read_png8
from neumatex_core.assets.pbr_fit import PBRFitConfig, fit_targets, pbr_albedo, pbr_targets, quantize_pbr
from neumatex_core.assets.render import make_previews, render_asset
from neumatex_core.geometry.mesh import load_mesh
from neumatex_core.imageio import read_image
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.materials.neural_basis import NeuralBasis, load_basis
from neumatex_core.render.path_tracer import PathTracerConfig

# Baked textures vs the triplane they were baked from, render PSNR over covered pixels. The neural basis aims at
# 35 dB against the analytic material (bench/basis.py); baking must stay well inside that budget, at most a tenth
# of its squared error: 35 + 10 dB. Measured with the shipped basis at this test's sizes (32^2 triplane, 48 px
# views): 66-68 dB at 128^2 texels, 53-54 dB at 64^2, on suzanne and cow; seam or uv convention errors cost tens of
# dB, so the bound catches them.
BAKED_PSNR_MIN = 45.0


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def basis():
    return load_basis()


@pytest.fixture(scope="module")
def mesh():
    return load_mesh(MESHES / "suzanne.obj").normalized()


@pytest.fixture(scope="module")
def asset(mesh, basis):
    return make_asset(mesh, basis)


@pytest.fixture(scope="module")
def envmap():
    return EnvironmentMap.from_file(ENVMAPS / "studio.exr")


@pytest.fixture(scope="module")
def written(asset, tmp_path_factory):
    """The asset written once as a folder (tests that damage it work on copies)."""
    return write_asset(asset, tmp_path_factory.mktemp("assets") / "object")


def _copy(src, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(src, dst)
    return dst


CONFIG = PathTracerConfig(spp=4, max_bounces=2)


@pytest.mark.parametrize("kind", ["folder", "zip"])
def test_round_trip_renders_bit_for_bit(asset, envmap, tmp_path, kind):
    path = write_asset(asset, tmp_path / ("object.zip" if kind == "zip" else "object"))
    assert path.is_file() == (kind == "zip")
    back = read_asset(path)
    assert back.field_kind == "triplane" and back.name == asset.name
    assert back.triplane is not None and asset.triplane is not None
    assert torch.equal(back.triplane.planes, asset.triplane.planes)
    assert torch.equal(back.material_texture, asset.material_texture)
    assert torch.equal(back.pbr_texture, asset.pbr_texture)
    assert np.array_equal(back.mesh.vertices, asset.mesh.vertices) and np.array_equal(back.mesh.uvs, asset.mesh.uvs)
    cams = views(16, (0, 20))
    for source in ("auto", "textures", "pbr"):
        before = render_asset(asset, envmap, cams, CONFIG, source, seed=3)
        after = render_asset(back, envmap, cams, CONFIG, source, seed=3)
        assert all(torch.equal(x, y) for x, y in zip(before, after, strict=True)), source
        assert all(float(x.max()) > 0 for x in before)


def test_the_same_asset_gives_the_same_texture_bytes(written, asset, tmp_path):
    """No time stamp in the EXR textures (OpenImageIO adds one unless told not to): the same material gives the same
    bytes, and so the same SHA-256 in the manifest, whenever it is written."""
    import OpenImageIO as oiio

    again = write_asset(asset, tmp_path / "again")
    textures = sorted(p.relative_to(written) for p in (written / "textures").iterdir())
    assert any(p.suffix == ".exr" for p in textures)
    for rel in textures:
        assert (written / rel).read_bytes() == (again / rel).read_bytes(), rel
        if rel.suffix == ".exr":
            inp = oiio.ImageInput.open(str(written / rel))
            assert inp.spec().get_string_attribute("DateTime") == "", rel
            inp.close()
    files = {k: v["sha256"] for k, v in json.loads((written / "manifest.json").read_text())["files"].items()}
    assert files == {k: v["sha256"] for k, v in json.loads((again / "manifest.json").read_text())["files"].items()}


def test_manifest_records_what_the_issue_asks(written, asset, basis):
    m = json.loads((written / "manifest.json").read_text())
    assert m["format_version"] == FORMAT_VERSION and m["format"] == "neumatex-material-asset"
    assert m["basis"] == {"basis_id": basis.basis_id, "content_hash": basis.content_hash}
    assert m["field"]["kind"] == "triplane" and m["field"]["shape"] == list(asset.triplane.planes.shape)
    assert m["decoders"]["material"]["id"].startswith("material-")
    assert m["provenance"]["source"] == "tests" and "distil_mse" in m["metrics"]
    assert {"uv_unwrap_s", "bake_s", "pbr_fit_s"} <= set(m["timings"])
    for rel in ("mesh.obj", "tensors.safetensors", "textures/base_color.exr", "textures/latent.exr",
                "textures/pbr_base_color.png", "textures/pbr_metallic_roughness.png", "fallback.glb", "fallback.usda"):
        assert rel in m["files"] and (written / rel).is_file(), rel
    latent = read_image(written / "textures" / "latent.exr")
    assert latent.shape == (128, 128, 6) and latent.min() >= -1 and latent.max() <= 1


def test_future_format_version_is_refused(written, tmp_path):
    root = _copy(written, tmp_path)
    m = json.loads((root / "manifest.json").read_text())
    m["format_version"] = FORMAT_VERSION + 1
    (root / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(AssetError, match=rf"manifest.json: written with asset format version {FORMAT_VERSION + 1}"):
        read_asset(root)
    # the same inside a zip names the zip
    z = tmp_path / "future.zip"
    with zipfile.ZipFile(z, "w") as zf:
        for p in root.rglob("*"):
            if p.is_file():
                zf.write(p, p.relative_to(root).as_posix())
    with pytest.raises(AssetError, match=r"future.zip/manifest.json: .*upgrade NeuMatEx"):
        read_asset(z)


def test_missing_and_damaged_files_are_named(written, tmp_path):
    root = _copy(written, tmp_path)
    (root / "textures" / "latent.exr").unlink()
    with pytest.raises(AssetError, match=r"textures/latent.exr: missing"):
        read_asset(root)
    root2 = tmp_path / "damaged"
    shutil.copytree(written, root2)
    data = bytearray((root2 / "tensors.safetensors").read_bytes())
    data[-1] ^= 0xFF
    (root2 / "tensors.safetensors").write_bytes(bytes(data))
    with pytest.raises(AssetError, match=r"tensors.safetensors: does not match the SHA-256"):
        read_asset(root2)
    (tmp_path / "empty").mkdir()
    with pytest.raises(AssetError, match=r"manifest.json: missing; not a NeuMatEx material asset"):
        read_asset(tmp_path / "empty")
    with pytest.raises(AssetError, match="asset not found"):
        read_asset(tmp_path / "nowhere.zip")


def test_unknown_basis_is_refused(written, tmp_path, basis):
    root = _copy(written, tmp_path)
    m = json.loads((root / "manifest.json").read_text())
    m["basis"]["content_hash"] = "0" * 64
    (root / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(AssetError, match=r"manifest.json: needs neural basis .* but this installation has"):
        read_asset(root)
    m["basis"] = {"basis_id": "nmx-basis-v9-000000000000", "content_hash": "f" * 64}
    (root / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(AssetError, match=r"needs neural basis nmx-basis-v9-000000000000 .* but this installation has"):
        read_asset(root)
    # Handed another basis than the one the asset names, the reader takes the installed basis it names.
    other = NeuralBasis()
    other.basis_id, other.content_hash = "nmx-basis-v9-000000000000", "f" * 64
    assert read_asset(written, basis=other).basis.basis_id == basis.basis_id


def test_glb_loads_in_trimesh_and_pygltflib(written, asset):
    import pygltflib
    import trimesh

    scene = trimesh.load(written / "fallback.glb")
    (geom,) = scene.geometry.values()
    assert len(geom.vertices) == len(asset.mesh.vertices) and len(geom.faces) == asset.mesh.num_faces
    mat = geom.visual.material
    assert isinstance(mat, trimesh.visual.material.PBRMaterial)
    assert mat.baseColorTexture.size == (128, 128) and mat.metallicRoughnessTexture.size == (128, 128)
    base = read_png8(written / "textures" / "pbr_base_color.png", "png")
    assert np.array_equal(np.asarray(mat.baseColorTexture.convert("RGB")), base)
    # trimesh flips glTF's v-down texture coordinates back to v up: the package's uvs
    assert np.allclose(np.asarray(geom.visual.uv), asset.mesh.uvs, atol=1e-6)
    gltf = pygltflib.GLTF2().load(str(written / "fallback.glb"))
    pbr = gltf.materials[0].pbrMetallicRoughness
    assert pbr.baseColorTexture.index == 0 and pbr.metallicRoughnessTexture.index == 1
    assert [im.mimeType for im in gltf.images] == ["image/png", "image/png"] and gltf.materials[0].doubleSided
    assert gltf.materials[0].extras["neumatex"]["basis_id"] == asset.basis.basis_id


def test_usd_opens_with_a_preview_surface(written):
    from pxr import Usd, UsdGeom, UsdShade

    stage = Usd.Stage.Open(str(written / "fallback.usda"))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert len(meshes) == 1
    geom = UsdGeom.Mesh(meshes[0])
    assert UsdGeom.PrimvarsAPI(geom).GetPrimvar("st").Get() is not None
    material = UsdShade.MaterialBindingAPI(meshes[0]).ComputeBoundMaterial()[0]
    surface = material.ComputeSurfaceSource()[0]
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface"
    for name, file in (("diffuseColor", "pbr_base_color.png"), ("roughness", "pbr_metallic_roughness.png"),
                       ("metallic", "pbr_metallic_roughness.png")):
        (src,), _ = surface.GetInput(name).GetConnectedSources()
        tex = UsdShade.Shader(src.source.GetPrim())
        assert tex.GetIdAttr().Get() == "UsdUVTexture"
        path = tex.GetInput("file").Get().path
        assert path.endswith(file) and (written / path).is_file()


def test_baked_textures_render_like_the_triplane(asset, envmap):
    cams = views(48)
    neural = render_asset(asset, envmap, cams, COMPARE, "triplane")
    baked = render_asset(asset, envmap, cams, COMPARE, "textures")
    assert render_psnr(neural, baked, asset.mesh, cams) > BAKED_PSNR_MIN


def test_bake_covers_every_texel_bilinear_lookups_touch(asset):
    samples = rasterize_uv(asset.mesh, 128)
    assert samples.inside.mean() > 0.5 and (~samples.inside).any()  # border texels exist, most are inside
    # every texel a lookup at a triangle corner touches holds a surface point
    uv = asset.mesh.uvs[asset.mesh.faces].reshape(-1, 2)
    x, y = uv[:, 0] * 128 - 0.5, (1 - uv[:, 1]) * 128 - 0.5
    cols = np.clip(np.stack([np.floor(x), np.floor(x) + 1]), 0, 127).astype(int)
    rows = np.clip(np.stack([np.floor(y), np.floor(y) + 1]), 0, 127).astype(int)
    mask = samples.mask
    assert all(mask[rows[i], cols[j]].all() for i in range(2) for j in range(2))


def test_pbr_fit_recovers_pbr_materials():
    truth = torch.tensor([[0.8, 0.2, 0.1, 0.3, 0.0], [0.9, 0.6, 0.3, 0.5, 1.0], [0.1, 0.1, 0.6, 0.8, 0.0],
                          [0.5, 0.5, 0.5, 0.15, 1.0]])  # fmt: skip
    params, loss = fit_targets(pbr_targets(truth), pbr_albedo(truth))
    assert float(loss.max()) < 2e-3  # log-space RMS under 5% over the direction pairs and albedos
    assert torch.allclose(params[:, 3], truth[:, 3], atol=0.05) and torch.equal(params[:, 4].round(), truth[:, 4])
    with torch.no_grad():  # the caller's grad mode changes nothing (a ground truth's G-buffers are read under it)
        again, _ = fit_targets(pbr_targets(truth), pbr_albedo(truth))
    assert torch.equal(again, params)


def test_pbr_fit_albedo_terms():
    """PBRFitConfig.albedo: with Karis' split-sum fit on both sides ("split_sum", the term until 2026-12-07) the fit
    recovers PBR materials as with the exact one (`test_pbr_fit_recovers_pbr_materials`); "none" is the fit without
    albedos; the split-sum fit underrates a mid-roughness conductor's exact albedo in proportion to its F0."""
    truth = torch.tensor([[0.8, 0.2, 0.1, 0.3, 0.0], [0.9, 0.6, 0.3, 0.5, 1.0], [0.1, 0.1, 0.6, 0.8, 0.0],
                          [0.5, 0.5, 0.5, 0.15, 1.0]])  # fmt: skip
    split = PBRFitConfig(albedo="split_sum")
    params, loss = fit_targets(pbr_targets(truth), pbr_albedo(truth, "split_sum"), split)
    assert float(loss.max()) < 2e-3
    assert torch.allclose(params[:, 3], truth[:, 3], atol=0.05) and torch.equal(params[:, 4].round(), truth[:, 4])
    without, _ = fit_targets(pbr_targets(truth), pbr_albedo(truth), PBRFitConfig(albedo="none"))
    assert torch.equal(without, fit_targets(pbr_targets(truth))[0])
    gap = pbr_albedo(truth[1:2]) - pbr_albedo(truth[1:2], "split_sum")  # f0 (0.9, 0.6, 0.3), roughness 0.5
    assert bool((gap > 0.02).all()) and float(gap[..., 0].min()) > 0.09, gap  # in proportion to f0


def test_pbr_fit_directions_and_chunks(basis):
    """The fit's targets must be made for its direction set (a clear error otherwise); the materials' chunk changes
    no bit of the fallback; more cosine directions per view fit the hemisphere's pairs the old six leave out."""
    from neumatex_core.assets.pbr_fit import N_COSINE, fit_directions, fit_pbr, neural_albedo, neural_targets

    truth = torch.tensor([[0.8, 0.2, 0.1, 0.3, 0.0], [0.9, 0.6, 0.3, 0.5, 1.0]])
    with pytest.raises(ValueError, match="direction pairs"):
        fit_targets(pbr_targets(truth, cosine=6), pbr_albedo(truth), PBRFitConfig(cosine_directions=N_COSINE))
    assert fit_directions(6)[0].shape[0] < fit_directions(N_COSINE)[0].shape[0]
    g = torch.Generator().manual_seed(3)
    latent = torch.rand(6, 5, basis.arch.latent_dim, generator=g) * 2 - 1
    texture = torch.cat([torch.rand(6, 5, 3, generator=g), latent], dim=-1)
    whole, loss = fit_pbr(basis, texture)
    pieces, loss_pieces = fit_pbr(basis, texture, config=PBRFitConfig(chunk=7))
    assert torch.equal(whole, pieces) and loss == loss_pieces
    # scored on the dense set, the grid search on it starts better on average than one on the six directions
    values = texture.reshape(-1, texture.shape[-1])
    dense = PBRFitConfig(steps=0)
    target, albedo = neural_targets(basis, values), neural_albedo(basis, values)
    _, dense_loss = fit_targets(target, albedo, dense)
    sparse, _ = fit_targets(neural_targets(basis, values, 6), albedo, PBRFitConfig(cosine_directions=6, steps=0))
    from neumatex_core.assets.pbr_fit import EPS, _total_loss

    wi, wo = fit_directions()
    sparse_loss = _total_loss(sparse, wi, wo, torch.log(EPS + target), torch.log(EPS + albedo))
    assert float((sparse_loss - dense_loss).mean()) > 0, (sparse_loss, dense_loss)


def test_pbr_fit_fits_the_surface_texels_and_fills_the_rest_from_them(basis):
    """With a mask only its texels' materials are fitted, each bit for bit as without the mask, and the others
    are filled from them as the neural texture's padding was (dilated, then quantised), not fitted: renders read
    only the surface, and the padding's neighbour means took 40% of the demo's fit."""
    from neumatex_core.assets.pbr_fit import fit_pbr

    g = torch.Generator().manual_seed(5)
    texture = torch.cat([torch.rand(6, 6, 3, generator=g),
                         torch.rand(6, 6, basis.arch.latent_dim, generator=g) * 2 - 1], dim=-1)  # fmt: skip
    mask = torch.zeros(6, 6, dtype=torch.bool)
    mask[1:4, 1:3] = True
    texture[5, 5] = texture[2, 2] + 1e-3  # one distinct material on and off the surface: fitted at both's mean
    fitted, loss = fit_pbr(basis, texture, mask)
    whole, _ = fit_pbr(basis, texture)
    assert torch.equal(fitted[mask], whole[mask])
    assert loss == pytest.approx(fit_pbr(basis, texture[1:4, 1:3])[1], rel=1e-6)
    assert torch.equal(fitted[0, 0], whole[1, 1])  # the corner's only filled neighbour
    assert torch.equal(fitted[~mask], quantize_pbr(fitted[~mask]))  # what 8-bit files hold
    assert not torch.equal(fitted[0, 3:5], whole[0, 3:5])  # the padding is not fitted


def test_pbr_fit_grid_search_is_the_same_in_any_chunk(basis):
    """The grid search runs in chunks of materials (small ones keep its [chunk, 3, G, K] tensors in cache: 5x faster
    than 1024); each material's fit is its own, so the chunk changes no bit of the result."""
    from neumatex_core.assets.pbr_fit import _grid_search, fit_directions, neural_albedo, neural_targets

    g = torch.Generator().manual_seed(8)
    values = torch.cat([torch.rand(300, 3, generator=g), torch.rand(300, 6, generator=g) * 2 - 1], dim=-1)
    target, albedo = neural_targets(basis, values), neural_albedo(basis, values)
    wi, wo = fit_directions()
    fits = [_grid_search(target, wi, wo, albedo, chunk=c) for c in (300, 128, 7)]
    assert all(torch.equal(fits[0], f) for f in fits[1:])


def test_uv_texture_asset_round_trip(asset, envmap, tmp_path, basis):
    uv_asset = asset_from_textures("uv-object", asset.mesh, asset.material_texture, basis)
    assert uv_asset.field_kind == "uv_textures"
    back = read_asset(write_asset(uv_asset, tmp_path / "uv.zip"))
    assert back.field_kind == "uv_textures" and back.triplane is None
    cams = views(16, (3,))
    assert torch.equal(render_asset(uv_asset, envmap, cams, CONFIG)[0], render_asset(back, envmap, cams, CONFIG)[0])
    with pytest.raises(ValueError, match="no triplane"):
        back.field("triplane")


def test_previews_are_written_and_read(asset, envmap, tmp_path):
    previews = make_previews(asset, envmap, resolution=16, spp=2, views=(0,))
    assert set(previews) == {"neural_view00", "pbr_view00"}
    back = read_asset(write_asset(asset, tmp_path / "with-previews"))
    assert (tmp_path / "with-previews" / "previews" / "neural_view00.png").is_file()
    assert back.previews["pbr_view00"].shape == (16, 16, 3)
    asset.previews = {}


def test_previews_render_both_sources_side_by_side_with_the_same_images(asset, envmap, monkeypatch):
    """With two torch threads the neural and PBR-fallback previews render side by side, each in its own thread of one
    torch thread (`side_by_side`; docs/design-notes.md item 47), and are the images one thread renders one after the
    other, bit for bit."""
    import threading

    from neumatex_core.assets import render

    rendered_in: list[str] = []
    real = render.render_asset

    def render_asset_seen(*a, **k):  # type: ignore[no-untyped-def]
        rendered_in.append(threading.current_thread().name)
        return real(*a, **k)

    monkeypatch.setattr(render, "render_asset", render_asset_seen)
    alone = make_previews(asset, envmap, resolution=16, spp=2, views=(0, 4))
    assert rendered_in == [threading.current_thread().name] * 2
    rendered_in.clear()
    torch.set_num_threads(2)
    try:
        paired = make_previews(asset, envmap, resolution=16, spp=2, views=(0, 4))
    finally:
        torch.set_num_threads(1)
    assert len(set(rendered_in)) == 2 and threading.current_thread().name not in rendered_in
    assert paired.keys() == alone.keys() and all(np.array_equal(paired[k], alone[k]) for k in alone)
    asset.previews = {}


def test_export_writes_each_format(asset, tmp_path):
    (glb,) = export_asset(asset, "glb", tmp_path / "glb")
    assert glb.name == "test_object.glb" and glb.stat().st_size > 0
    usd = export_asset(asset, "usd", tmp_path / "usd")
    assert usd[0].suffix == ".usda" and all(p.is_file() for p in usd)
    tex = export_asset(asset, "textures", tmp_path / "tex")
    assert {p.name for p in tex} >= {"mesh.obj", "base_color.exr", "latent.exr", "pbr_base_color.png"}


def neumatex(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "neumatex_core.cli", *args], capture_output=True, text=True,
                          timeout=300, env=env)  # fmt: skip


def test_cli_render_and_export_an_asset(asset, tmp_path):
    pkg = write_asset(asset, tmp_path / "object.zip")
    out = tmp_path / "render"
    res = neumatex("render", str(pkg), "--envmap", str(ENVMAPS / "courtyard.exr"), "--views", "0,17",
                   "--resolution", "16", "--spp", "2", "--material", "textures", "--out", str(out))  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert read_image(out / "view_01.exr").shape == (16, 16, 3) and (out / "views.png").is_file()
    res = neumatex("render", "--asset", str(pkg), "--envmap", str(ENVMAPS / "courtyard.exr"), "--views", "5",
                   "--resolution", "12", "--spp", "1", "--out", str(tmp_path / "r2"))  # fmt: skip
    assert res.returncode == 0, res.stderr
    capture = write_capture(tmp_path / "cap", n_frames=2, resolution=12)  # its cameras, map and tonemap
    res = neumatex("render", str(pkg), "--capture", str(capture), "--spp", "1", "--out", str(tmp_path / "r3"))
    assert res.returncode == 0, res.stderr
    assert read_image(tmp_path / "r3" / "view_01.png").shape == (12, 12, 3)
    res = neumatex("export", str(pkg), "--format", "usd", "--out", str(tmp_path / "usd"))
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "usd" / "test_object.usda").is_file()


def test_cli_asset_errors_are_clear(written, tmp_path):
    res = neumatex("render", str(tmp_path / "none.zip"), "--envmap", str(ENVMAPS / "courtyard.exr"))
    assert res.returncode == 2 and "none.zip: asset not found" in res.stderr and "Traceback" not in res.stderr
    root = _copy(written, tmp_path)
    (root / "mesh.obj").unlink()
    res = neumatex("export", str(root), "--format", "glb", "--out", str(tmp_path / "x"))
    assert res.returncode == 2 and "mesh.obj: missing" in res.stderr and "Traceback" not in res.stderr
    res = neumatex("render", str(root), "--asset", "other", "--envmap", "x.exr")
    assert res.returncode == 2 and "given twice" in res.stderr


def test_uncertainty_and_pbr_decoders_travel_with_the_triplane(asset, tmp_path):
    import dataclasses

    from neumatex_core.fields import PBRDecoder, UncertaintyDecoder, module_id

    feat = asset.triplane.feature_dim
    extra = {"uncertainty": UncertaintyDecoder(feat), "pbr": PBRDecoder(feat, hidden=32)}
    full = dataclasses.replace(asset, decoders={**asset.decoders, **extra})
    back = read_asset(write_asset(full, tmp_path / "full"))
    assert set(back.decoders) == {"material", "uncertainty", "pbr"}
    assert all(module_id(back.decoders[k]) == module_id(full.decoders[k]) for k in back.decoders)
    assert back.decoders["pbr"].hidden == 32
