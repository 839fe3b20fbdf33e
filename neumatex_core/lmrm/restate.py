"""One LMRM's prediction restated through another checkpoint's decoders (docs/lmrm.md, "The restatement in the
pipeline"; docs/design-notes.md items 95 and 97).

The extraction reads the LMRM's triplane through the LMRM's own decoders: its PBR phase fine-tunes the PBR head, its
neural phase a copy of the material decoder. A checkpoint that predicts better alone can still be a worse
parametrisation for that TTO (design note 95). Restating separates the two: per object, a triplane is fitted (Adam on
its planes, from the readout checkpoint's own prediction for the object) so that the readout's decoders give, at
area-uniform surface points, what the predicting checkpoint's decoders give there: the PBR head's base colour,
roughness and metallic and the material decoder's base colour and latent (squared error, the latent mapped to
[0, 1] as the G-buffer metric maps it). The result reads like any prediction: the fitted triplane and the readout's
frozen decoders, its uncertainty decoder among them.

    pred = restate(candidate.predict(...), shipped.predict(...), points, steps=1500, lr=0.05, batch=8192)
"""

from __future__ import annotations

import torch

from neumatex_core.fields.fit import fit_on_points
from neumatex_core.fields.triplane import Triplane
from neumatex_core.lmrm.inference import LMRMPrediction


def heads(pred: LMRMPrediction, triplane: Triplane, points: torch.Tensor) -> torch.Tensor:
    """[N, 8 + D] what `pred`'s PBR head and material decoder give at points [N, 3] through `triplane`: PBR base
    colour, roughness, metallic, then rho_d and (latent + 1) / 2 (the metric's scale)."""
    feats = triplane.features(points)
    base, rough, metal = pred.pbr_decoder(feats)
    rho_d, latent = pred.material_decoder(feats)
    return torch.cat([base, rough.reshape(-1, 1), metal.reshape(-1, 1), rho_d, (latent + 1) / 2], dim=-1)


def restate(prediction: LMRMPrediction, readout: LMRMPrediction, points: torch.Tensor, *, steps: int, lr: float,
            batch: int, seed: int = 0) -> tuple[LMRMPrediction, dict[str, float]]:
    """`prediction` read through `readout`'s decoders: a triplane fitted from `readout`'s planes (Adam, `steps` steps
    of `batch` of points [P, 3] drawn with replacement, lr cosine-decayed to 0) so that `readout`'s decoders give
    `prediction`'s heads there. Returns the prediction (fitted triplane, frozen; `readout`'s decoders) and the mean
    squared error on each head before and after the fit ({"pbr"|"material"}_{"start"|"end"})."""
    if readout.material_decoder.latent_dim != prediction.material_decoder.latent_dim:
        raise ValueError(f"the readout's latents have {readout.material_decoder.latent_dim} channels, the "
                         f"prediction's {prediction.material_decoder.latent_dim}: they were trained for different "
                         "neural bases")  # fmt: skip
    points = points.to(readout.triplane.planes.device)
    with torch.no_grad():
        want = heads(prediction, prediction.triplane, points)
    fitted = Triplane.from_planes(readout.triplane.planes.detach().clone())
    fitted.requires_grad_(True)

    def errors() -> dict[str, float]:
        with torch.no_grad():
            d = (heads(readout, fitted, points) - want) ** 2
            return {"pbr": float(d[:, :5].mean()), "material": float(d[:, 5:].mean())}

    def batch_error(idx: torch.Tensor) -> torch.Tensor:
        return ((heads(readout, fitted, points[idx]) - want[idx]) ** 2).mean()

    start = errors()
    fit_on_points(fitted.parameters(), batch_error, points.shape[0], steps, lr, batch, seed, points.device)
    end = errors()
    fitted.requires_grad_(False)
    restated = LMRMPrediction(fitted, readout.material_decoder, readout.uncertainty_decoder, readout.pbr_decoder)
    return restated, {**{f"{k}_start": v for k, v in start.items()}, **{f"{k}_end": v for k, v in end.items()}}
