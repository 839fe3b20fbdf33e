"""The diagonal Gauss-Newton step of the TTO (tto/gauss_newton.py, `TTOConfig.optimizer` "gauss_newton"): the sign
probe's squared gradient estimates the Gauss-Newton diagonal; one undamped step solves a separable least-squares
problem; the residuals the probe takes are the losses' own; a TTO with it descends the photo loss (and resumes bit for
bit: tests/test_tto.py)."""

from __future__ import annotations

import math

import pytest
import torch

from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.tto import Anchor, TTOConfig, build_problem, optimise
from neumatex_core.tto.gauss_newton import DiagonalGaussNewton, sign_probe
from neumatex_core.tto.loss import consistency, consistency_residuals, photo_residuals, photometric_loss

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def test_the_sign_probe_estimates_the_gauss_newton_diagonal():
    # r = A x - b: the Gauss-Newton diagonal of sum r^2 is 2 sum_k A_ki^2, exactly.
    g = torch.Generator().manual_seed(0)
    a = torch.randn(40, 7, generator=g) * torch.linspace(0.1, 3.0, 7)
    b = torch.randn(40, generator=g)
    x = torch.randn(7, generator=g, requires_grad=True)
    exact = 2 * (a * a).sum(0)
    draws = 4000
    probes = torch.stack([torch.autograd.grad(sign_probe([a @ x - b], g), x)[0] ** 2 for _ in range(draws)])
    mean, se = probes.mean(0), probes.std(0) / math.sqrt(draws)
    assert torch.all((mean - exact).abs() < 5 * se), (mean, exact, se)
    # a signal the estimate can see: the columns' scales differ by 30x
    assert float(exact[-1] / exact[0]) > 100


def test_an_undamped_gauss_newton_step_solves_a_separable_least_squares_problem():
    # sum_k (w_k (x_k - t_k))^2: diagonal curvature 2 w^2; with no moving averages and no damping, lr 1 is Newton.
    w, t = torch.tensor([0.1, 1.0, 10.0]), torch.tensor([1.0, -2.0, 0.5])
    x = torch.zeros(3, requires_grad=True)
    other = torch.ones(2, requires_grad=True)  # an Adam group beside it
    opt = DiagonalGaussNewton([{"params": [x], "curvature": True}, {"params": [other]}], lr=1.0, betas=(0.0, 0.0),
                              damping=0.0, max_step=100.0)  # fmt: skip
    residual = w * (x - t)
    loss = (residual**2).sum() + other.sum()
    loss.backward(retain_graph=True)
    # the exact diagonal in place of the probe's estimate: the step is then the Newton step
    opt.fold_curvature([torch.sqrt(2 * w * w)])
    opt.step()
    assert torch.allclose(x.detach(), t, atol=1e-5), x
    assert torch.allclose(other.detach(), torch.zeros(2), atol=1e-6)  # Adam's first step: lr x sign(gradient)
    # damping shrinks the step of the weakly seen parameter, not of the strongly seen one; the clamp bounds it
    y = torch.zeros(3, requires_grad=True)
    damped = DiagonalGaussNewton([{"params": [y], "curvature": True}], lr=1.0, betas=(0.0, 0.0), damping=0.01,
                                 max_step=0.75)  # fmt: skip
    ((w * (y - t)) ** 2).sum().backward()
    damped.fold_curvature([torch.sqrt(2 * w * w)])
    damped.step()
    h = 2 * w * w
    expected = (2 * w * w * t / (h + 0.01 * h.mean())).clamp(-0.75, 0.75)
    moved = y.detach()
    assert torch.allclose(moved, expected, atol=1e-6), (moved, expected)
    assert float(moved[0]) < 0.05 * float(t[0]) and float(moved[2]) == pytest.approx(0.5, rel=1e-2)
    assert float(moved[1]) == -0.75
    with pytest.raises(RuntimeError, match="no curvature"):
        ((w * (y - t)) ** 2).sum().backward()
        damped.step()


def test_the_probes_residuals_are_the_losses_own():
    g = torch.Generator().manual_seed(3)
    tonemap = Tonemap()
    radiance, target = torch.rand(64 * 4, 3, generator=g), torch.rand(64, 3, generator=g)
    scale = 0.5 + torch.rand(64, generator=g)
    mse, _ = photometric_loss(radiance, target, 4, tonemap, scale)
    r = photo_residuals(radiance, target, 4, tonemap, scale)
    assert float((r * r).sum()) == pytest.approx(float(mse), rel=1e-5)
    points, values = torch.rand(50, 3, generator=g), torch.rand(50, 9, generator=g)
    anchor = Anchor(points, None, values + 0.1 * torch.rand(50, 9, generator=g), torch.ones(50, 9))
    first, second = torch.randint(0, 50, (30,), generator=g), torch.randint(0, 50, (30,), generator=g)
    lookup = {tuple(p.tolist()): v for p, v in zip(points, values, strict=True)}

    def gbuffer(p: torch.Tensor, uv: torch.Tensor | None) -> torch.Tensor:
        return torch.stack([lookup[tuple(q.tolist())] for q in p])

    for kw in ({}, {"rho_value": 3.0}, {"of": "value", "latent_value": 0.5}):
        cost = consistency(gbuffer, anchor, first, second, 0.5, **kw)
        parts = consistency_residuals(gbuffer, anchor, first, second, 0.5, **kw)
        assert float(sum((p * p).sum() for p in parts)) == pytest.approx(float(cost), rel=1e-5), kw


def test_a_gauss_newton_tto_descends_the_photo_loss(example, truth_prediction):
    from test_tto import per_pixel_error, perturbed  # the TTO tests' helpers (its stop and resume test covers this)

    # paired per-pixel errors on identical pixels and paths, beyond 4 standard errors (measured: 12.5)
    cfg = TTOConfig.preset("tiny", steps=40, pixels=256, spp=8, max_bounces=3, lr=0.2, init="lmrm",
                           optimizer="gauss_newton", gn_lr_scale=0.3, gn_damping=1.0)
    start = build_problem(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap,
                          perturbed(truth_prediction, 0.6), example.basis)  # fmt: skip
    before = per_pixel_error(example, start.params.field())
    after = per_pixel_error(example, optimise(start, cfg).params.field())
    d = before - after
    assert float(d.mean()) > 4 * float(d.std()) / math.sqrt(d.numel()), (float(d.mean()), float(d.std()))


def test_the_gauss_newton_step_needs_the_traced_triplane():
    for bad in ({"estimator": "cached"}, {"field": "uv"}):
        with pytest.raises(ValueError, match="gauss_newton"):
            TTOConfig.preset("tiny", optimizer="gauss_newton", **bad).check()
