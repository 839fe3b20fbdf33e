"""The LMRM network (docs/architecture.md section 5): preset views + known geometry -> feature triplane -> decoders.

Per object, for each of the V views (V = 23 preset views, any V >= 1 works):

1. `view_inputs` builds per-pixel input channels [V, IN_CHANNELS, H, W]: the tonemapped view (sRGB), the
   coverage mask, the G-buffer normal and the unit direction to the camera (world space), the pre-filtered
   lighting cues (diffuse at the normal, three glossy widths at the mirror direction, squashed c / (1 + c)), the
   ratio of the linear pixel to the diffuse cue (a shading-normalised colour, /3) and a "lighting known" flag.
   Uncovered pixels are zero.
2. A small per-view CNN (`ViewEncoder`, 3x3 convolutions) maps them to per-pixel features [V, F, H, W].
3. Lifting: covered pixels carry their surface point (position G-buffer); each plane k of the triplane (XY, YZ,
   XZ) gets the scatter-mean of the features of the points falling into each of its R x R texels, their mean
   square (view-dependent effects, e.g. highlights, raise it) and log(1 + count) (`lift_to_planes`). With
   `LMRMConfig.angle_bins` also the mean per texel within each bin of the viewing angle's cosine n . v
   (`angle_bin`, `lift_binned`): how a point looks head-on against at grazing angles, which a sheen, dust or a
   coat's Fresnel change and a plain diffuse base does not. With `LMRMConfig.gloss_bins` also per bin of how bright
   the sharp reflection of the lighting is against the diffuse light at the pixel (`gloss_bin`): a coat or a metal
   follows the reflected light, a diffuse base does not.
4. A shared U-Net (`PlaneNet`, with a one-hot plane-id input and the mean feature of all the object's points as
   global context at every texel) turns the three lifted planes into the triplane [3, C, R, R]. With
   `LMRMConfig.ratio_path` its first `RATIO_PATH_CHANNELS` channels are instead the lifted per-texel mean and mean
   square of the shading-normalised colour itself (a fixed colour path to the decoders, nothing learnt; the U-Net
   makes the other C - 6; docs/lmrm.md). With `LMRMConfig.ratio_bins` the triplane's last channels are the
   shading-normalised colour's own binned lifts (per angle bin, then per gloss bin: the bin's mean RGB and log
   count), fixed like the colour path, so the decoders read how the colour changes with the angle directly
   (measured: no gain; docs/lmrm.md).
5. Decoders from `neumatex_core.fields`: `MaterialDecoder` (rho_d, latent), `UncertaintyDecoder` (9 log-variances),
   `PBRDecoder` (base colour, roughness, metallic), all reading `Triplane.features(points)` [N, 3C]. With
   `LMRMConfig.family_head` a `FamilyDecoder` also reads them: the logits of the point's material family, a training
   signal meant to make the triplane tell the families apart (measured: no gain; docs/lmrm.md).

`LMRMConfig` sizes everything; `LMRMConfig.preset("gpu")` is the larger configuration of the same code.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal, get_args

import torch
import torch.nn.functional as F
from torch import nn
from torch.func import functional_call

from neumatex_core.capture.tonemap import srgb_eotf
from neumatex_core.config import check_known_keys
from neumatex_core.fields.decoders import FamilyDecoder, MaterialDecoder, PBRDecoder, UncertaintyDecoder
from neumatex_core.fields.triplane import PLANE_AXES, Triplane
from neumatex_core.lighting.prefilter import KAPPAS

N_CUES = 3 * (1 + len(KAPPAS))  # diffuse RGB + glossy RGB per lobe width
NORMAL_INPUT, TO_CAMERA_INPUT = slice(4, 7), slice(7, 10)  # view_inputs' world normal and direction to the camera
CUE_INPUT = slice(TO_CAMERA_INPUT.stop, TO_CAMERA_INPUT.stop + N_CUES)  # squashed cues: diffuse, then glossy by KAPPAS
# gloss_bin's edges on log(sharpest glossy cue / diffuse cue), mean over RGB: the terciles over 100 training objects
GLOSS_EDGES = (-1.45, -0.36)
RATIO_INPUT = slice(CUE_INPUT.stop, CUE_INPUT.stop + 3)  # the ratio's channels in view_inputs
IN_CHANNELS = RATIO_INPUT.stop + 1  # image, mask, normal, to-camera, cues, ratio, lighting flag
RATIO_MAX = 3.0  # linear pixel / diffuse cue is clipped to [0, RATIO_MAX] and divided by it
# LMRMConfig.preset's names
LMRMPreset = Literal["cpu", "cpu-ratio", "cpu-family", "cpu-angle", "cpu-angle-gloss", "cpu-angle-ratio", "gpu",
                     "test"]
LMRM_PRESETS: tuple[str, ...] = get_args(LMRMPreset)
RATIO_PATH_CHANNELS = 6  # LMRMConfig.ratio_path: the lifted ratio's mean and mean square (RGB each)
RATIO_BIN_CHANNELS = 4  # LMRMConfig.ratio_bins, per bin: the lifted ratio's mean (RGB) and log(1 + count) / 5


@dataclass
class LMRMConfig:
    """Sizes of the LMRM (defaults: the CPU model, trained in about 40 minutes on one core)."""

    view_resolution: int = 64  # views are resampled to this size (pixels, square) before encoding
    view_channels: int = 24  # hidden width of the per-view CNN
    view_layers: int = 2  # 3x3 convolutions in the per-view CNN
    feature_channels: int = 16  # per-pixel features lifted into the planes (F)
    plane_resolution: int = 48  # R
    plane_channels: int = 32  # width of the plane U-Net (doubled at its lower levels)
    triplane_channels: int = 16  # C
    decoder_hidden: int = 64
    decoder_layers: int = 2
    # the triplane's first RATIO_PATH_CHANNELS channels hold the lifted shading-normalised colour (module docstring,
    # step 4): an MLP on those statistics alone beats the learnt path on the test split (docs/lmrm.md)
    ratio_path: bool = False
    # a fourth decoder classifies each point's material family (FAMILIES), trained with cross-entropy: the latents'
    # error is mostly which family a region is; the head did not reduce it (docs/lmrm.md)
    family_head: bool = False
    # > 0: the per-view features are also lifted per bin of n . v (`angle_bin`, module docstring step 3), this
    # many bins of equal width in the cosine over [0, 1]
    angle_bins: int = 0
    # the per-view features also lifted per bin of `gloss_bin` (len(GLOSS_EDGES) + 1 bins; module docstring step 3)
    gloss_bins: bool = False
    # with ratio_path and bins: the ratio's own lifts per bin as the triplane's last channels (module docstring, step
    # 4), RATIO_BIN_CHANNELS per bin of angle_bins and gloss_bins
    ratio_bins: bool = False

    def __post_init__(self) -> None:
        if self.ratio_bins and not (self.ratio_path and self.n_bins):
            raise ValueError("LMRM ratio_bins lifts the colour path per bin: it needs ratio_path and angle_bins or "
                             "gloss_bins")
        if self.triplane_channels <= self.fixed_channels:
            raise ValueError(f"LMRM ratio_path / ratio_bins take {self.fixed_channels} of the triplane's channels: "
                             f"it needs triplane_channels > {self.fixed_channels}, got {self.triplane_channels}")

    @property
    def n_bins(self) -> int:
        """Bins the features are lifted in besides the plain lift: angle_bins, then gloss_bin's."""
        return self.angle_bins + (len(GLOSS_EDGES) + 1 if self.gloss_bins else 0)

    @property
    def fixed_channels(self) -> int:
        """Triplane channels that are lifted statistics, not the U-Net's output (ratio_path's, ratio_bins')."""
        return ((RATIO_PATH_CHANNELS if self.ratio_path else 0)
                + (RATIO_BIN_CHANNELS * self.n_bins if self.ratio_bins else 0))  # fmt: skip

    @classmethod
    def preset(cls, name: str) -> LMRMConfig:
        """The named config (`LMRM_PRESET_FIELDS`): 'cpu' (the defaults), 'cpu-ratio' (the same with the fixed colour
        path, `ratio_path`), 'cpu-family' (cpu-ratio with the family head, `family_head`), 'cpu-angle' (cpu-ratio
        with the features also lifted per viewing angle, `angle_bins`), 'cpu-angle-gloss' (cpu-angle with the
        features also lifted per brightness of the reflected light, `gloss_bins`), 'cpu-angle-ratio' (cpu-angle with
        the colour path also per angle bin, `ratio_bins`, 12 more triplane channels), 'gpu' (about 30x the
        compute: larger views, planes and widths) or 'test' (a few thousand parameters, for unit tests)."""
        if name not in LMRM_PRESET_FIELDS:
            raise ValueError(f"unknown LMRM preset {name!r} (expected one of {', '.join(LMRM_PRESETS)})")
        return cls(**LMRM_PRESET_FIELDS[name])

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LMRMConfig:
        check_known_keys(cls, data, "LMRM config")
        return cls(**data)

    def to_dict(self) -> dict[str, Any]:
        """The fields; `ratio_path`, `family_head`, `angle_bins`, `gloss_bins` and `ratio_bins` only when on, so the
        records of models made before them stay as they are."""
        out = asdict(self)
        for flag in ("ratio_path", "family_head", "angle_bins", "gloss_bins", "ratio_bins"):
            if not out[flag]:
                del out[flag]
        return out


# LMRMConfig.preset: each preset's fields over the defaults (the CPU model)
LMRM_PRESET_FIELDS: dict[str, dict[str, Any]] = {
    "cpu": {},
    "cpu-ratio": {"ratio_path": True},
    "cpu-family": {"ratio_path": True, "family_head": True},
    "cpu-angle": {"ratio_path": True, "angle_bins": 3},
    "cpu-angle-gloss": {"ratio_path": True, "angle_bins": 3, "gloss_bins": True},
    "cpu-angle-ratio": {"ratio_path": True, "angle_bins": 3, "ratio_bins": True,
                        "triplane_channels": 16 + 3 * RATIO_BIN_CHANNELS},
    "gpu": {"view_resolution": 128, "view_channels": 64, "view_layers": 3, "feature_channels": 32,
            "plane_resolution": 96, "plane_channels": 64, "triplane_channels": 32, "decoder_hidden": 128},
    "test": {"view_resolution": 24, "view_channels": 8, "view_layers": 1, "feature_channels": 4, "plane_resolution": 8,
             "plane_channels": 8, "triplane_channels": 4, "decoder_hidden": 16, "decoder_layers": 1},
}
assert set(LMRM_PRESET_FIELDS) == set(LMRM_PRESETS)  # the names are written once, in LMRMPreset


def view_inputs(
    rgb: torch.Tensor, mask: torch.Tensor, normal: torch.Tensor, to_camera: torch.Tensor,
    cues: torch.Tensor | None,
) -> torch.Tensor:
    """Per-pixel network inputs [V, IN_CHANNELS, H, W].

    rgb [V, H, W, 3] tonemapped sRGB in [0, 1]; mask [V, H, W] bool coverage; normal, to_camera [V, H, W, 3] unit
    world vectors (surface normal, direction from the surface point to the camera); cues [V, H, W, N_CUES] linear
    radiance of the pre-filtered lighting (diffuse(normal), glossy(reflection) per KAPPAS), or None when the
    lighting is unknown (cue channels and the flag are zero).
    """
    m = mask.unsqueeze(-1).to(rgb.dtype)
    if cues is None:
        cue_feat = torch.zeros(*rgb.shape[:3], N_CUES, dtype=rgb.dtype, device=rgb.device)
        ratio = torch.zeros_like(rgb)
        flag = torch.zeros_like(m)
    else:
        cues = cues.clamp_min(0)
        cue_feat = cues / (1 + cues)
        ratio = (srgb_eotf(rgb) / cues[..., :3].clamp_min(1e-3)).clamp(0, RATIO_MAX) / RATIO_MAX
        flag = m
    x = torch.cat([rgb, m, normal, to_camera, cue_feat, ratio, flag], dim=-1) * m
    return x.permute(0, 3, 1, 2).contiguous()


def _conv(c_in: int, c_out: int) -> nn.Sequential:
    """3x3 convolution + SiLU. No normalisation layer: per-sample normalisation (GroupNorm) would remove the
    absolute colour level of a view or plane, which is exactly what the base colour needs (measured: with it the
    first CPU run stayed at the mean-material baseline)."""
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, padding=1), nn.SiLU())


class ViewEncoder(nn.Module):
    """Per-view CNN: [V, IN_CHANNELS, H, W] -> per-pixel features [V, F, H, W] (full resolution)."""

    def __init__(self, cfg: LMRMConfig) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c = IN_CHANNELS
        for _ in range(cfg.view_layers):
            layers.append(_conv(c, cfg.view_channels))
            c = cfg.view_channels
        self.body = nn.Sequential(*layers)
        self.head = nn.Conv2d(c + IN_CHANNELS, cfg.feature_channels, 1)  # skip: raw inputs reach the planes

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(torch.cat([self.body(x), x], dim=1))


def texel_index(points: torch.Tensor, resolution: int) -> torch.Tensor:
    """[3, N] flat texel index (row * R + column) of points [N, 3] in each plane (grid_sample's layout: the
    plane's first coordinate picks the column, the second the row; texel i covers [-1 + 2i/R, -1 + 2(i+1)/R])."""
    out = []
    for a, b in PLANE_AXES:
        col = ((points[:, a] + 1) * 0.5 * resolution).floor().long().clamp(0, resolution - 1)
        row = ((points[:, b] + 1) * 0.5 * resolution).floor().long().clamp(0, resolution - 1)
        out.append(row * resolution + col)
    return torch.stack(out)


def lift_to_planes(features: torch.Tensor, points: torch.Tensor, resolution: int) -> torch.Tensor:
    """Scatter point features [N, F] at world points [N, 3] into three planes: [3, 2F + 1, R, R] holding the
    per-texel mean, mean square and log(1 + count)/5 of the features of the points inside each texel."""
    n_feat = features.shape[1]
    idx = texel_index(points, resolution)  # [3, N]
    planes = []
    both = torch.cat([features, features * features, torch.ones_like(features[:, :1])], dim=1)
    for k in range(3):
        acc = torch.zeros(resolution * resolution, 2 * n_feat + 1, dtype=features.dtype, device=features.device)
        acc = acc.index_add(0, idx[k], both)
        count = acc[:, -1:]
        mean = acc[:, :-1] / count.clamp_min(1)
        planes.append(torch.cat([mean, torch.log1p(count) / 5], dim=1))
    return torch.stack(planes).reshape(3, resolution, resolution, 2 * n_feat + 1).permute(0, 3, 1, 2)


def angle_bin(cos_view: torch.Tensor, bins: int) -> torch.Tensor:
    """[N] bin index in 0..bins-1 of cos_view [N] (n . v of the pixel each point came from; bins of equal width over
    [0, 1])."""
    return (cos_view.clamp(0, 1) * bins).long().clamp_max(bins - 1)


def gloss_bin(cues: torch.Tensor) -> torch.Tensor:
    """[...] bin index in 0..len(GLOSS_EDGES) of squashed lighting cues [..., N_CUES] (`view_inputs`' c / (1 + c)):
    log(sharpest glossy cue / diffuse cue), each the mean over RGB, against GLOSS_EDGES."""
    raw = cues / (1 - cues).clamp_min(1e-6)
    ratio = raw[..., 3:6].mean(-1).clamp_min(1e-4) / raw[..., :3].mean(-1).clamp_min(1e-4)
    return torch.bucketize(torch.log(ratio), torch.tensor(GLOSS_EDGES, dtype=cues.dtype, device=cues.device))


def lift_binned(features: torch.Tensor, points: torch.Tensor, which: torch.Tensor, resolution: int,
                bins: int) -> torch.Tensor:
    """Scatter point features [N, F] at world points [N, 3] into three planes per bin `which` [N] (long, 0..bins-1):
    [3, bins * (F + 1), R, R], per bin the texel's mean feature over the points in that bin (over all its points
    where the bin has none, so an empty bin reads as no change) and log(1 + the bin's count)/5."""
    n_feat = features.shape[1]
    idx = texel_index(points, resolution)  # [3, N]
    both = torch.cat([features, torch.ones_like(features[:, :1])], dim=1)  # features and a count
    planes = []
    for k in range(3):
        # one scatter for all bins: texel t of bin j is row j * R^2 + t
        acc = torch.zeros(bins * resolution * resolution, n_feat + 1, dtype=features.dtype, device=features.device)
        acc = acc.index_add(0, which * resolution * resolution + idx[k], both).reshape(bins, -1, n_feat + 1)
        total = acc.sum(0)  # the texel's sums over all its points
        overall = total[:, :-1] / total[:, -1:].clamp_min(1)
        count = acc[..., -1:]
        mean = torch.where(count > 0, acc[..., :-1] / count.clamp_min(1), overall)
        per_texel = torch.cat([mean, torch.log1p(count) / 5], dim=-1).permute(1, 0, 2)  # [R^2, bins, F + 1]
        planes.append(per_texel.reshape(-1, bins * (n_feat + 1)))
    return torch.stack(planes).reshape(3, resolution, resolution, -1).permute(0, 3, 1, 2)


class PlaneNet(nn.Module):
    """Shared U-Net over the three lifted planes: [B*3, 3F + 1 + 3 (+ bins * (F + 1)), R, R] (lifted mean, mean
    square, count, the object's global feature mean, plane id; with `angle_bins` then the angle bins' `lift_binned`
    channels and with `gloss_bins` then the gloss bins', last so that a model without them widens into one with them,
    `train.init_from`) -> [B*3, C_out, R, R] (two levels down; C_out = C less `LMRMConfig.fixed_channels`)."""

    def __init__(self, cfg: LMRMConfig) -> None:
        super().__init__()
        c_in = 3 * cfg.feature_channels + 1 + 3 + cfg.n_bins * (cfg.feature_channels + 1)
        c1, c2 = cfg.plane_channels, 2 * cfg.plane_channels
        self.enc1 = nn.Sequential(_conv(c_in, c1), _conv(c1, c1))
        self.enc2 = nn.Sequential(_conv(c1, c2), _conv(c2, c2))
        self.mid = nn.Sequential(_conv(c2, c2), _conv(c2, c2))
        self.dec2 = _conv(2 * c2, c1)
        self.dec1 = nn.Sequential(_conv(2 * c1, c1), _conv(c1, c1))
        c_out = cfg.triplane_channels - cfg.fixed_channels
        self.out = nn.Conv2d(c1, c_out, 1)
        self.skip = nn.Conv2d(c_in, c_out, 1)  # linear path: lifted means straight to the triplane

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        e1 = self.enc1(x)
        e2 = self.enc2(F.avg_pool2d(e1, 2))
        m = self.mid(F.avg_pool2d(e2, 2))
        d2 = self.dec2(torch.cat([F.interpolate(m, size=e2.shape[-2:], mode="bilinear", align_corners=False), e2], 1))
        d1 = self.dec1(torch.cat([F.interpolate(d2, size=e1.shape[-2:], mode="bilinear", align_corners=False), e1], 1))
        return self.out(d1) + self.skip(x)


@dataclass
class ObjectInputs:
    """What the network reads for one object: inputs [V, IN_CHANNELS, H, W] (`view_inputs`), mask [V, H, W] bool
    and position [V, H, W, 3] world surface points (zero where uncovered)."""

    inputs: torch.Tensor
    mask: torch.Tensor
    position: torch.Tensor


@dataclass
class Heads:
    """Decoded G-buffers at N query points: rho_d [N, 3], latent [N, 6], log_var [N, 9], pbr [N, 5]
    (base colour, roughness, metallic); family [N, len(FAMILIES)] logits, None without the family head."""

    rho_d: torch.Tensor
    latent: torch.Tensor
    log_var: torch.Tensor
    pbr: torch.Tensor
    family: torch.Tensor | None = None


class LMRMNet(nn.Module):
    """The trainable LMRM: `planes(objects)` -> [B, 3, C, R, R]; `forward(objects, points)` also decodes the
    heads at per-object query points [N_b, 3] (one call, so DistributedDataParallel sees every parameter)."""

    _template: Triplane

    def __init__(self, cfg: LMRMConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.view_encoder = ViewEncoder(cfg)
        self.plane_net = PlaneNet(cfg)
        n_features = 3 * cfg.triplane_channels
        self.material_decoder = MaterialDecoder(n_features, cfg.decoder_hidden, cfg.decoder_layers)
        self.uncertainty_decoder = UncertaintyDecoder(n_features, cfg.decoder_hidden, cfg.decoder_layers)
        self.pbr_decoder = PBRDecoder(n_features, cfg.decoder_hidden, cfg.decoder_layers)
        self.family_decoder = (FamilyDecoder(n_features, cfg.decoder_hidden, cfg.decoder_layers)
                               if cfg.family_head else None)  # fmt: skip
        # Shape holder for functional_call; kept out of the module tree (not a parameter, not in the state dict).
        object.__setattr__(self, "_template", Triplane(cfg.triplane_channels, cfg.plane_resolution, init_std=0.0))

    def planes(self, objects: list[ObjectInputs]) -> torch.Tensor:
        """Triplane planes [B, 3, C, R, R] of B objects."""
        r = self.cfg.plane_resolution
        lifted, ratios, binned, ratio_binned = [], [], [], []
        for obj in objects:
            feats = self.view_encoder(obj.inputs)  # [V, F, H, W]
            m = obj.mask
            pts = obj.position[m]  # [P, 3]
            per_pixel = feats.permute(0, 2, 3, 1)[m]  # [P, F]
            planes = lift_to_planes(per_pixel, pts, r)
            context = per_pixel.mean(0)[None, :, None, None].expand(3, -1, r, r)  # object-level colour, gloss
            lifted.append(torch.cat([planes, context], dim=1))
            bin_sets = []  # (each point's bin [P], the number of bins): the angle bins, then the gloss bins
            if self.cfg.angle_bins:
                cos_view = (obj.inputs[:, NORMAL_INPUT] * obj.inputs[:, TO_CAMERA_INPUT]).sum(1)[m]  # [P]
                bin_sets.append((angle_bin(cos_view, self.cfg.angle_bins), self.cfg.angle_bins))
            if self.cfg.gloss_bins:
                bin_sets.append((gloss_bin(obj.inputs[:, CUE_INPUT].permute(0, 2, 3, 1)[m]), len(GLOSS_EDGES) + 1))
            if bin_sets:
                binned.append(torch.cat([lift_binned(per_pixel, pts, w, r, n) for w, n in bin_sets], dim=1))
            if self.cfg.ratio_path:  # the ratio input back in [0, RATIO_MAX], lifted: mean, mean square
                ratio = obj.inputs[:, RATIO_INPUT].permute(0, 2, 3, 1)[m] * RATIO_MAX
                ratios.append(lift_to_planes(ratio, pts, r)[:, :RATIO_PATH_CHANNELS])
                if self.cfg.ratio_bins:
                    ratio_binned.append(torch.cat([lift_binned(ratio, pts, w, r, n) for w, n in bin_sets], dim=1))
        x = torch.stack(lifted)  # [B, 3, 3F+1, R, R]
        b = x.shape[0]
        plane_id = torch.eye(3, dtype=x.dtype, device=x.device)[None, :, :, None, None].expand(b, 3, 3, r, r)
        x = torch.cat([x, plane_id, *([torch.stack(binned)] if binned else [])], dim=2).reshape(b * 3, -1, r, r)
        out = self.plane_net(x).reshape(b, 3, -1, r, r)
        if ratios:
            out = torch.cat([torch.stack(ratios), out, *([torch.stack(ratio_binned)] if ratio_binned else [])], dim=2)
        return out

    def features(self, planes: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """`Triplane.features` of planes [3, C, R, R] at points [N, 3] -> [N, 3C], differentiable in planes."""
        out: torch.Tensor = functional_call(self._template, {"planes": planes}, (points,))
        return out

    def decode(self, features: torch.Tensor) -> Heads:
        rho_d, latent = self.material_decoder(features)
        base, rough, metal = self.pbr_decoder(features)
        pbr = torch.cat([base, rough.unsqueeze(-1), metal.unsqueeze(-1)], dim=-1)
        family = self.family_decoder(features) if self.family_decoder is not None else None
        return Heads(rho_d, latent, self.uncertainty_decoder(features), pbr, family)

    def forward(self, objects: list[ObjectInputs], points: list[torch.Tensor]) -> tuple[torch.Tensor, list[Heads]]:
        planes = self.planes(objects)
        return planes, [self.decode(self.features(planes[i], p)) for i, p in enumerate(points)]
