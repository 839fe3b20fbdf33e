"""`neumatex export`: an asset's PBR fallback as GLB or USD, or its baked textures, into a folder."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from neumatex_core.assets.asset import MaterialAsset
from neumatex_core.assets.meshfile import write_obj
from neumatex_core.assets.package import (
    MESH,
    write_glb_fallback,
    write_pbr_textures,
    write_textures,
    write_usd_fallback,
)
from neumatex_core.assets.usd import usd_name

ExportFormat = Literal["glb", "usd", "textures"]


def export_asset(asset: MaterialAsset, fmt: ExportFormat, out_dir: str | Path) -> list[Path]:
    """Write `fmt` into out_dir; returns the files written.

    glb: <name>.glb (textures embedded). usd: <name>.usda + textures/pbr_*.png (paths relative to the .usda).
    textures: mesh.obj (with the uvs the textures use) + textures/ (base_color.exr, latent.exr, texel_mask.png,
    pbr_base_color.png, pbr_metallic_roughness.png)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = usd_name(asset.name)
    if fmt == "glb":
        return [write_glb_fallback(asset, out / f"{stem}.glb")]
    if fmt == "usd":
        return [write_usd_fallback(asset, out / f"{stem}.usda"), *write_pbr_textures(asset, out)]
    if fmt == "textures":
        write_obj(out / MESH, asset.mesh, asset.name)
        return [out / MESH, *write_textures(asset, out)]
    raise ValueError(f"--format: expected glb, usd or textures, got {fmt!r}")
