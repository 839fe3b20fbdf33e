"""The asset manifest (`manifest.json`): what a package holds, which basis decodes it, where it came from.

Schema (pydantic; version FORMAT_VERSION). Files are listed with SHA-256 and size, so a reader can tell a
missing or damaged file from a bad format. A manifest whose `format_version` is newer than this code's is
refused before anything else is read (a newer writer may have changed what the files mean); older versions are
upgraded by `MIGRATIONS` (none yet: version 1 is the first).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, Field, ValidationError

FORMAT: Literal["neumatex-material-asset"] = "neumatex-material-asset"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"


class AssetError(ValueError):
    """An asset that cannot be written or read; the message names the file and the reason."""


class FileRecord(BaseModel):
    sha256: str
    bytes: int


class BasisRecord(BaseModel):
    basis_id: str
    content_hash: str


class FieldRecord(BaseModel):
    """kind "triplane": planes [3, C, R, R] in `tensors` (with the material decoder); kind "uv_textures": the
    baked textures are the field. bounds: the cube the triplane covers (object space)."""

    kind: Literal["triplane", "uv_textures"]
    shape: list[int]
    tensors: str | None = None
    bounds: tuple[float, float] = (-1.0, 1.0)


class DecoderRecord(BaseModel):
    id: str
    architecture: dict[str, int]


class MeshRecord(BaseModel):
    """The object-space mesh (unit sphere) with xatlas uvs; `to_capture` maps it back: p_capture = p / scale +
    centre (from the capture's mesh normalisation), when known."""

    path: str
    vertices: int
    faces: int
    uv_unwrap: str
    centre: list[float] | None = None
    scale: float | None = None


class TextureRecord(BaseModel):
    """Baked UV textures (v up, row 0 at v = 1): rho_d and latent as float32 EXR; the PBR fallback as 8-bit PNG
    (base colour sRGB; metallic-roughness with roughness in G and metallic in B, linear, as glTF)."""

    resolution: int
    base_color: str
    latent: str
    mask: str
    pbr_base_color: str
    pbr_metallic_roughness: str


class FallbackRecord(BaseModel):
    gltf: str
    usd: str
    method: str
    fit_loss: float  # the loss of the fit to the neural material (method says whether the fallback is that fit)


class Manifest(BaseModel):
    format: Literal["neumatex-material-asset"] = FORMAT
    format_version: int = FORMAT_VERSION
    writer: str
    created: str
    name: str
    basis: BasisRecord
    field: FieldRecord
    decoders: dict[str, DecoderRecord] = Field(default_factory=dict)
    mesh: MeshRecord
    textures: TextureRecord
    pbr_fallback: FallbackRecord
    previews: list[str] = Field(default_factory=list)
    provenance: dict[str, Any] = Field(default_factory=dict)
    metrics: dict[str, float] = Field(default_factory=dict)
    timings: dict[str, float] = Field(default_factory=dict)
    files: dict[str, FileRecord] = Field(default_factory=dict)


# from_version -> function upgrading the raw JSON to from_version + 1
MIGRATIONS: dict[int, Callable[[dict[str, Any]], dict[str, Any]]] = {}


def parse_manifest(path: Path, label: str) -> Manifest:
    """Read and check `path`; `label` names it in errors (e.g. 'asset.zip:manifest.json')."""
    try:
        raw = json.loads(path.read_text())
    except FileNotFoundError:
        raise AssetError(f"{label}: missing; not a NeuMatEx material asset") from None
    except (OSError, ValueError) as exc:
        raise AssetError(f"{label}: not readable JSON ({exc})") from None
    if not isinstance(raw, dict) or raw.get("format") != FORMAT:
        raise AssetError(f"{label}: not a NeuMatEx material asset (format is {raw.get('format')!r}, "
                         f"expected {FORMAT!r})" if isinstance(raw, dict) else f"{label}: not a JSON object")
    version = raw.get("format_version")
    if not isinstance(version, int) or version < 1:
        raise AssetError(f"{label}: format_version {version!r} is not a positive integer")
    if version > FORMAT_VERSION:
        raise AssetError(f"{label}: written with asset format version {version} by {raw.get('writer', 'a newer')} "
                         f"NeuMatEx; this installation reads versions up to {FORMAT_VERSION}: upgrade NeuMatEx")
    while version < FORMAT_VERSION:
        if version not in MIGRATIONS:
            raise AssetError(f"{label}: asset format version {version} is no longer supported (no upgrade path)")
        raw = MIGRATIONS[version](raw)
        version += 1
        raw["format_version"] = version
    try:
        return Manifest.model_validate(raw)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors())
        raise AssetError(f"{label}: invalid manifest ({problems})") from None
