"""Neural material asset packages (docs/architecture.md section 8): build, write, read, export, render.

- `asset.py`: `MaterialAsset` and `asset_from_triplane` / `asset_from_textures` (unwrap, bake, PBR fit);
- `package.py`: `write_asset` / `read_asset` (folder or zip; manifest, hashes, basis check);
- `manifest.py`: the manifest schema, FORMAT_VERSION, `AssetError`;
- `uv_unwrap.py` (xatlas), `bake.py` (UV rasterisation, dilation), `pbr_fit.py` (PBR fallback fit);
- `gltf.py` (GLB), `usd.py` (UsdPreviewSurface), `export.py` (`neumatex export`), `render.py` (renders, previews).
"""

from neumatex_core.assets.asset import MaterialAsset, asset_from_textures, asset_from_triplane
from neumatex_core.assets.manifest import FORMAT_VERSION, AssetError, Manifest
from neumatex_core.assets.package import read_asset, read_manifest, write_asset

__all__ = [
    "FORMAT_VERSION",
    "AssetError",
    "Manifest",
    "MaterialAsset",
    "asset_from_textures",
    "asset_from_triplane",
    "read_asset",
    "read_manifest",
    "write_asset",
]
