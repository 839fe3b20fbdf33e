"""The browser viewer (neumatex_core/viewer/, docs/viewer.md): its bundle holds the basis exactly, and the page,
rendered in headless Debian Chromium with software WebGL2 (ANGLE on SwiftShader), converges to the torch path
tracer's direct lighting of the same asset, camera and map.

The comparison object is a sphere: convex, so the path tracer's shadow rays are never blocked and a rasteriser
without shadows computes the same integral. The page's neural mode evaluates the basis MLPs in GLSL with the same
estimator as the path tracer (map sampling + the basis's BSDF sampling, balance heuristic) and accumulates frames
with sub-pixel jitter; the map is the bundle's downsampled one on both sides (`web_bundle.torch_envmap`). The
comparison is of the 8-bit canvas (the page's own clip + sRGB tonemap) against `Tonemap().apply` of the torch image,
over the pixels whose centre sees the sphere. The PBR fallback mode, a different BSDF, must score clearly lower
against the same neural reference: the agreement is the material's, not the lighting's or the geometry's alone.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest
import torch
from conftest import ENVMAPS
from viewer_fixtures import read_display, read_linear, set_camera, sphere_asset, view_camera, viewer_page

from neumatex_core.assets import read_asset, write_asset
from neumatex_core.assets.render import render_asset
from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.materials.neural_basis import BASIS_V6, load_basis
from neumatex_core.render.path_tracer import PathTracerConfig
from neumatex_core.viewer.serve import serve_folder
from neumatex_core.viewer.web_bundle import BUNDLE, EnvSource, env_tables, torch_envmap, write_bundle

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

# Measured (32 x 32 px, 48 frames x 4 spp in the page vs 512 spp in torch, studio map at 128 x 64): 33.0 dB
# for the neural mode, 25.7 dB for the PBR fallback against the neural reference; 30 dB is the bar (issue 17).
PSNR_MIN = 30.0
SIZE, FRAMES, SPP, REF_SPP = 32, 48, 4, 512


# The shipped basis (6 latents) and basis v6 (16): the bundle's channels and the shader follow the latent size.
@pytest.fixture(scope="module", params=["", BASIS_V6], ids=["default-basis", "basis-v6"])
def asset_dir(request, tmp_path_factory):
    basis = load_basis("cpu", request.param)
    folder = tmp_path_factory.mktemp("viewer") / "sphere"
    write_asset(sphere_asset(basis), folder)
    return folder


@pytest.fixture(scope="module")
def bundle(asset_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("bundle")
    write_bundle(read_asset(asset_dir), out, [EnvSource.from_file(ENVMAPS / "studio.exr")], env_height=64)
    return out


def _mlp_numpy(data: np.ndarray, layers: list[dict], bias_offset: int, x: np.ndarray) -> np.ndarray:
    """The packed network evaluated from basis.bin with the documented layout (what the shader reads)."""
    h = x
    for k, layer in enumerate(layers):
        n_in4, n_out4 = layer["n_in4"], layer["n_out4"]
        blocks = data[layer["offset"]: layer["offset"] + layer["floats"]].reshape(n_out4, n_in4, 4, 4)
        w = blocks.transpose(0, 3, 1, 2).reshape(n_out4 * 4, n_in4 * 4)  # [i, c, j, r] -> rows, columns
        start = bias_offset + 4 * layer["bias_vec4"]
        b = data[start: start + 4 * n_out4]
        hp = np.zeros((h.shape[0], n_in4 * 4), np.float64)
        hp[:, : h.shape[1]] = h
        h = hp @ w.T.astype(np.float64) + b
        if k < len(layers) - 1:
            h = h / (1 + np.exp(-h))
    return h


def test_bundle_holds_the_basis_and_the_map_sampling(asset_dir, bundle):
    info = json.loads((bundle / BUNDLE).read_text())
    data = np.fromfile(bundle / info["basis"]["file"], dtype="<f4")
    asset = read_asset(asset_dir)
    basis = asset.basis
    k = basis.arch.latent_dim
    assert info["basis"]["basis_id"] == basis.basis_id and info["basis"]["latent_dim"] == k
    # the textures: rho_d, the k latents, the PBR fallback, the mask, zero padding to whole RGBA textures
    texels = np.fromfile(bundle / info["material"]["file"], dtype="<f4")
    channels = info["material"]["channels"]
    assert channels % 4 == 0 and 3 + k + 6 <= channels < 3 + k + 10
    texels = texels.reshape(asset.texture_resolution, asset.texture_resolution, channels)
    assert np.array_equal(texels[..., : 3 + k], asset.material_texture.numpy())
    assert np.array_equal(texels[..., 3 + k + 5], asset.texel_mask.numpy().astype(np.float32))
    g = torch.Generator().manual_seed(0)
    latent = torch.rand(64, k, generator=g) * 2 - 1
    wi = torch.nn.functional.normalize(torch.rand(64, 3, generator=g) + torch.tensor([-0.5, -0.5, 0.2]), dim=-1)
    wo = torch.nn.functional.normalize(torch.rand(64, 3, generator=g) + torch.tensor([-0.5, -0.5, 0.2]), dim=-1)
    from neumatex_core.materials.neural_basis import direction_features

    nets = info["basis"]["networks"]
    off = info["basis"]["bias_offset"]
    dec = _mlp_numpy(data, nets["decoder"], off, torch.cat([latent, direction_features(wi, wo)], -1).numpy())
    aux = _mlp_numpy(data, nets["aux"], off, torch.cat([latent, wo], -1).numpy())
    smp = _mlp_numpy(data, nets["sampler"], off, torch.cat([latent, wo], -1).numpy())
    with torch.no_grad():
        assert np.abs(dec[:, :3] - basis.log_bsdf(latent, wi, wo).numpy()).max() < 1e-4
        assert np.abs(aux[:, :4] - basis.aux(torch.cat([latent, wo], -1)).numpy()).max() < 1e-4
        assert np.abs(smp[:, :5] - basis.sampler(torch.cat([latent, wo], -1)).numpy()).max() < 1e-4
    # The sampling tables: every CDF ends at 1, and the marginal's steps are the rows' shares of the bin probabilities.
    env = torch_envmap(bundle, "studio")
    texels, tables = env_tables(env.texels.numpy())
    h, w = env.height, env.width
    assert np.allclose(tables[:h, w], 1.0) and tables[h, h] == pytest.approx(1.0)
    assert np.allclose(np.diff(tables[h, : h + 1]), env.bin_prob.sum(1).numpy(), atol=1e-6)
    assert np.allclose(texels[:, :, 3], env.bin_prob.numpy())


def _psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    mse = float(np.mean((a[mask].astype(np.float64) - b[mask]) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(1.0 / mse)


def test_viewer_converges_to_the_path_tracers_direct_lighting(asset_dir, bundle):
    asset = read_asset(asset_dir)
    camera = view_camera(SIZE)
    envmap = torch_envmap(bundle, "studio")
    torch.manual_seed(0)
    reference = render_asset(asset, envmap, [camera], PathTracerConfig(max_bounces=1, spp=REF_SPP),
                             source="textures")[0]  # fmt: skip
    ref_display = Tonemap().apply(reference).numpy()
    mask = render_gbuffer(asset.mesh, camera).mask.numpy()
    assert mask.mean() > 0.4  # the sphere fills most of the frame
    server = serve_folder(bundle)
    try:
        with viewer_page(server.url + f"?auto=0&spp={SPP}") as page:
            set_camera(page, camera)
            t0 = time.perf_counter()
            ms = page.evaluate(f"() => window.neumatexViewer.renderFrames({FRAMES})")
            seconds = time.perf_counter() - t0
            neural = read_display(page)
            linear = read_linear(page)
            page.evaluate("() => window.neumatexViewer.setMode('pbr')")
            page.evaluate(f"() => window.neumatexViewer.renderFrames({FRAMES})")
            pbr = read_display(page)
    finally:
        server.close()
    psnr_neural = _psnr(neural, ref_display, mask)
    psnr_linear = _psnr(Tonemap().apply_numpy(linear), ref_display, mask)
    psnr_pbr = _psnr(pbr, ref_display, mask)
    print(f"\nviewer vs torch direct lighting ({SIZE}x{SIZE}, {FRAMES}x{SPP} spp vs {REF_SPP} spp): neural "
          f"{psnr_neural:.2f} dB (8-bit canvas), {psnr_linear:.2f} dB (float readback, same tonemap); PBR fallback "
          f"{psnr_pbr:.2f} dB; {ms:.0f} ms/frame in software GL ({seconds:.1f} s)")
    assert psnr_neural >= PSNR_MIN
    assert psnr_linear >= PSNR_MIN
    assert psnr_pbr < psnr_neural - 5.0
    # no bias: the mean radiance over the sphere agrees within 3%
    ratio = linear[mask].mean(0) / reference.numpy()[mask].mean(0)
    assert np.all(np.abs(ratio - 1) < 0.03), ratio


def test_neumatex_view_serves_the_page(asset_dir, tmp_path):
    env = {**os.environ, "NEUMATEX_SHARED": ""}
    proc = subprocess.Popen([sys.executable, "-m", "neumatex_core.cli", "view", str(asset_dir), "--envmap",
                             str(ENVMAPS / "studio.exr"), "--port", "0", "--no-browser", "--env-height", "32"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)  # fmt: skip
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "http://127.0.0.1:" in line, (line, proc.stderr.read() if proc.poll() is not None else "")
        url = line.split(" at ")[1].split()[0]
        with urllib.request.urlopen(url, timeout=10) as r:
            page = r.read().decode()
            assert "viewer.js" in page and "script-src 'self'" in r.headers["Content-Security-Policy"]
        with urllib.request.urlopen(url.replace("index.html", "bundle.json"), timeout=10) as r:
            info = json.loads(r.read())
        assert [m["name"] for m in info["envmaps"]] == ["studio"]
        assert info["envmaps"][0]["height"] == 32 and info["mesh"]["corners"] % 3 == 0
    finally:
        proc.terminate()
        proc.wait(timeout=10)
