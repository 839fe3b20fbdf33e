"""Writing and reading material asset packages: a folder or a zip of the same files (docs/architecture.md section 8).

    manifest.json                     format version, basis id + hash, field kind and shape, decoder ids,
                                      provenance, metrics, timings, every file's SHA-256 and size
    mesh.obj                          object-space mesh with xatlas uvs and normals (float32-exact)
    tensors.safetensors               triplane planes [3, C, R, R] and decoder weights (triplane assets)
    textures/base_color.exr           rho_d [R, R, 3], linear float32
    textures/latent.exr               latent [R, R, K] in [-1, 1], float32, channels l0..l5 (K: the basis's
                                      latent size, 6 in the paper's basis; l00..l15 for 16)
    textures/texel_mask.png           texels on the surface (255) vs dilation padding (0)
    textures/pbr_base_color.png       PBR fallback base colour, sRGB 8-bit
    textures/pbr_metallic_roughness.png  glTF layout: G roughness, B metallic (linear 8-bit)
    fallback.glb                      glTF 2.0 of the PBR fallback (textures embedded)
    fallback.usda                     USD with a UsdPreviewSurface reading the PNGs above
    previews/*.png                    preview renders (neural and PBR), if made

`write_asset(asset, path)` writes a zip when path ends in .zip, else a folder (atomically: a temporary sibling
renamed into place). `read_asset(path)` checks the manifest version, that every listed file is there and unchanged,
and that this installation has the neural basis the asset names; every failure is an AssetError naming the file.
A read asset renders bit for bit like the written one (same device and seed): every stored value is exact.
"""

from __future__ import annotations

import datetime as _dt
import importlib.metadata
import os
import shutil
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import torch
from torch import nn

from neumatex_core.assets.asset import MaterialAsset
from neumatex_core.assets.gltf import png_bytes, write_glb
from neumatex_core.assets.manifest import (
    MANIFEST,
    AssetError,
    BasisRecord,
    DecoderRecord,
    FallbackRecord,
    FieldRecord,
    FileRecord,
    Manifest,
    MeshRecord,
    TextureRecord,
    parse_manifest,
)
from neumatex_core.assets.meshfile import read_obj, write_obj
from neumatex_core.assets.pbr_fit import (
    decode_linear8,
    decode_srgb8,
    encode_linear8,
    encode_srgb8,
)
from neumatex_core.assets.usd import write_usd
from neumatex_core.fields.decoders import DECODERS, module_id
from neumatex_core.fields.triplane import Triplane
from neumatex_core.hashing import sha256_file
from neumatex_core.materials.neural_basis import (
    BasisError,
    NeuralBasis,
    check_basis_id,
    latent_channel_names,
    load_basis,
)

MESH = "mesh.obj"
TENSORS = "tensors.safetensors"
BASE_COLOR = "textures/base_color.exr"
LATENT = "textures/latent.exr"
MASK = "textures/texel_mask.png"
PBR_BASE = "textures/pbr_base_color.png"
PBR_MR = "textures/pbr_metallic_roughness.png"
GLB = "fallback.glb"
USD = "fallback.usda"
_STORED = (".png", ".exr", ".glb")  # already compressed: stored as is in zips


def neumatex_version() -> str:
    try:
        return importlib.metadata.version("neumatex")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


# -- texture files -------------------------------------------------------------------------------------------
def write_exr(path: Path, pixels: np.ndarray, channels: tuple[str, ...] | None = None) -> None:
    """float32 [H, W, C] EXR (zip compression: lossless), with channel names if given. Written by
    `imageio.write_image`, which leaves out EXR's time stamp: the same texture gives the same bytes, so an asset's
    manifest (its files' SHA-256) is the same for the same material."""
    from neumatex_core.imageio import ImageError, write_image

    try:
        write_image(path, np.asarray(pixels, dtype=np.float32), channels)
    except ImageError as exc:
        raise AssetError(str(exc)) from None


def read_exr(path: Path, label: str, channels: int, resolution: int) -> np.ndarray:
    from neumatex_core.imageio import read_image

    try:
        pixels = read_image(path)
    except ValueError as exc:
        raise AssetError(f"{label}: {exc}") from None
    if pixels.shape != (resolution, resolution, channels):
        raise AssetError(f"{label}: expected a {resolution}x{resolution} image with {channels} channels, got "
                         f"{pixels.shape[1]}x{pixels.shape[0]} with {pixels.shape[2]}")
    return pixels


def read_png8(path: Path, label: str) -> np.ndarray:
    """uint8 [H, W, C] codes of a PNG, exactly."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            arr = np.asarray(im)
    except (OSError, UnidentifiedImageError) as exc:
        raise AssetError(f"{label}: cannot be read as a PNG ({exc})") from None
    if arr.dtype != np.uint8:
        raise AssetError(f"{label}: expected 8-bit pixels, got {arr.dtype}")
    return arr if arr.ndim == 3 else arr[:, :, None]


def pbr_pngs(pbr_texture: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(base colour sRGB codes [R, R, 3], metallic-roughness codes [R, R, 3] = (0, roughness, metallic))."""
    t = pbr_texture.detach().cpu()
    base = encode_srgb8(t[..., :3]).numpy()
    rm = encode_linear8(t[..., 3:5]).numpy()
    mr = np.stack([np.zeros_like(rm[..., 0]), rm[..., 0], rm[..., 1]], axis=-1)
    return base, mr


def write_pbr_textures(asset: MaterialAsset, root: Path) -> list[Path]:
    """The PBR fallback PNGs (textures/pbr_base_color.png, textures/pbr_metallic_roughness.png) under root."""
    (root / "textures").mkdir(parents=True, exist_ok=True)
    base, mr = pbr_pngs(asset.pbr_texture)
    (root / PBR_BASE).write_bytes(png_bytes(base))
    (root / PBR_MR).write_bytes(png_bytes(mr))
    return [root / PBR_BASE, root / PBR_MR]


def write_textures(asset: MaterialAsset, root: Path) -> list[Path]:
    """Every texture file (EXR + PNG) of the package layout under root."""
    (root / "textures").mkdir(parents=True, exist_ok=True)
    mat = asset.material_texture.detach().cpu().numpy()
    write_exr(root / BASE_COLOR, mat[..., :3], ("R", "G", "B"))
    write_exr(root / LATENT, mat[..., 3:], latent_channel_names(asset.basis.arch.latent_dim))
    (root / MASK).write_bytes(png_bytes(asset.texel_mask.cpu().numpy().astype(np.uint8) * 255))
    return [root / BASE_COLOR, root / LATENT, root / MASK, *write_pbr_textures(asset, root)]


def write_glb_fallback(asset: MaterialAsset, path: Path) -> Path:
    """The PBR fallback as one GLB file (textures embedded)."""
    base, mr = pbr_pngs(asset.pbr_texture)
    extras = {"basis_id": asset.basis.basis_id, "asset": asset.name, "neural_material": MANIFEST}
    write_glb(path, asset.mesh, png_bytes(base), png_bytes(mr), asset.name, extras)
    return path


def write_usd_fallback(asset: MaterialAsset, path: Path) -> Path:
    """The PBR fallback as USD; it reads the PNGs of `write_pbr_textures` under path's folder."""
    write_usd(path, asset.mesh, PBR_BASE, PBR_MR, asset.name)
    return path


# -- writing -------------------------------------------------------------------------------------------------
def _tensors(asset: MaterialAsset) -> dict[str, torch.Tensor]:
    assert asset.triplane is not None
    out = {"triplane.planes": asset.triplane.planes.detach().cpu().float().contiguous()}
    for kind, dec in asset.decoders.items():
        for k, v in dec.state_dict().items():
            out[f"decoder.{kind}.{k}"] = v.detach().cpu().float().contiguous()
    return out


def _write_folder(asset: MaterialAsset, root: Path) -> Manifest:
    from safetensors.torch import save_file

    from neumatex_core.imageio import write_image

    root.mkdir(parents=True)
    write_obj(root / MESH, asset.mesh, asset.name)
    decoders: dict[str, DecoderRecord] = {}
    if asset.triplane is not None:
        save_file(_tensors(asset), str(root / TENSORS), metadata={"format": "neumatex-material-asset"})
        # safetensors writes through a private (0600) temporary file; give the tensors the mode of the other files
        (root / TENSORS).chmod((root / MESH).stat().st_mode & 0o777)
        for kind, dec in asset.decoders.items():
            if kind not in DECODERS or not isinstance(dec, DECODERS[kind]):
                raise AssetError(f"decoder {kind!r}: expected one of {sorted(DECODERS)} ({type(dec).__name__})")
            decoders[kind] = DecoderRecord(id=module_id(dec), architecture=dec.architecture())
        shape = list(asset.triplane.planes.shape)
    else:
        shape = list(asset.material_texture.shape)
    write_textures(asset, root)
    write_glb_fallback(asset, root / GLB)
    write_usd_fallback(asset, root / USD)
    previews = []
    for name, img in sorted(asset.previews.items()):
        rel = f"previews/{name}.png"
        write_image(root / rel, img)
        previews.append(rel)
    files = {}
    for p in sorted(root.rglob("*")):
        if p.is_file():
            files[p.relative_to(root).as_posix()] = FileRecord(sha256=sha256_file(p), bytes=p.stat().st_size)
    manifest = Manifest(
        writer=f"neumatex {neumatex_version()}",
        created=_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        name=asset.name,
        basis=BasisRecord(basis_id=asset.basis.basis_id, content_hash=asset.basis.content_hash),
        field=FieldRecord(kind=asset.field_kind, shape=shape, tensors=TENSORS if asset.triplane is not None else None),
        decoders=decoders,
        mesh=MeshRecord(path=MESH, vertices=len(asset.mesh.vertices), faces=asset.mesh.num_faces,
                        uv_unwrap="xatlas", centre=asset.centre, scale=asset.scale),
        textures=TextureRecord(resolution=asset.texture_resolution, base_color=BASE_COLOR, latent=LATENT, mask=MASK,
                               pbr_base_color=PBR_BASE, pbr_metallic_roughness=PBR_MR),
        pbr_fallback=FallbackRecord(gltf=GLB, usd=USD, method=asset.pbr_method,
                                    fit_loss=asset.pbr_fit_loss),
        previews=previews,
        provenance=asset.provenance,
        metrics=asset.metrics,
        timings=asset.timings,
        files=files,
    )  # fmt: skip
    (root / MANIFEST).write_text(manifest.model_dump_json(indent=2) + "\n")
    return manifest


def write_asset(asset: MaterialAsset, path: str | Path, overwrite: bool = False) -> Path:
    """Write the package to `path` (a .zip file, or else a folder); returns path. AssetError if it exists and
    not `overwrite`."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise AssetError(f"{path}: already exists (pass overwrite=True to replace it)")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        staging = tmp / "asset"
        _write_folder(asset, staging)
        if path.suffix.lower() == ".zip":
            tmp_zip = tmp / "asset.zip"
            with zipfile.ZipFile(tmp_zip, "w") as zf:
                for p in sorted(staging.rglob("*")):
                    if p.is_file():
                        rel = p.relative_to(staging).as_posix()
                        mode = zipfile.ZIP_STORED if p.suffix in _STORED else zipfile.ZIP_DEFLATED
                        zf.write(p, rel, compress_type=mode)
            if path.exists():
                path.unlink() if path.is_file() else shutil.rmtree(path)
            os.replace(tmp_zip, path)
        else:
            if path.exists():
                shutil.rmtree(path) if path.is_dir() else path.unlink()
            os.replace(staging, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


# -- reading -------------------------------------------------------------------------------------------------
def _check_files(root: Path, manifest: Manifest, label: str) -> None:
    for rel, rec in manifest.files.items():
        p = root / rel
        if not p.is_file():
            raise AssetError(f"{label}/{rel}: missing (listed in {MANIFEST}); the package is incomplete")
        if p.stat().st_size != rec.bytes or sha256_file(p) != rec.sha256:
            raise AssetError(f"{label}/{rel}: does not match the SHA-256 in {MANIFEST} (damaged or modified)")
    required = [manifest.mesh.path, manifest.textures.base_color, manifest.textures.latent, manifest.textures.mask,
                manifest.textures.pbr_base_color, manifest.textures.pbr_metallic_roughness]
    if manifest.field.kind == "triplane":
        required.append(manifest.field.tensors or TENSORS)
    for rel in required:
        if rel not in manifest.files:
            raise AssetError(f"{label}/{MANIFEST}: does not list {rel}, which a {manifest.field.kind} asset needs")


def _load_triplane(root: Path, manifest: Manifest, label: str) -> tuple[Triplane, dict[str, nn.Module]]:
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    rel = manifest.field.tensors or TENSORS
    try:
        tensors = load_file(str(root / rel))
    except (SafetensorError, OSError) as exc:
        raise AssetError(f"{label}/{rel}: cannot be read ({exc})") from None
    planes = tensors.get("triplane.planes")
    if planes is None or list(planes.shape) != manifest.field.shape:
        got = None if planes is None else list(planes.shape)
        raise AssetError(f"{label}/{rel}: triplane.planes has shape {got}, the manifest says {manifest.field.shape}")
    triplane = Triplane.from_planes(planes)
    triplane.requires_grad_(False)
    decoders: dict[str, nn.Module] = {}
    for kind, rec in manifest.decoders.items():
        if kind not in DECODERS:
            raise AssetError(f"{label}/{MANIFEST}: unknown decoder kind {kind!r} (known: {sorted(DECODERS)})")
        try:
            dec = DECODERS[kind](**rec.architecture)
        except TypeError as exc:
            raise AssetError(f"{label}/{MANIFEST}: decoder {kind!r} architecture {rec.architecture} ({exc})") from None
        prefix = f"decoder.{kind}."
        state = {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}
        try:
            dec.load_state_dict(state)
        except RuntimeError as exc:
            raise AssetError(f"{label}/{rel}: decoder {kind!r} weights do not fit its architecture ({exc})") from None
        if module_id(dec) != rec.id:
            raise AssetError(f"{label}/{rel}: decoder {kind!r} is {module_id(dec)}, the manifest names {rec.id}")
        dec.requires_grad_(False)
        decoders[kind] = dec.eval()
    if "material" not in decoders:
        raise AssetError(f"{label}/{MANIFEST}: a triplane asset needs a 'material' decoder")
    return triplane, decoders


def _read_root(root: Path, label: str, basis: NeuralBasis) -> MaterialAsset:
    manifest = parse_manifest(root / MANIFEST, f"{label}/{MANIFEST}")
    _check_files(root, manifest, label)
    try:
        basis = check_basis_id(manifest.basis.basis_id, manifest.basis.content_hash, basis)
    except BasisError as exc:
        raise AssetError(f"{label}/{MANIFEST}: {exc}") from None
    mesh = read_obj(root / manifest.mesh.path, f"{label}/{manifest.mesh.path}")
    tex = manifest.textures
    r = tex.resolution
    rho = read_exr(root / tex.base_color, f"{label}/{tex.base_color}", 3, r)
    lat = read_exr(root / tex.latent, f"{label}/{tex.latent}", basis.arch.latent_dim, r)
    material = torch.from_numpy(np.concatenate([rho, lat], axis=-1))
    mask = torch.from_numpy(read_png8(root / tex.mask, f"{label}/{tex.mask}")[..., 0] > 127)
    base = read_png8(root / tex.pbr_base_color, f"{label}/{tex.pbr_base_color}")
    mr = read_png8(root / tex.pbr_metallic_roughness, f"{label}/{tex.pbr_metallic_roughness}")
    for rel, arr in ((tex.mask, mask), (tex.pbr_base_color, base), (tex.pbr_metallic_roughness, mr)):
        if tuple(arr.shape[:2]) != (r, r):
            raise AssetError(f"{label}/{rel}: expected {r}x{r} pixels, got {arr.shape[1]}x{arr.shape[0]}")
    pbr = torch.cat([decode_srgb8(torch.from_numpy(base[..., :3].copy())),
                     decode_linear8(torch.from_numpy(mr[..., 1:3].copy()))], dim=-1)  # fmt: skip
    triplane: Triplane | None = None
    decoders: dict[str, nn.Module] = {}
    if manifest.field.kind == "triplane":
        triplane, decoders = _load_triplane(root, manifest, label)
    previews = {}
    for rel in manifest.previews:
        previews[Path(rel).stem] = read_png8(root / rel, f"{label}/{rel}")[..., :3].astype(np.float32) / 255
    return MaterialAsset(manifest.name, mesh, basis, material, pbr, mask, triplane, decoders,
                         manifest.pbr_fallback.fit_loss, previews, dict(manifest.provenance),
                         dict(manifest.metrics), dict(manifest.timings), manifest.mesh.centre, manifest.mesh.scale,
                         manifest.pbr_fallback.method)  # fmt: skip


def read_manifest(path: str | Path) -> Manifest:
    """Only the manifest of a package (folder or zip), checked for format and version."""
    path = Path(path)
    if path.is_file():
        try:
            with zipfile.ZipFile(path) as zf, tempfile.TemporaryDirectory() as tmp:
                target = Path(tmp) / MANIFEST
                try:
                    target.write_bytes(zf.read(MANIFEST))
                except KeyError:
                    raise AssetError(f"{path.name}:{MANIFEST}: missing; not a NeuMatEx material asset") from None
                return parse_manifest(target, f"{path.name}:{MANIFEST}")
        except zipfile.BadZipFile as exc:
            raise AssetError(f"{path}: not a zip archive or asset folder ({exc})") from None
    return parse_manifest(path / MANIFEST, f"{path}/{MANIFEST}")


def read_asset(path: str | Path, basis: NeuralBasis | None = None,
               device: torch.device | str = "cpu") -> MaterialAsset:
    """Read a package (folder or .zip); `basis` defaults to the shipped one. AssetError naming the file on any
    problem (future format version, missing or damaged file, a basis this installation does not have)."""
    from neumatex_core.capture.archive import extract_zip

    path = Path(path)
    if basis is None:
        try:
            basis = load_basis(str(torch.device(device)))
        except BasisError as exc:
            raise AssetError(f"{path}: cannot load this installation's neural basis ({exc})") from None
    if path.is_dir():
        return _read_root(path, str(path), basis).to(device)
    if not path.exists():
        raise AssetError(f"{path}: asset not found (expected a package folder or .zip)")
    if not zipfile.is_zipfile(path):
        raise AssetError(f"{path}: not a zip archive or asset folder")
    with tempfile.TemporaryDirectory(prefix="neumatex-asset-") as tmp:
        try:
            root = extract_zip(path, Path(tmp) / "asset")
        except ValueError as exc:
            raise AssetError(f"{path}: {exc}") from None
        return _read_root(root, path.name, basis).to(device)
