"""A material asset as files a browser can load: JSON + little-endian float32 `.bin` (docs/viewer.md).

`write_bundle(asset, out, envmaps)` writes, next to the static `index.html` / `viewer.js` of this package:

    bundle.json          names, sizes, byte layouts of the files below, the basis id, the default map
    mesh.bin             triangle soup, 11 floats per corner: position, shading normal, uv, face normal (the
                         geometric normal of `Mesh.face_normals`, as the path tracer uses it)
    material.bin         [R, R, C] texel rows from the top (v = 1), C / 4 RGBA textures of the channels rho_d, the
                         basis's K latents, PBR base colour (linear), PBR roughness, metallic, texel mask, zeros to a
                         multiple of 4 (C = 16 for the paper's K = 6: (rho_d, l0), (l1..l4), (l5, PBR base colour),
                         (roughness, metallic, mask, 0))
    basis.bin            the decoder and auxiliary MLPs of the asset's basis as std140 uniform blocks: per layer
                         its weights as 4x4 column-major blocks (out block i, in block j at i * n_in4 + j), then
                         every layer's bias (zero padded to a multiple of 4)
    env/<name>.bin       an equirectangular map (box-downsampled) as [H, W, 4] (radiance RGB, the bin probability
                         of `EnvironmentMap` importance sampling), then the sampling tables [H + 1, W + 1]: rows
                         0..H-1 the conditional CDF of each row over its W bins, row H the marginal CDF over rows

Everything the page computes is what `neumatex_core` computes: the BSDF is `NeuralMaterial.eval` (basis eval
f = T(wo) rho_d / pi + f_neu(l, wi, wo), docs/asset-format.md), the map lookup and its sampling pdf those of
`lighting/envmap.py`, so a viewer frame converges to the path tracer's direct lighting (`tests/test_viewer.py`).
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from neumatex_core.assets.asset import MaterialAsset
from neumatex_core.lighting.envmap import EnvironmentMap, load_envmap_radiance
from neumatex_core.materials.neural_basis import NeuralBasis

STATIC_DIR = Path(__file__).resolve().parent / "static"
STATIC_FILES = ("index.html", "viewer.js")
BUNDLE = "bundle.json"
BUNDLE_FORMAT = "neumatex-viewer-bundle"
BUNDLE_VERSION = 1
ENV_HEIGHT = 256  # default height of the maps the page gets (width 2x): 512 x 256 texels, 2 MiB + tables


@dataclass(frozen=True)
class EnvSource:
    """A map for the page: its name in the menu and its linear radiance [H, W, 3] (2:1)."""

    name: str
    radiance: np.ndarray

    @classmethod
    def from_file(cls, path: str | Path, name: str | None = None) -> EnvSource:
        path = Path(path)
        return cls(name or path.stem, load_envmap_radiance(path))


def downsample_envmap(radiance: np.ndarray, height: int = ENV_HEIGHT) -> np.ndarray:
    """[H, W, 3] -> [h, 2h, 3] by averaging k x k texel boxes (k = H // height), h = min(height, H); H must be
    a multiple of k (the shared maps are powers of two)."""
    h_in = radiance.shape[0]
    k = max(1, h_in // max(1, height))
    if h_in % k or radiance.shape[1] % k:
        raise ValueError(f"environment map of {radiance.shape[1]}x{h_in} cannot be box-downsampled by {k}")
    h, w = h_in // k, radiance.shape[1] // k
    boxes = radiance[:, :, :3].astype(np.float64).reshape(h, k, w, k, 3)
    return boxes.mean(axis=(1, 3)).astype(np.float32)


def env_tables(radiance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """([H, W, 4] radiance + bin probability, [H + 1, W + 1] CDF tables) of a map, the bin probabilities exactly
    those `EnvironmentMap` samples with (its `bin_prob`)."""
    env = EnvironmentMap(radiance)
    prob = env.bin_prob.double().numpy()
    h, w = prob.shape
    texels = np.concatenate([env.texels.numpy(), prob[:, :, None].astype(np.float32)], axis=2)
    tables = np.zeros((h + 1, w + 1), dtype=np.float64)
    row_sum = prob.sum(axis=1)
    cond = np.cumsum(prob, axis=1) / np.where(row_sum > 0, row_sum, 1.0)[:, None]
    tables[:h, 1:] = np.where(row_sum[:, None] > 0, cond, np.arange(1, w + 1) / w)
    marginal = np.cumsum(row_sum) / row_sum.sum()
    tables[h, 1: h + 1] = marginal
    tables[h, h + 1:] = 1.0
    tables[:h, w] = 1.0
    tables[h, h] = 1.0
    return texels.astype(np.float32), tables.astype(np.float32)


def mesh_soup(asset: MaterialAsset) -> np.ndarray:
    """[3F, 11] float32 corners: position, shading normal, uv, face normal."""
    mesh = asset.mesh
    if mesh.uvs is None or mesh.vertex_normals is None:
        raise ValueError("the viewer needs a mesh with uvs and vertex normals (an asset's mesh has them)")
    f = mesh.faces
    fn = np.repeat(mesh.face_normals()[:, None, :], 3, axis=1)
    soup = np.concatenate([mesh.vertices[f], mesh.vertex_normals[f], mesh.uvs[f], fn], axis=2)
    return np.ascontiguousarray(soup.reshape(-1, 11), dtype=np.float32)


def material_texels(asset: MaterialAsset) -> np.ndarray:
    """[R, R, C] float32: the neural textures (3 + K), the PBR fallback (5, decoded as the renderer reads it), the
    mask, zeros to make C a multiple of 4."""
    mat = asset.material_texture.detach().float().cpu().numpy()
    pbr = asset.pbr_texture.detach().float().cpu().numpy()
    if pbr.shape[:2] != mat.shape[:2]:
        raise ValueError(f"PBR textures {pbr.shape[:2]} and neural textures {mat.shape[:2]} differ in size")
    mask = asset.texel_mask.detach().float().cpu().numpy()[:, :, None]
    used = mat.shape[2] + pbr.shape[2] + 1
    zero = np.zeros((*mask.shape[:2], -used % 4), np.float32)
    return np.ascontiguousarray(np.concatenate([mat, pbr, mask, zero], axis=2), dtype=np.float32)


def _linear_layers(net: nn.Sequential) -> list[nn.Linear]:
    layers = [m for m in net if isinstance(m, nn.Linear)]
    acts = [type(m).__name__ for m in net if not isinstance(m, nn.Linear)]
    if any(a != "SiLU" for a in acts) or len(acts) != len(layers) - 1:
        raise ValueError(f"the viewer evaluates Linear + SiLU stacks; this basis has activations {acts}")
    return layers


def _pack_layer(layer: nn.Linear) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(weights as 4x4 column-major blocks [n_out4 * n_in4 * 16], bias [n_out4 * 4], n_in4, n_out4)."""
    w = layer.weight.detach().double().cpu().numpy()
    b = layer.bias.detach().double().cpu().numpy()
    n_out4, n_in4 = -(-w.shape[0] // 4), -(-w.shape[1] // 4)
    padded = np.zeros((n_out4 * 4, n_in4 * 4))
    padded[: w.shape[0], : w.shape[1]] = w
    blocks = padded.reshape(n_out4, 4, n_in4, 4).transpose(0, 2, 3, 1)  # [i, j, column c, row r]
    bias = np.zeros(n_out4 * 4)
    bias[: b.shape[0]] = b
    return blocks.reshape(-1).astype(np.float32), bias.astype(np.float32), n_in4, n_out4


def pack_basis(basis: NeuralBasis) -> tuple[np.ndarray, dict[str, object]]:
    """The decoder and auxiliary networks as float32 uniform-block data and its layout (see the module doc)."""
    parts: list[np.ndarray] = []
    biases: list[np.ndarray] = []
    offset = 0
    nets: dict[str, list[dict[str, int]]] = {}
    for name, net in (("decoder", basis.decoder), ("aux", basis.aux), ("sampler", basis.sampler)):
        nets[name] = []
        for layer in _linear_layers(net):
            weights, bias, n_in4, n_out4 = _pack_layer(layer)
            nets[name].append({"offset": offset, "floats": int(weights.size), "n_in4": n_in4, "n_out4": n_out4,
                               "bias_vec4": sum(b.size for b in biases) // 4,
                               "n_in": layer.in_features, "n_out": layer.out_features})  # fmt: skip
            parts.append(weights)
            biases.append(bias)
            offset += int(weights.size)
    bias_all = np.concatenate(biases)
    data = np.concatenate([*parts, bias_all]).astype("<f4")
    layout = {"networks": nets, "bias_offset": offset, "bias_floats": int(bias_all.size),
              "latent_dim": basis.arch.latent_dim, "basis_id": basis.basis_id}  # fmt: skip
    return data, layout


def _write_bin(path: Path, array: np.ndarray) -> dict[str, object]:
    data = np.ascontiguousarray(array, dtype="<f4")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data.tobytes())
    return {"file": path.name if path.parent.name != "env" else f"env/{path.name}", "shape": list(data.shape)}


def write_bundle(asset: MaterialAsset, out: str | Path, envmaps: list[EnvSource], default_envmap: str = "",
                 env_height: int = ENV_HEIGHT, static: bool = True) -> Path:
    """Write the page's data for `asset` lit by `envmaps` (at least one) into folder `out`; with `static`, copy
    index.html and viewer.js there too. Returns `out`/bundle.json."""
    if not envmaps:
        raise ValueError("the viewer needs at least one environment map")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    soup = mesh_soup(asset)
    texels = material_texels(asset)
    basis_data, layout = pack_basis(asset.basis)
    env_entries = []
    names = set()
    for i, env in enumerate(envmaps):
        small = downsample_envmap(env.radiance, env_height)
        texels_env, tables = env_tables(small)
        key = f"map{i}"
        names.add(env.name)
        body = np.concatenate([texels_env.reshape(-1), tables.reshape(-1)])
        entry = _write_bin(out / "env" / f"{key}.bin", body)
        entry.update({"name": env.name, "width": int(small.shape[1]), "height": int(small.shape[0]),
                      "mean_radiance": float(small.mean())})  # fmt: skip
        env_entries.append(entry)
    default = default_envmap if default_envmap in names else envmaps[0].name
    bundle = {
        "format": BUNDLE_FORMAT,
        "format_version": BUNDLE_VERSION,
        "name": asset.name,
        "mesh": {**_write_bin(out / "mesh.bin", soup), "corners": int(soup.shape[0]), "floats_per_corner": 11},
        "material": {**_write_bin(out / "material.bin", texels), "resolution": int(texels.shape[0]),
                     "channels": int(texels.shape[2])},
        "basis": {**_write_bin(out / "basis.bin", basis_data), **layout},
        "envmaps": env_entries,
        "default_envmap": default,
        "bounds_radius": float(np.linalg.norm(asset.mesh.vertices, axis=1).max()),
    }  # fmt: skip
    path = out / BUNDLE
    path.write_text(json.dumps(bundle, indent=1) + "\n")
    if static:
        for name in STATIC_FILES:
            shutil.copyfile(STATIC_DIR / name, out / name)
    return path


def shared_envmaps(folder: str | Path) -> list[EnvSource]:
    """Every usable EXR/HDR map in a folder (e.g. the shared CC0 maps), sorted by name."""
    folder = Path(folder)
    found = sorted(p for p in folder.glob("*") if p.suffix.lower() in (".exr", ".hdr"))
    return [EnvSource.from_file(p) for p in found]


def sky_envmap(height: int = 64) -> EnvSource:
    """A built-in soft sky (brighter above, a warm patch for a highlight) for when no map is at hand."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(2 * height) + 0.5) / (2 * height)
    theta, phi = np.meshgrid(math.pi * v, 2 * math.pi * u, indexing="ij")
    up = np.cos(theta)
    sky = 0.4 + 0.6 * np.clip(up, 0, 1)[..., None] * np.array([0.6, 0.8, 1.0])
    sun = np.exp(-((theta - 0.8) ** 2 + (phi - 2.0) ** 2) / 0.02)[..., None] * np.array([8.0, 7.0, 5.5])
    ground = np.where(up[..., None] < 0, 0.25, 1.0)
    return EnvSource("sky", ((sky + sun) * ground).astype(np.float32))


def torch_envmap(bundle_dir: str | Path, name: str) -> EnvironmentMap:
    """The map `name` exactly as the page sees it (downsampled), for renders to compare with the page."""
    bundle = json.loads((Path(bundle_dir) / BUNDLE).read_text())
    for entry in bundle["envmaps"]:
        if entry["name"] == name:
            h, w = entry["height"], entry["width"]
            raw = np.fromfile(Path(bundle_dir) / entry["file"], dtype="<f4")[: h * w * 4].reshape(h, w, 4)
            return EnvironmentMap(torch.from_numpy(raw[:, :, :3].copy()).numpy())
    raise ValueError(f"{bundle_dir}: the bundle has no map named {name!r}")
