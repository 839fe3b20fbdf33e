"""LMRM training data: synthetic object folders (`neumatex synth`, layout in synth/writer.py) -> cached tensors ->
augmented training samples.

`load_synth_object(folder)` reads one object at its own resolution (the 23 tonemapped views, masks, position /
normal / base colour / latent / PBR G-buffers, each pixel's material family, cameras, environment map).
`build_cache` keeps what training needs of its covered pixels in one small `.pt` file (sRGB uint8, positions,
normals, directions to the camera, lighting cues, 14 target channels, the family's index in `FAMILIES`), made once
per object. `LMRMDataset.sample` turns a cached object into network inputs
and supervised points, with augmentation (training): a random rotation of the world about +Y (positions, normals
and directions; pixel colours and cues are unchanged, so the sample stays physically consistent), an exposure
change (linear pixels and cues scaled together, pixels re-clipped), dropping views, and hiding the lighting.
A sample is made on the device its cached object lies on (the random numbers always come from the step's CPU
generator, so a GPU sample draws the same choices as a CPU one); `LMRMDataset(resident=...)` keeps objects on the
training device after their first use, so a GPU makes its samples itself instead of waiting on one CPU process.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neumatex_core.capture.tonemap import srgb_eotf, srgb_oetf
from neumatex_core.geometry.camera import Camera
from neumatex_core.imageio import read_image
from neumatex_core.lighting.envmap import EnvironmentMap, envmap_rgb
from neumatex_core.lighting.prefilter import PrefilteredLighting
from neumatex_core.lmrm.model import ObjectInputs, view_inputs
from neumatex_core.materials.prior import FAMILIES
from neumatex_core.synth.writer import GBUFFER_CHANNELS

N_TARGETS = 14  # rho_d (3), latent (6), PBR base colour (3), roughness, metallic
# 2: PBR targets in the writer's channel order (version 1 had OpenEXR's alphabetical order); 3: the pixels' family
CACHE_VERSION = 3
LIGHTING_GRID = (16, 48)  # PrefilteredLighting (grid, source): coarse cues, 0.5 s per object on one core


def prefiltered(envmap: EnvironmentMap) -> PrefilteredLighting:
    """The lighting cues' pre-filtered maps, at the resolution training and inference share."""
    return PrefilteredLighting(envmap, grid=LIGHTING_GRID[0], source=LIGHTING_GRID[1])


class LMRMDataError(ValueError):
    """A training/benchmark object folder that cannot be used; the message names the file."""


def finished_objects(root: Path) -> list[Path]:
    """Object folders of a synth output folder that are complete (meta.json written last), sorted by name."""
    if not root.is_dir():
        raise LMRMDataError(f"{root}: not a folder of synthetic objects (make one with `neumatex synth`)")
    return sorted(p for p in root.iterdir()
                  if p.is_dir() and not p.name.startswith(".") and (p / "meta.json").is_file())  # fmt: skip


def read_channels(path: Path, names: tuple[str, ...]) -> np.ndarray:
    """[H, W, len(names)] float32 channels of an EXR picked by name, in the order of `names`. OpenEXR stores
    channels sorted by name, so e.g. the PBR G-buffer (base_r, base_g, base_b, roughness, metallic; GBUFFER_CHANNELS
    in synth/writer.py) reads back as base_b, base_g, base_r, metallic, roughness without this."""
    import OpenImageIO as oiio

    pixels = read_image(path)
    inp = oiio.ImageInput.open(str(path))
    have = tuple(inp.spec().channelnames) if inp is not None else ()
    if inp is not None:
        inp.close()
    missing = [n for n in names if n not in have]
    if missing:
        raise LMRMDataError(f"{path}: channels {missing} missing (has {list(have)})")
    return np.ascontiguousarray(pixels[:, :, [have.index(n) for n in names]])


def _camera(frame: dict[str, Any], top: dict[str, Any]) -> Camera:
    def get(key: str) -> Any:
        return frame.get(key, top.get(key))

    return Camera(np.asarray(frame["transform_matrix"], dtype=np.float64), float(get("fl_x")), float(get("fl_y")),
                  float(get("cx")), float(get("cy")), int(get("w")), int(get("h")))  # fmt: skip


@dataclass
class SynthObject:
    """One synthetic object at its own resolution (V views of H x W).

    rgb [V, H, W, 3] tonemapped sRGB in [0, 1]; mask [V, H, W] bool; position, normal [V, H, W, 3] world;
    targets [V, H, W, 14] (rho_d, latent, PBR base colour, roughness, metallic); family [V, H, W] long, the index
    in `FAMILIES` of each pixel's region's family; cameras; envmap.
    """

    id: str
    folder: Path
    rgb: torch.Tensor
    mask: torch.Tensor
    position: torch.Tensor
    normal: torch.Tensor
    targets: torch.Tensor
    family: torch.Tensor
    cameras: list[Camera]
    envmap: EnvironmentMap


def pixel_families(folder: Path, views: int) -> tuple[list[str], torch.Tensor]:
    """The material family of every region of the object in `folder` (material.json), and its views' region ids
    [V, H, W] long (gbuffers/NNN_region.exr)."""
    families = [r["family"] for r in json.loads((folder / "material.json").read_text())["regions"]]
    ids = [torch.from_numpy(read_channels(folder / "gbuffers" / f"{v:03d}_region.exr", ("region",))[..., 0].copy())
           for v in range(views)]  # fmt: skip
    return families, torch.stack(ids).round().long()


def load_synth_object(folder: Path) -> SynthObject:
    """Read an object folder written by `neumatex synth` (raises LMRMDataError naming the file)."""
    tf = folder / "transforms.json"
    try:
        top = json.loads(tf.read_text())
        frames = top["frames"]
        cams = [_camera(f, top) for f in frames]
        buffers = [f["gbuffers"] for f in frames]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise LMRMDataError(f"{tf}: not a synthetic object's transforms.json ({exc!r})") from None
    try:
        rgb = np.stack([read_image(folder / f["file_path"])[:, :, :3] for f in frames])
        mask = np.stack([read_image(folder / f["mask_path"])[:, :, 0] > 0.5 for f in frames])
        pos = np.stack([read_image(folder / b["position"]) for b in buffers])
        nrm = np.stack([read_image(folder / b["normal"]) for b in buffers])
        tgt = np.stack([np.concatenate([read_channels(folder / b[k], GBUFFER_CHANNELS[k])
                                        for k in ("basecolor", "latent", "pbr")], axis=-1) for b in buffers])
        env_pixels = read_image(folder / top["envmap"])
        names, regions = pixel_families(folder, len(frames))
        family_of_region = torch.tensor([FAMILIES.index(n) for n in names], dtype=torch.long)
        family = family_of_region[regions.clamp(0, len(names) - 1)]
    except (OSError, ValueError, KeyError) as exc:
        raise LMRMDataError(f"{folder}: cannot read the object's images ({exc})") from None
    if tgt.shape[-1] != N_TARGETS:
        raise LMRMDataError(f"{folder}: G-buffers hold {tgt.shape[-1]} target channels, expected {N_TARGETS}")
    env = EnvironmentMap(envmap_rgb(env_pixels), np.asarray(top.get("envmap_to_world", np.eye(3))),
                         float(top.get("envmap_scale", 1.0)))  # fmt: skip
    t = torch.from_numpy
    return SynthObject(folder.name, folder, t(rgb).float(), t(mask), t(pos).float(), t(nrm).float(), t(tgt).float(),
                       family, cams, env)  # fmt: skip


def to_camera_directions(position: torch.Tensor, cameras: list[Camera]) -> torch.Tensor:
    """Unit directions [V, H, W, 3] from surface points position [V, H, W, 3] to each view's camera centre."""
    centres = torch.tensor(np.stack([c.position for c in cameras]), dtype=position.dtype, device=position.device)
    d = centres[:, None, None, :] - position
    return d / d.norm(dim=-1, keepdim=True).clamp_min(1e-9)


def lighting_cues(lighting: PrefilteredLighting, normal: torch.Tensor, to_camera: torch.Tensor) -> torch.Tensor:
    """[N, 12] linear radiance cues at unit normals [N, 3] seen from unit directions to_camera [N, 3]: the diffuse
    lookup at the normal, then the glossy lookups (KAPPAS) at the mirror direction 2 (n.v) n - v."""
    refl = 2 * (normal * to_camera).sum(-1, keepdim=True) * normal - to_camera
    refl = refl / refl.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    return torch.cat([lighting.diffuse(normal), lighting.glossy(refl).reshape(normal.shape[0], -1)], dim=-1)


def cache_path(cache_dir: Path, folder: Path) -> Path:
    return cache_dir / f"{folder.name}.v{CACHE_VERSION}.pt"


def build_cache(folder: Path, cache_dir: Path) -> Path:
    """Cache the covered pixels of one object (see the module docstring); returns the file (kept when present and
    made from the same meta.json)."""
    out = cache_path(cache_dir, folder)
    meta_hash = hashlib.sha256((folder / "meta.json").read_bytes()).hexdigest()
    if out.is_file():
        try:
            head = torch.load(out, map_location="cpu", weights_only=True)
            if head.get("meta_sha256") == meta_hash and head.get("version") == CACHE_VERSION:
                return out
        except (OSError, RuntimeError, EOFError):
            pass
    obj = load_synth_object(folder)
    m = obj.mask
    to_cam = to_camera_directions(obj.position, obj.cameras)
    with torch.no_grad():
        cues = lighting_cues(prefiltered(obj.envmap), obj.normal[m], to_cam[m])
    data = {
        "version": CACHE_VERSION, "id": obj.id, "meta_sha256": meta_hash, "mask": m,
        "rgb": (obj.rgb[m] * 255).round().clamp(0, 255).to(torch.uint8), "position": obj.position[m],
        "normal": obj.normal[m], "to_camera": to_cam[m], "cues": cues.half(), "targets": obj.targets[m].half(),
        "family": obj.family[m].to(torch.uint8),
    }  # fmt: skip
    cache_dir.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(f".{os.getpid()}.tmp")  # unique: several processes may cache the same object
    torch.save(data, tmp)
    tmp.replace(out)
    return out


@dataclass
class Augment:
    """Training augmentation (see the module docstring); `none()` for evaluation."""

    rotate: bool = True
    exposure: tuple[float, float] = (0.7, 1.4)
    min_views: int = 16
    p_no_lighting: float = 0.1

    @classmethod
    def none(cls) -> Augment:
        return cls(rotate=False, exposure=(1.0, 1.0), min_views=1000, p_no_lighting=0.0)


def _rot_y(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@dataclass
class Sample:
    """One training sample: the network inputs, query points [N, 3], their targets [N, 14] and their family [N]
    (long, index in `FAMILIES`)."""

    inputs: ObjectInputs
    points: torch.Tensor
    targets: torch.Tensor
    family: torch.Tensor


def make_sample(data: dict[str, Any], generator: torch.Generator, augment: Augment, n_points: int) -> Sample:
    """A sample from a cached object (`build_cache`'s dict). n_points <= 0: every covered pixel, in order."""
    mask: torch.Tensor = data["mask"]
    v, h, w = mask.shape
    device = mask.device
    rgb = data["rgb"].float() / 255
    pos, nrm, to_cam = data["position"], data["normal"], data["to_camera"]
    cues: torch.Tensor | None = data["cues"].float()
    u = torch.rand(4, generator=generator)
    if augment.rotate:
        r = _rot_y(2 * math.pi * float(u[0])).to(device)
        pos, nrm, to_cam = pos @ r.T, nrm @ r.T, to_cam @ r.T
    lo, hi = augment.exposure
    if hi > lo:
        s = math.exp(math.log(lo) + float(u[1]) * (math.log(hi) - math.log(lo)))
        rgb = srgb_oetf((srgb_eotf(rgb) * s).clamp(0, 1))
        cues = cues * s if cues is not None else None
    if float(u[2]) < augment.p_no_lighting:
        cues = None
    # Scatter the covered pixels back into images.
    idx = mask.reshape(-1).nonzero().squeeze(-1)

    def image(values: torch.Tensor) -> torch.Tensor:
        full = torch.zeros(v * h * w, values.shape[-1], dtype=values.dtype, device=device)
        full[idx] = values
        return full.reshape(v, h, w, -1)

    keep = torch.arange(v)
    if augment.min_views < v:
        k = augment.min_views + int(torch.randint(0, v - augment.min_views + 1, (1,), generator=generator))
        keep = torch.randperm(v, generator=generator)[:k].sort().values
    keep = keep.to(device)
    inputs = view_inputs(image(rgb)[keep], mask[keep], image(nrm)[keep], image(to_cam)[keep],
                         image(cues)[keep] if cues is not None else None)  # fmt: skip
    obj = ObjectInputs(inputs, mask[keep], image(pos)[keep])
    targets, family = data["targets"].float(), data["family"].long()
    if 0 < n_points < pos.shape[0]:
        pick = torch.randperm(pos.shape[0], generator=generator)[:n_points].to(device)
        return Sample(obj, pos[pick], targets[pick], family[pick])
    return Sample(obj, pos, targets, family)


class LMRMDataset:
    """The cached objects of one or more synth folders. `sample(i, generator, augment, n_points)`.

    resident: a store (folder path -> cached dict on `device`) kept across datasets: an object is read once and
    stays there, so samples are made on `device`; None reads the cache file at each use (on the CPU)."""

    def __init__(self, roots: list[Path], cache_dir: Path, exclude: set[str] | None = None,
                 resident: dict[str, dict[str, Any]] | None = None, device: torch.device | None = None) -> None:
        self.roots, self.cache_dir = roots, cache_dir
        self.folders = [f for r in roots for f in finished_objects(r) if f.name not in (exclude or set())]
        self.resident, self.device = resident, device or torch.device("cpu")

    def __len__(self) -> int:
        return len(self.folders)

    @property
    def ids(self) -> list[str]:
        return [f.name for f in self.folders]

    def load(self, i: int) -> dict[str, Any]:
        key = str(self.folders[i])
        if self.resident is not None and key in self.resident:
            return self.resident[key]
        data: dict[str, Any] = torch.load(build_cache(self.folders[i], self.cache_dir), map_location=self.device,
                                          weights_only=True)  # fmt: skip
        if self.resident is not None:
            self.resident[key] = data
        return data

    def sample(self, i: int, generator: torch.Generator, augment: Augment, n_points: int) -> Sample:
        return make_sample(self.load(i), generator, augment, n_points)

    def manifest_hash(self) -> str:
        """SHA-256 over (object id, its tree_sha256 from meta.json) of every object, sorted by id."""
        h = hashlib.sha256()
        for f in sorted(self.folders, key=lambda p: p.name):
            tree = json.loads((f / "meta.json").read_text()).get("tree_sha256", "")
            h.update(f"{f.name} {tree}\n".encode())
        return h.hexdigest()


def training_mean(dataset: LMRMDataset, limit: int | None = None) -> torch.Tensor:
    """[14] mean target over the covered pixels of every object (or of `limit` evenly spread ones): the
    mean-material baseline. Every object by default: a 64-object subsample moved the baseline on the LMRM test
    split by up to 0.1 dB between two training sets, as much as the gains it is set against (docs/lmrm.md)."""
    n = len(dataset)
    n_picks = n if limit is None else min(n, limit)
    picks = sorted({int(round(k * (n - 1) / max(n_picks - 1, 1))) for k in range(n_picks)})
    total, count = torch.zeros(N_TARGETS, dtype=torch.float64), 0
    for i in picks:
        t = dataset.load(i)["targets"].double().cpu()
        total += t.sum(0)
        count += t.shape[0]
    return (total / max(count, 1)).float()
