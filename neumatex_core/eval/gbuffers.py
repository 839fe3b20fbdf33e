"""Ground-truth G-buffers of a synthetic object (written by `neumatex synth`) and the G-buffer metrics.

`ground_truth(object_dir, views)` reads the preset views' position / base colour / latent buffers at their covered
pixels (with a `basis` other than the one the object was made in, the latents in that basis: the encoding of each
pixel's region's layered parameters from material.json, the region told by the stored latent); `truth_lookup`
turns them into a function of surface points (nearest stored pixel: what reg="oracle" needs); `gbuffer_psnr` gives
PSNR_BaseColor (rho_d) and PSNR_Latents ((l + 1) / 2) of any G-buffer function over those pixels
(docs/architecture.md section 2: covered pixels only).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from neumatex_core.eval.metrics import psnr_of_mse
from neumatex_core.imageio import read_image
from neumatex_core.materials.layered import PARAMETER_NAMES
from neumatex_core.materials.neural_basis import BasisError, NeuralBasis, load_basis

GBufferFn = Callable[[torch.Tensor], torch.Tensor]  # points [N, 3] -> (rho_d, latent) [N, 3 + K]


@dataclass
class GroundTruth:
    """points [M, 3] (covered pixel centres of the chosen views, world frame), values [M, 3 + K] (rho_d, latent),
    view [M] index of the view each pixel belongs to."""

    points: torch.Tensor
    values: torch.Tensor
    view: torch.Tensor


def ground_truth(object_dir: str | Path, views: Sequence[int] | None = None,
                 basis: NeuralBasis | None = None) -> GroundTruth:
    """The stored ground truth of `views` (default: all frames with G-buffers) of a synthetic object folder; with
    `basis` other than the object's (material.json's basis_id), its latents are `basis.encode` of each pixel's region's
    layered parameters, values [M, 3 + K]: a region's stored latent is the object's basis's encoding of its
    parameters (synth/materials.py), so the nearest of those encodings tells each pixel's region.
    Raises ValueError naming the file when the folder has no G-buffers (not a synthetic object)."""
    root = Path(object_dir)
    transforms = root / "transforms.json"
    try:
        frames = json.loads(transforms.read_text())["frames"]
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f"{transforms}: cannot read the frames ({exc})") from None
    picks = list(range(len(frames))) if views is None else list(views)
    recode = _region_encodings(root, basis) if basis is not None else None
    pts, vals, idx = [], [], []
    for v in picks:
        g = frames[v].get("gbuffers")
        if not g or not all(k in g for k in ("position", "basecolor", "latent")):
            raise ValueError(f"{transforms}: frame {v} has no ground-truth G-buffers (not a synthetic object)")
        mask = read_image(root / frames[v]["mask_path"])[:, :, 0] > 0.5
        pts.append(read_image(root / g["position"])[mask])
        latent = read_image(root / g["latent"])[mask]
        if recode is not None:
            own, other = recode
            latent = other[torch.cdist(torch.from_numpy(latent), own).argmin(1).numpy()]
        vals.append(np.concatenate([read_image(root / g["basecolor"])[mask], latent], 1))
        idx.append(np.full(int(mask.sum()), v))
    return GroundTruth(torch.from_numpy(np.concatenate(pts)).float(), torch.from_numpy(np.concatenate(vals)).float(),
                       torch.from_numpy(np.concatenate(idx)))  # fmt: skip


def _region_encodings(root: Path, basis: NeuralBasis) -> tuple[torch.Tensor, np.ndarray] | None:
    """(the regions' latents in the object's basis [regions, 6], in `basis` [regions, K] float32): their layered
    parameters (material.json) encoded by each; None where `basis` is the object's (its stored latents are those)."""
    path = root / "material.json"
    try:
        material = json.loads(path.read_text())
        if material["basis_id"] == basis.basis_id:
            return None
        params = torch.tensor([[float(r["params"][name]) for name in PARAMETER_NAMES] for r in material["regions"]])
        own = load_basis(basis_id=material["basis_id"])
    except (OSError, ValueError, KeyError, TypeError, BasisError) as exc:
        raise ValueError(f"{path}: cannot encode the regions' layered parameters ({exc})") from None
    with torch.no_grad():
        other = basis.encode(params.to(next(basis.parameters()).device)).cpu().numpy().astype(np.float32)
        return own.encode(params), other


def truth_lookup(gt: GroundTruth, chunk: int = 4096) -> GBufferFn:
    """points [N, 3] -> the values [N, 3 + K] of the nearest ground-truth pixel."""
    def lookup(points: torch.Tensor) -> torch.Tensor:
        src = gt.points.to(points.device)
        out = []
        for s in range(0, points.shape[0], chunk):
            out.append(torch.cdist(points[s:s + chunk], src).argmin(1))
        return gt.values.to(points.device)[torch.cat(out)]

    return lookup


def gbuffer_psnr(fn: GBufferFn, gt: GroundTruth, chunk: int = 1 << 15) -> dict[str, float]:
    """{'psnr_basecolor', 'psnr_latents'} (dB) of fn's G-buffers against the ground truth over its pixels."""
    with torch.no_grad():
        pred = torch.cat([fn(gt.points[s:s + chunk]).cpu() for s in range(0, gt.points.shape[0], chunk)])
    truth = gt.values
    rho = float(((pred[:, :3].double() - truth[:, :3].double()) ** 2).mean())
    if pred.shape[1] != truth.shape[1]:  # a basis of another latent size (TTOConfig.basis): nothing to compare
        return {"psnr_basecolor": psnr_of_mse(rho), "psnr_latents": math.nan}
    lat = float((((pred[:, 3:].double() - truth[:, 3:].double()) / 2) ** 2).mean())
    return {"psnr_basecolor": psnr_of_mse(rho), "psnr_latents": psnr_of_mse(lat)}
