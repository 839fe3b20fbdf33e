"""Shared setup of the TTO and pipeline tests: the bundled example capture (examples/teapot, a synthetic object at
64 px with ground-truth G-buffers) as photos, lighting and ground truth in torch."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from neumatex_core.capture import Capture, load_capture
from neumatex_core.eval import ground_truth
from neumatex_core.fields import MaterialDecoder, PBRDecoder, Triplane, UncertaintyDecoder
from neumatex_core.fields.fit import fit_triplane
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.lmrm.inference import LMRMPrediction
from neumatex_core.materials.neural_basis import NeuralBasis, load_basis
from neumatex_core.tto import PhotoSet

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "teapot"


@dataclass
class Example:
    capture: Capture
    mesh: Mesh
    envmap: EnvironmentMap
    photos: PhotoSet
    basis: NeuralBasis
    gt_points: torch.Tensor  # [M, 3] surface points seen by the preset views
    gt_values: torch.Tensor  # [M, 9] ground-truth (rho_d, latent) there


def load_example(views: tuple[int, ...] = (0, 4, 8, 12, 17, 19)) -> Example:
    cap = load_capture(EXAMPLE)
    mesh = cap.load_mesh()
    env = EnvironmentMap.from_file(cap.envmap_path, cap.envmap_to_world, cap.envmap_scale)
    photos = PhotoSet.of_capture(cap, mesh)
    gt = ground_truth(EXAMPLE, views)
    return Example(cap, mesh, env, photos, load_basis(), gt.points, gt.values)


def gt_prediction(ex: Example, steps: int = 200, seed: int = 0) -> LMRMPrediction:
    """A triplane + decoder distilled from the ground truth (an 'LMRM' that is nearly right), random other heads."""
    values = ex.gt_values
    field, _ = fit_triplane(ex.gt_points, lambda p: (values[:, :3], values[:, 3:]), ex.basis, channels=8,
                            resolution=32, steps=steps, seed=seed)  # fmt: skip
    torch.manual_seed(seed)
    f = field.triplane.feature_dim
    unc, pbr = UncertaintyDecoder(f), PBRDecoder(f)
    for m in (unc, pbr, field.decoder, field.triplane):
        m.requires_grad_(False)
        m.zero_grad(set_to_none=True)  # no gradients left over from the fit
    return LMRMPrediction(field.triplane, field.decoder, unc, pbr)


def random_prediction(seed: int = 0) -> LMRMPrediction:
    g = torch.Generator().manual_seed(seed)
    tp = Triplane(8, 32, generator=g)
    torch.manual_seed(seed)
    decs = (MaterialDecoder(24), UncertaintyDecoder(24), PBRDecoder(24))
    for m in decs:
        m.requires_grad_(False)
    return LMRMPrediction(tp, *decs)


def gbuffer_mse(prediction_or_field: object, points: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    """(MSE of rho_d, MSE of (l + 1) / 2) of a G-buffer function's values at points against truth [M, 9]."""
    with torch.no_grad():
        g = prediction_or_field(points)  # type: ignore[operator]
    rho = float(((g[:, :3] - truth[:, :3]) ** 2).mean())
    lat = float((((g[:, 3:] - truth[:, 3:]) / 2) ** 2).mean())
    return rho, lat


def stop_after(checks: int) -> Callable[[], bool]:
    """A `should_stop` for `optimise` that says stop from its (checks + 1)-th call on: the run stops after `checks`
    steps."""
    calls = {"n": 0}

    def should_stop() -> bool:
        calls["n"] += 1
        return calls["n"] > checks

    return should_stop
