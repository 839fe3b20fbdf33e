"""The neural start blended with the LMRM's prediction (tto/lmrm_start.py): each channel the precision-weighted mean
of the PBR start and the LMRM, the latent only in the basis whose latents the LMRM predicts; `fit_start` fits the
planes to that blend (TTOConfig.lmrm_start_var); and the anchor to the start weighs each channel by the LMRM's share
of it (TTOConfig.lmrm_start_anchor)."""

from __future__ import annotations

import copy
import math
from dataclasses import replace

import pytest
import torch
from tto_fixtures import gbuffer_mse

from neumatex_core.fields import Triplane
from neumatex_core.lmrm.inference import LMRMPrediction
from neumatex_core.materials.neural_basis import BASIS_V4, BASIS_V6, load_basis
from neumatex_core.tto import TTOConfig
from neumatex_core.tto.lmrm_start import lmrm_blend
from neumatex_core.tto.optimise import TTOResult
from neumatex_core.tto.params import PBRTriplane
from neumatex_core.tto.pbr_start import fit_start

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def with_variance(prediction: LMRMPrediction, var: float) -> LMRMPrediction:
    """`prediction` whose uncertainty decoder predicts the variance `var` for every channel everywhere."""
    unc = copy.deepcopy(prediction.uncertainty_decoder)
    last = [m for m in unc.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.fill_(math.log(var))
    return LMRMPrediction(prediction.triplane, prediction.material_decoder, unc, prediction.pbr_decoder)


def test_lmrm_blend_meets_the_pbr_start_where_their_variances_meet(example, truth_prediction):
    points, _ = example.mesh.sample_surface(512, seed=0)
    rho, latent = torch.full((512, 3), 0.2), torch.zeros(512, 6)
    with torch.no_grad():
        want_rho, want_latent, _ = truth_prediction.gbuffers(points)
    prediction = with_variance(truth_prediction, 0.01)
    # equal variances: halfway; the PBR start three times as uncertain: three quarters of the way to the LMRM
    for pbr_var, w in ((0.01, 0.5), (0.03, 0.75)):
        got_rho, got_latent, record = lmrm_blend(prediction, example.basis, points, rho, latent, pbr_var)
        assert torch.allclose(got_rho, rho + w * (want_rho - rho), atol=1e-5)
        assert torch.allclose(got_latent, latent + w * (want_latent - latent), atol=1e-5)
        assert record == pytest.approx({"lmrm_start_weight_rho": w, "lmrm_start_weight_latent": w}, abs=1e-5)
    # in another basis the LMRM's latents mean nothing, whatever their size (v4: 6 numbers, v6: 16): the base colour
    # alone is blended
    for other in (BASIS_V4, BASIS_V6):
        basis = load_basis(basis_id=other)
        latent = torch.zeros(512, basis.arch.latent_dim)
        got_rho, got_latent, record = lmrm_blend(prediction, basis, points, rho, latent, 0.01)
        assert torch.equal(got_latent, latent) and record["lmrm_start_weight_latent"] == 0.0
        assert torch.allclose(got_rho, (rho + want_rho) / 2, atol=1e-5)


def test_fit_start_fits_the_planes_to_the_blend(example, truth_prediction):
    """A sure LMRM (here distilled from the ground truth) moves the fitted start from the PBR solution to its own
    prediction: both G-buffers end much nearer the truth; without lmrm_start_var the start is the PBR solution's."""
    sure = with_variance(truth_prediction, 1e-4)
    pbr = PBRTriplane(Triplane.from_planes(truth_prediction.triplane.planes.detach().clone()),
                      truth_prediction.pbr_decoder)  # fmt: skip
    first = TTOResult(pbr, finished=True)
    cfg = TTOConfig.preset("tiny", max_bounces=1, init="pbr", reg="start", lambda_consistency=0.1)
    args = (first, example.mesh, example.envmap, example.photos, example.capture.tonemap, sure, example.basis, True)
    plain = fit_start(cfg, *args)
    blended = fit_start(replace(cfg, lmrm_start_var=1.0), *args)
    assert plain.record == {}
    assert blended.record["lmrm_start_weight_rho"] > 0.99 and blended.record["lmrm_start_weight_latent"] > 0.99
    plain_rho, plain_latent = gbuffer_mse(lambda p: plain.params.gbuffer(p, None), example.gt_points,
                                          example.gt_values)  # fmt: skip
    rho, latent = gbuffer_mse(lambda p: blended.params.gbuffer(p, None), example.gt_points, example.gt_values)
    assert rho < 0.05 * plain_rho and latent < 0.05 * plain_latent  # measured: 0.00055 / 0.048, 0.00018 / 0.024


def test_the_anchor_holds_the_start_where_the_lmrm_made_it(example, truth_prediction, monkeypatch):
    """TTOConfig.lmrm_start_anchor: the neural phase's anchor to its start weighs each channel by the LMRM's share of
    the start, so the anchor's first step is zero (the start itself) and its weights are that share: 1/2 where both
    estimates are as sure, none where the LMRM is far less sure than the PBR start."""
    from neumatex_core.tto import pbr_start, solve

    cfg = TTOConfig.preset("tiny", steps=3, pbr_steps=3, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=1.0, lmrm_start_var=0.01, lmrm_start_anchor=True)  # fmt: skip
    args = (example.mesh, example.envmap, example.photos, example.capture.tonemap)
    weights: list[torch.Tensor] = []
    optimise = pbr_start.optimise

    def spy(problem, *rest, **kw):
        if problem.anchor is not None:  # the neural phase's (the PBR phase has none)
            weights.append(problem.anchor.weight)
        return optimise(problem, *rest, **kw)

    monkeypatch.setattr(pbr_start, "optimise", spy)
    result = solve(cfg, *args, with_variance(truth_prediction, 0.01), example.basis)
    assert torch.allclose(weights[-1], torch.full_like(weights[-1], 0.5), atol=1e-5)
    reg = [r["reg"] for r in result.history if r["phase"] == 1.0]
    assert reg[0] == pytest.approx(0.0, abs=1e-9) and max(reg) > 0
    solve(cfg, *args, with_variance(truth_prediction, 1e6), example.basis)
    assert float(weights[-1].max()) < 1e-6
    with pytest.raises(ValueError, match="lmrm_start_anchor"):
        replace(cfg, lmrm_start_var=0.0).check()
