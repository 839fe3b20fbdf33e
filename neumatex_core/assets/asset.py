"""The in-memory material asset and how one is built from a material field on a mesh.

A `MaterialAsset` holds everything a package stores (docs/architecture.md section 8): the object-space mesh with
xatlas uvs, the neural field (a triplane with its decoders, or UV textures), the baked textures (rho_d + latent
[R, R, 3 + K], K the basis's latent size: 6 in the paper's), the PBR fallback textures ([R, R, 5], 8-bit exact),
previews, provenance, metrics and timings.
`field(source)` gives the renderable MaterialField of any of its representations.

    asset = asset_from_triplane("vase", mesh, TriplaneMaterialField(triplane, decoder, basis), resolution=512)
    write_asset(asset, "vase.nmx.zip"); asset = read_asset("vase.nmx.zip")
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import torch
from torch import nn

from neumatex_core.assets.bake import TexelSamples, bake, rasterize_uv
from neumatex_core.assets.pbr_fit import METHOD, PBRFitConfig, fit_pbr
from neumatex_core.assets.uv_unwrap import unwrap
from neumatex_core.fields.decoders import MaterialDecoder
from neumatex_core.fields.neural_field import TriplaneMaterialField
from neumatex_core.fields.triplane import Triplane
from neumatex_core.fields.uv_textures import PBRTextureField, UVTextureField, material_channels
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.materials.field import MaterialField
from neumatex_core.materials.neural_basis import NeuralBasis

Source = Literal["auto", "triplane", "textures", "pbr"]
FieldKind = Literal["triplane", "uv_textures"]


@dataclass
class MaterialAsset:
    """name; mesh (object space, in the unit sphere, with uvs and vertex normals); basis (frozen);
    material_texture [R, R, 3 + K] (rho_d in [0, 1], latent [K] in [-1, 1]); pbr_texture [R, R, 5] (base colour,
    roughness, metallic; 8-bit exact); triplane + decoders ("material" required with a triplane; "uncertainty", "pbr"
    optional) or None for a UV-texture asset; texel_mask [R, R] (texels on the surface); pbr_fit_loss: the loss of the
    fallback's fit to the neural material (`pbr_method` says whether the fallback is that fit); previews name ->
    display image [H, W, 3]; centre/scale: the capture mesh's normalisation (p_object = (p_capture - centre) *
    scale), if known."""

    name: str
    mesh: Mesh
    basis: NeuralBasis
    material_texture: torch.Tensor
    pbr_texture: torch.Tensor
    texel_mask: torch.Tensor
    triplane: Triplane | None = None
    decoders: dict[str, nn.Module] = field(default_factory=dict)
    pbr_fit_loss: float = float("nan")
    previews: dict[str, np.ndarray] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, float] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    centre: list[float] | None = None
    scale: float | None = None
    pbr_method: str = METHOD  # how the fallback was made (the manifest's pbr_fallback.method)

    @property
    def field_kind(self) -> FieldKind:
        return "triplane" if self.triplane is not None else "uv_textures"

    @property
    def texture_resolution(self) -> int:
        return int(self.material_texture.shape[0])

    def field(self, source: Source = "auto") -> MaterialField:
        """The asset's own field ("auto": triplane if it has one, else its textures), its baked neural textures
        ("textures") or its PBR fallback ("pbr")."""
        if source == "pbr":
            return PBRTextureField(self.pbr_texture)
        if source == "textures" or (source == "auto" and self.triplane is None):
            return UVTextureField(self.material_texture, self.basis)
        if self.triplane is None:
            raise ValueError(f"asset {self.name!r} has no triplane (its field is its UV textures)")
        decoder = self.decoders.get("material")
        if not isinstance(decoder, MaterialDecoder):
            raise ValueError(f"asset {self.name!r} has a triplane but no material decoder")
        return TriplaneMaterialField(self.triplane, decoder, self.basis)

    def to(self, device: torch.device | str) -> MaterialAsset:
        """The asset with its tensors and networks on `device`; the basis is moved (in place) only if it is
        elsewhere, so pass `read_asset` a basis of the right device (`load_basis(device)`) to keep it shared."""
        if next(self.basis.parameters()).device != torch.device(device):
            self.basis = self.basis.to(device)
        self.material_texture = self.material_texture.to(device)
        self.pbr_texture = self.pbr_texture.to(device)
        self.texel_mask = self.texel_mask.to(device)
        if self.triplane is not None:
            self.triplane = self.triplane.to(device)
        self.decoders = {k: v.to(device) for k, v in self.decoders.items()}
        return self


def _ensure_normals(mesh: Mesh) -> Mesh:
    return mesh if mesh.vertex_normals is not None else mesh.with_smooth_normals()


def bake_triplane(field_: TriplaneMaterialField, samples: TexelSamples,
                  device: torch.device | str = "cpu") -> torch.Tensor:
    """Texture [R, R, 3 + K] of the field's (rho_d, latent) at the texel samples (dilated); K: the basis's latent
    size."""
    return bake(samples, lambda p: torch.cat(field_.gbuffer(p), dim=-1), material_channels(field_.basis),
                device=device)


def asset_from_triplane(name: str, mesh: Mesh, field_: TriplaneMaterialField, resolution: int = 512,
                        pbr: PBRFitConfig | None = None, extra_decoders: dict[str, nn.Module] | None = None,
                        provenance: dict[str, Any] | None = None, metrics: dict[str, float] | None = None,
                        timings: dict[str, float] | None = None) -> MaterialAsset:
    """Unwrap `mesh` (object space) with xatlas, bake the triplane field to [resolution]^2 textures, fit the PBR
    fallback. The unwrapped mesh replaces `mesh` (same surface, seam vertices split)."""
    device = field_.triplane.planes.device
    timings = dict(timings or {})
    t0 = time.perf_counter()
    uv_mesh = unwrap(_ensure_normals(mesh), resolution)
    t1 = time.perf_counter()
    samples = rasterize_uv(uv_mesh, resolution)
    material = bake_triplane(field_, samples, device)
    t2 = time.perf_counter()
    mask = torch.from_numpy(samples.mask).to(device)
    pbr_texture, loss = fit_pbr(field_.basis, material, mask, pbr)
    t3 = time.perf_counter()
    timings.update({"uv_unwrap_s": t1 - t0, "bake_s": t2 - t1, "pbr_fit_s": t3 - t2})
    decoders: dict[str, nn.Module] = {"material": field_.decoder, **(extra_decoders or {})}
    return MaterialAsset(name, uv_mesh, field_.basis, material, pbr_texture, mask, field_.triplane, decoders, loss,
                         provenance=dict(provenance or {}), metrics=dict(metrics or {}), timings=timings)


def asset_from_textures(name: str, mesh: Mesh, material_texture: torch.Tensor, basis: NeuralBasis,
                        pbr: PBRFitConfig | None = None, provenance: dict[str, Any] | None = None,
                        metrics: dict[str, float] | None = None,
                        timings: dict[str, float] | None = None) -> MaterialAsset:
    """A UV-texture asset: `mesh` must carry the uvs the texture [R, R, 3 + K] was made for (e.g. TTO's UV ablation)."""
    if mesh.uvs is None:
        raise ValueError("a UV-texture asset needs a mesh with uvs")
    timings = dict(timings or {})
    r = int(material_texture.shape[0])
    mask = torch.from_numpy(rasterize_uv(mesh, r).mask).to(material_texture.device)
    t0 = time.perf_counter()
    pbr_texture, loss = fit_pbr(basis, material_texture.detach(), mask, pbr)
    timings["pbr_fit_s"] = time.perf_counter() - t0
    return MaterialAsset(name, _ensure_normals(mesh), basis, material_texture.detach(), pbr_texture, mask, None, {},
                         loss, provenance=dict(provenance or {}), metrics=dict(metrics or {}), timings=timings)
