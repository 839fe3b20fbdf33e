"""Test-time optimisation: the photometric loss falls and the G-buffers move toward ground truth; the anchor's
weights are exp(-log_var); only the triplane moves; a stopped and resumed TTO equals an uninterrupted one.

All on the bundled example capture (examples/teapot: 23 views at 64 px of a synthetic object whose ground-truth
G-buffers are known), one torch thread, a few seconds per test.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from tto_fixtures import Example, gbuffer_mse, load_example, random_prediction, stop_after

from neumatex_core.capture.tonemap import Tonemap
from neumatex_core.eval import GroundTruth, gbuffer_psnr, truth_lookup
from neumatex_core.fields import Triplane
from neumatex_core.lmrm.inference import LMRMPrediction
from neumatex_core.render.path_tracer import PathTracer, PathTracerConfig
from neumatex_core.render.scene import Scene
from neumatex_core.tto import Anchor, TTOConfig, build_problem, optimise, oracle_weights, uncertainty_weights
from neumatex_core.tto.data import PhotoSet, shuffled_pixels
from neumatex_core.tto.loss import photometric_loss, regulariser, tonemap_slope
from neumatex_core.tto.optimise import step_generator

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def perturbed(pred: LMRMPrediction, std: float, seed: int = 1) -> LMRMPrediction:
    g = torch.Generator().manual_seed(seed)
    planes = pred.triplane.planes + torch.randn(pred.triplane.planes.shape, generator=g) * std
    return LMRMPrediction(Triplane.from_planes(planes), pred.material_decoder, pred.uncertainty_decoder,
                          pred.pbr_decoder)  # fmt: skip


def per_pixel_error(example: Example, field, seed: int = 12345, pixels: int = 2048, spp: int = 8) -> torch.Tensor:
    """Squared tonemapped error [pixels] of `field` on a fixed batch (same pixels, same random numbers)."""
    gen = torch.Generator().manual_seed(seed)
    batch = example.photos.batch(pixels, spp, gen)
    scene = Scene(example.mesh if example.mesh.vertex_normals is not None else example.mesh.with_smooth_normals(),
                  example.envmap, field)  # fmt: skip
    with torch.no_grad():
        radiance = PathTracer(PathTracerConfig(max_bounces=3, spp=spp)).render_rays(
            scene, batch.origins, batch.directions, torch.Generator().manual_seed(seed + 1))
    shown = example.capture.tonemap.apply(radiance.reshape(-1, spp, 3).mean(1))
    return ((shown - batch.target) ** 2).mean(-1)


def test_tto_lowers_photometric_loss_and_moves_gbuffers_toward_truth(example, truth_prediction):
    start = perturbed(truth_prediction, 0.3)
    cfg = TTOConfig.preset("tiny", steps=40, pixels=256, spp=8, max_bounces=3, lr=0.02, reg="none")
    problem = build_problem(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap, start,
                            example.basis)  # fmt: skip
    before_field = problem.params.field()
    before_err = per_pixel_error(example, before_field)
    rho0, lat0 = gbuffer_mse(lambda p: problem.params.gbuffer(p, None), example.gt_points, example.gt_values)
    result = optimise(problem, cfg)
    assert result.finished and result.steps_done == 40 and len(result.history) == 40
    after_err = per_pixel_error(example, result.params.field())
    rho1, lat1 = gbuffer_mse(lambda p: result.params.gbuffer(p, None), example.gt_points, example.gt_values)
    # Paired difference on identical pixels and random numbers: significant beyond 4 standard errors of its mean.
    d = before_err - after_err
    assert float(d.mean()) > 4 * float(d.std()) / math.sqrt(d.numel()), (float(d.mean()), float(d.std()))
    assert rho1 < 0.85 * rho0, (rho0, rho1)
    assert lat1 < lat0, (lat0, lat1)
    gt = GroundTruth(example.gt_points, example.gt_values, torch.zeros(0))
    scores = gbuffer_psnr(lambda p: result.params.gbuffer(p, None), gt)
    assert scores["psnr_basecolor"] == pytest.approx(10 * math.log10(1 / rho1), abs=1e-3)
    assert scores["psnr_latents"] == pytest.approx(10 * math.log10(1 / lat1), abs=1e-3)


@pytest.mark.parametrize("kind", ["l2", "decorrelated", "linear_decorrelated", "decorrelated_debiased"])
def test_decorrelated_photo_loss_has_no_variance_bias(kind):
    """A pixel whose samples are theta * X, X in {0, 2} with equal odds (mean 1, variance 1), against a photo of
    0.2 (theta* = 0.2), 8 spp, linear tonemap. The squared error of the 8-sample mean has expectation
    (theta - 0.2)^2 + theta^2 / 8, so its gradient at theta* is 2 * 0.2 / 8 = 0.05 (the variance pulls theta down);
    the decorrelated loss's gradient there is 0. Means over 40 independent batches of 4096 pixels, judged against
    their own standard error."""
    spp, n, batches = 8, 4096, 40
    g = torch.Generator().manual_seed(3)
    grads = []
    for _ in range(batches):
        theta = torch.tensor(0.2, requires_grad=True)
        x = 2.0 * torch.randint(0, 2, (n * spp, 1), generator=g).float().expand(-1, 3)
        objective, mse = photometric_loss(theta * x, torch.full((n, 3), 0.2), spp, Tonemap(transfer="linear"),
                                          kind=kind)  # fmt: skip
        (grad,) = torch.autograd.grad(objective, theta)
        grads.append(float(grad))
        assert not mse.requires_grad
    mean = sum(grads) / batches
    se = math.sqrt(sum((v - mean) ** 2 for v in grads) / (batches - 1) / batches)
    if kind == "l2":
        assert abs(mean - 0.05) < 4 * se and mean > 8 * se, (mean, se)
    else:
        assert abs(mean) < 4 * se and se < 0.005, (mean, se)


@pytest.mark.parametrize("kind", ["l2", "decorrelated", "linear_decorrelated", "decorrelated_debiased"])
def test_debiased_losses_are_least_at_a_noise_free_photo_through_the_srgb_tonemap(kind):
    """Samples theta * X, X in {0.5, 1.5} with equal odds, 8 spp, against a noise-free photo T(0.2) through the sRGB
    tonemap (theta* = 0.2). The L2's gradient at theta* is its two biases': the tonemap's concavity (an 8-sample
    mean's tonemap lies below T(theta), which pushes theta up) and the variance term (down, larger here), so it is
    > 0 (about 0.002); "decorrelated" has only the concavity of its 4-sample halves, < 0 (about -0.01); both beyond
    8 standard errors of the mean over 40 batches of 4096 pixels. "linear_decorrelated" (no curvature in linear
    radiance, no variance term) and "decorrelated_debiased" (each half's gap removed by the delta method, exact to
    second order: the rest is below the test's noise here) have 0 within 4 standard errors."""
    spp, n, batches = 8, 4096, 40
    tonemap = Tonemap(transfer="srgb")
    g = torch.Generator().manual_seed(3)
    grads = []
    for _ in range(batches):
        theta = torch.tensor(0.2, requires_grad=True)
        x = (0.5 + torch.randint(0, 2, (n * spp, 1), generator=g).float()).expand(-1, 3)
        objective, _ = photometric_loss(theta * x, tonemap.apply(torch.full((n, 3), 0.2)), spp, tonemap, kind=kind)
        (grad,) = torch.autograd.grad(objective, theta)
        grads.append(float(grad))
    mean = sum(grads) / batches
    se = math.sqrt(sum((v - mean) ** 2 for v in grads) / (batches - 1) / batches)
    if kind == "l2":
        assert mean > 8 * se, (mean, se)
    elif kind == "decorrelated":
        assert mean < -8 * se, (mean, se)
    else:
        assert abs(mean) < 4 * se and se < 0.0005, (mean, se)


def test_linear_loss_weighed_at_the_smoothed_photo_is_not_pulled_darker_by_the_photos_noise(example):
    """Noisy photos of a flat radiance mu = 0.2 (each foreground pixel mu * Z, Z in {0.5, 1.5} with equal odds, sRGB
    tonemap) and a noise-free render theta. "linear_decorrelated" weighs a pixel by T'(x)^2 with x its photo's
    linear value; at its own value the darker pixels weigh more, so at theta = mu the gradient is the mean of
    2 T'(x)^2 (mu - x): 0.1 (T'(0.1)^2 - T'(0.3)^2) in expectation, > 0, pulling theta below mu. Weighed at the
    photo's 5 x 5 foreground mean (`PhotoSet.smoothed_colour(2)`) a pixel's own noise is at most 1/ (the window's
    foreground pixels) of its weight's argument, so the expected gradient at mu is near 0: asserted below a tenth of
    the own-value one (an interior pixel's window holds 25 pixels; the silhouette's fewer). Both within 4 standard
    errors of their per-pixel terms."""
    tonemap = Tonemap(transfer="srgb")
    g = torch.Generator().manual_seed(5)
    images, mu = [], 0.2
    for cam in example.photos.cameras:
        z = 0.5 + torch.randint(0, 2, (cam.height, cam.width, 1), generator=g).float()
        images.append(tonemap.apply(mu * z.expand(-1, -1, 3)).numpy())
    photos = PhotoSet(images, example.photos.cameras, example.mesh)
    smoothed = photos.smoothed_colour(2)
    assert torch.equal(photos.smoothed_colour(0), photos.colour)
    # one interior pixel checked by hand: its window's foreground pixels' mean
    k = int(((photos.pixel[:, 0] == 0) & (photos.pixel[:, 1] == 32) & (photos.pixel[:, 2] == 32)).nonzero()[0])
    near = (photos.pixel[:, 0] == 0) & ((photos.pixel[:, 1:] - photos.pixel[k, 1:]).abs().amax(1) <= 2)
    assert torch.allclose(smoothed[k], photos.colour[near].mean(0), atol=1e-6) and int(near.sum()) == 25
    n = photos.size

    def per_pixel_gradient(weight_target: torch.Tensor | None) -> torch.Tensor:
        theta = torch.full((n, 1), mu, requires_grad=True)
        radiance = theta.expand(-1, 3).repeat_interleave(2, 0)  # 2 identical samples a pixel: no render noise
        objective, _ = photometric_loss(radiance, photos.colour, 2, tonemap, kind="linear_decorrelated",
                                        weight_target=weight_target)  # fmt: skip
        (grad,) = torch.autograd.grad(objective * n, theta)
        return grad.squeeze(1)  # each pixel's term of the gradient on a shared theta

    def slope(x: float) -> float:
        return float(tonemap_slope(tonemap, torch.full((1, 3), x))[0, 0])

    expected = 0.1 * (slope(0.1) ** 2 - slope(0.3) ** 2)
    own, weighed = per_pixel_gradient(None), per_pixel_gradient(smoothed)
    se = float(own.std()) / math.sqrt(n)
    assert expected > 20 * se and abs(float(own.mean()) - expected) < 4 * se, (float(own.mean()), expected, se)
    assert abs(float(weighed.mean())) < 0.1 * expected + 4 * float(weighed.std()) / math.sqrt(n), \
        (float(weighed.mean()), expected)


def test_decorrelated_photo_loss_logs_the_full_pixel_error():
    """Both kinds log the same mse (of the spp-sample mean); the decorrelated objective is the product of the two
    halves' errors, so it differs from that mse and can be negative."""
    radiance = torch.tensor([[0.1] * 3, [0.5] * 3, [0.3] * 3, [0.0] * 3])  # 2 pixels x 2 spp
    target = torch.tensor([[0.3] * 3, [0.2] * 3])
    tonemap = Tonemap(transfer="linear")
    l2, mse = photometric_loss(radiance, target, 2, tonemap)
    dec, mse_d = photometric_loss(radiance, target, 2, tonemap, kind="decorrelated")
    assert float(mse) == pytest.approx(float(l2)) == pytest.approx(float(mse_d)) == pytest.approx(0.00125)
    assert float(dec) == pytest.approx(((0.1 - 0.3) * (0.5 - 0.3) + (0.3 - 0.2) * (0.0 - 0.2)) / 2)
    with pytest.raises(ValueError, match="spp >= 2"):
        photometric_loss(radiance, target.repeat(2, 1), 1, tonemap, kind="decorrelated")
    with pytest.raises(ValueError, match="spp >= 2"):
        TTOConfig.preset("cpu", photo_loss="decorrelated", spp=1).check()


def test_debiased_decorrelated_loss_is_the_product_of_each_halfs_debiased_error():
    """One pixel of 4 samples through the sRGB tonemap: the objective is (T(a) - g_a - y)(T(b) - g_b - y) with a, b
    the halves' means and g = T''(mean) s^2 / (2 * 2) (s^2 the half's unbiased sample variance, T'' by finite
    differences here); under a linear tonemap (T'' = 0) it is "decorrelated" itself."""
    tonemap = Tonemap(transfer="srgb")
    radiance = torch.tensor([[0.1] * 3, [0.3] * 3, [0.2] * 3, [0.6] * 3])
    target = torch.full((1, 3), 0.5)

    def curvature(x: float, h: float = 1e-4) -> float:
        t = tonemap.apply(torch.tensor([x - h, x, x + h], dtype=torch.float64))
        return float((t[0] - 2 * t[1] + t[2]) / h**2)

    def shown(x: float) -> float:
        return float(tonemap.apply(torch.tensor(x)))

    ea = shown(0.2) - curvature(0.2) * 0.02 / 4 - 0.5
    eb = shown(0.4) - curvature(0.4) * 0.08 / 4 - 0.5
    objective, _ = photometric_loss(radiance, target, 4, tonemap, kind="decorrelated_debiased")
    assert float(objective) == pytest.approx(ea * eb, rel=1e-3)
    linear = Tonemap(transfer="linear")
    debiased, _ = photometric_loss(radiance, target, 4, linear, kind="decorrelated_debiased")
    plain, _ = photometric_loss(radiance, target, 4, linear, kind="decorrelated")
    assert float(debiased) == pytest.approx(float(plain)) == pytest.approx((0.2 - 0.5) * (0.4 - 0.5))
    with pytest.raises(ValueError, match="spp >= 4"):
        photometric_loss(radiance, target.repeat(2, 1), 2, tonemap, kind="decorrelated_debiased")
    with pytest.raises(ValueError, match="unknown photometric loss"):
        photometric_loss(radiance, target, 4, tonemap, kind="l1")  # type: ignore[arg-type]


def test_regulariser_weights_are_exp_minus_log_var():
    target = torch.tensor([[0.2, 0.4, 0.6], [0.1, -0.5, 0.9]])
    log_var = torch.tensor([[0.0, -2.0, 1.0], [3.0, -1.0, 0.5]])
    anchor = Anchor(torch.zeros(2, 3), None, target, uncertainty_weights(log_var))
    value = torch.tensor([[0.3, 0.1, 0.6], [0.4, -0.2, 0.0]], requires_grad=True)
    reg = regulariser(lambda p, uv: value, anchor, torch.arange(2))
    expected = (torch.exp(-log_var) * (value.detach() - target) ** 2).mean()
    assert torch.allclose(reg, expected)
    reg.backward()
    assert value.grad is not None
    want = 2 * torch.exp(-log_var) * (value.detach() - target) / value.numel()
    assert torch.allclose(value.grad, want)
    # The oracle weights are 1 / squared error, floored.
    truth = target + torch.tensor([[0.1, 0.0, 1.0], [0.5, 0.2, 0.01]])
    w = oracle_weights(target, truth, eps=1e-3)
    assert torch.allclose(w, 1 / ((target - truth) ** 2).clamp_min(1e-3))


def test_anchor_uses_the_lmrm_uncertainty_and_pulls_toward_its_gbuffers(example, truth_prediction):
    # An "LMRM" that is nearly right and confident (log_var = -4 everywhere via the decoder's bias).
    pred = perturbed(truth_prediction, 0.0)
    with torch.no_grad():
        last = pred.uncertainty_decoder.net[-1]
        last.weight.zero_()
        last.bias.fill_(-4.0)
    base = TTOConfig.preset("tiny", steps=10, pixels=64, spp=1, max_bounces=1, lr=0.05, init="random",
                            lambda_reg=0.05)  # fmt: skip
    problem = build_problem(base, example.mesh, example.envmap, example.photos, example.capture.tonemap, pred,
                            example.basis)  # fmt: skip
    anchor = problem.anchor
    assert anchor is not None
    assert torch.allclose(anchor.weight, torch.full_like(anchor.weight, math.exp(4.0)))
    rho_a, lat_a, _ = pred.gbuffers(anchor.points)
    assert torch.allclose(anchor.target, torch.cat([rho_a, lat_a], -1))
    reg_run = optimise(problem, base)
    free = replace(base, reg="none")
    free_run = optimise(build_problem(free, example.mesh, example.envmap, example.photos, example.capture.tonemap,
                                      pred, example.basis), free)  # fmt: skip
    target = torch.cat([rho_a, lat_a], -1)

    def distance(run) -> float:
        with torch.no_grad():
            return float(((run.params.gbuffer(anchor.points, None) - target) ** 2).mean())

    assert distance(reg_run) < 0.7 * distance(free_run), (distance(reg_run), distance(free_run))


def test_gradients_reach_only_the_triplane(example, truth_prediction):
    pred = perturbed(truth_prediction, 0.1)
    cfg = TTOConfig.preset("tiny", steps=1, pixels=64, spp=1, max_bounces=2, init="lmrm")
    # reg="uncertainty" with a prediction: the anchor is active as well as the photometric term.
    problem = build_problem(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap, pred,
                            example.basis)  # fmt: skip
    frozen = {name: p.detach().clone() for mod in (pred.material_decoder, pred.uncertainty_decoder, example.basis)
              for name, p in mod.named_parameters(prefix=type(mod).__name__)}  # fmt: skip
    start = problem.params.tensor.detach().clone()
    optimise(problem, cfg)
    assert problem.params.tensor.requires_grad and problem.params.tensor.grad is not None
    assert float(problem.params.tensor.grad.abs().sum()) > 0
    assert not torch.equal(problem.params.tensor.detach(), start)
    for mod in (pred.material_decoder, pred.uncertainty_decoder, pred.pbr_decoder, example.basis):
        for name, p in mod.named_parameters(prefix=type(mod).__name__):
            assert not p.requires_grad and p.grad is None, name
            if name in frozen:
                assert torch.equal(p, frozen[name]), name
    # The prediction's own triplane (the anchor) is a separate tensor and stays put.
    assert torch.equal(pred.triplane.planes, perturbed(truth_prediction, 0.1).triplane.planes)


@pytest.mark.parametrize("variant", [{"estimator": "path"}, {"estimator": "cached"},
                                     {"optimizer": "gauss_newton", "train_decoder": True},
                                     {"control_variate": "settle", "settle_fraction": 2 / 3, "settle_spp": 4,
                                      "cv_spp": 4, "cv_refresh": 2, "train_decoder": True},
                                     {"pixel_order": "shuffled", "stratified": True, "settle_fraction": 1 / 3,
                                      "settle_spp": 4}])  # fmt: skip
def test_stop_and_resume_equals_an_uninterrupted_run(example, truth_prediction, tmp_path, variant):
    # cached: rebuilt at steps 0 and 4, so the stop after step 3 resumes inside the first cache's round; the control
    # variate's copies are made at steps 2 (the settling's first) and 4, so it resumes inside the first copy's round
    cfg = TTOConfig.preset("tiny", steps=6, pixels=64, spp=2, max_bounces=2, checkpoint_every=0, init="lmrm",
                           cache_pixels=128, cache_every=4, **variant)  # fmt: skip

    def problem():
        return build_problem(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap,
                             perturbed(truth_prediction, 0.2), example.basis)  # fmt: skip

    whole = optimise(problem(), cfg)
    checkpoint = tmp_path / "checkpoint.pt"
    first = optimise(problem(), cfg, should_stop=stop_after(3), checkpoint=checkpoint)
    assert not first.finished and first.steps_done == 3 and checkpoint.is_file()
    second = optimise(problem(), cfg, checkpoint=checkpoint)
    assert second.finished and second.steps_done == 6
    assert torch.equal(second.params.tensor, whole.params.tensor)
    assert second.history == whole.history
    # A checkpoint of another configuration is refused with a clear message.
    with pytest.raises(ValueError, match="another configuration"):
        optimise(problem(), replace(cfg, lr=0.5), checkpoint=checkpoint)


@pytest.mark.parametrize("field,material,reg", [("uv", "neural", "uncertainty"), ("triplane", "pbr", "uncertainty"),
                                                ("uv", "pbr", "none"), ("triplane", "neural", "oracle")])
def test_variants_optimise_their_own_tensor(example, truth_prediction, field, material, reg):
    pred = perturbed(truth_prediction, 0.2)
    cfg = TTOConfig.preset("tiny", steps=3, pixels=64, spp=1, max_bounces=1, field=field, material=material, reg=reg,
                           uv_resolution=32)  # fmt: skip
    truth = truth_lookup(GroundTruth(example.gt_points, example.gt_values, torch.zeros(0))) if reg == "oracle" else None
    problem = build_problem(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap, pred,
                            example.basis, truth=truth)  # fmt: skip
    channels = {"neural": 9, "pbr": 5}[material]
    if field == "uv":
        assert tuple(problem.params.tensor.shape) == (32, 32, channels) and problem.mesh.uvs is not None
    start = problem.params.tensor.detach().clone()
    result = optimise(problem, cfg)
    assert result.finished and all(math.isfinite(r["loss"]) for r in result.history)
    assert not torch.equal(result.params.tensor.detach(), start)
    if field == "uv":
        t = result.params.tensor.detach()
        assert float(t.min()) >= (-1 if material == "neural" else 0) and float(t.max()) <= 1
    if reg != "none":
        assert problem.anchor is not None and problem.anchor.target.shape[-1] == channels


def test_misconfigured_variants_fail_clearly(example):
    pred = random_prediction()
    cfg = TTOConfig.preset("tiny")
    with pytest.raises(ValueError, match="no trained LMRM"):
        build_problem(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap, pred, example.basis,
                      anchor_available=False)  # fmt: skip
    with pytest.raises(ValueError, match="ground-truth"):
        build_problem(replace(cfg, reg="oracle"), example.mesh, example.envmap, example.photos,
                      example.capture.tonemap, pred, example.basis)  # fmt: skip
    with pytest.raises(ValueError, match="field"):
        replace(cfg, field="mesh").check()  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="pixel_order"):
        replace(cfg, pixel_order="sorted").check()  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="stratified off"):
        replace(cfg, control_variate="all", stratified=True).check()
    assert step_generator(cfg, 3, torch.device("cpu")).initial_seed() == step_generator(cfg, 3, torch.device("cpu")
                                                                                       ).initial_seed()


def test_pbr_maps_into_the_basis_with_its_albedo():
    """PBR -> layered -> encoder: the neural material's directional albedo (cosine-weighted average over wo) is
    the PBR material's within 5% per channel for rough dielectrics (estimated with 2e5 common random samples: the
    standard error is under 0.5%)."""
    from neumatex_core.materials.base import cosine_sample
    from neumatex_core.materials.neural_basis import NeuralMaterial
    from neumatex_core.materials.pbr import PBRMaterial
    from neumatex_core.materials.pbr_to_neural import pbr_to_neural

    basis = load_example().basis
    g = torch.Generator().manual_seed(0)
    n = 200_000
    wo, wi = cosine_sample(torch.rand(n, 2, generator=g)), cosine_sample(torch.rand(n, 2, generator=g))
    for base, rough in (((0.8, 0.2, 0.1), 0.5), ((0.3, 0.5, 0.8), 0.8), ((0.5, 0.5, 0.5), 0.35)):
        b = torch.tensor(base).expand(n, 3)
        r, m = torch.full((n,), rough), torch.zeros(n)
        rho, latent = pbr_to_neural(basis, b, r, m)
        pbr = (PBRMaterial(b, r, m).eval(wi, wo) * math.pi).mean(0)
        neural = (NeuralMaterial(basis, rho, latent).eval(wi, wo) * math.pi).mean(0)
        assert torch.allclose(neural, pbr, rtol=0.05), (base, rough, pbr, neural)


def test_init_pbr_runs_pbr_then_starts_the_neural_field_at_its_solution(example, truth_prediction, tmp_path):
    from neumatex_core.tto import solve

    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="none")
    result = solve(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap,
                   perturbed(truth_prediction, 0.2), example.basis, checkpoint_dir=tmp_path)  # fmt: skip
    assert result.finished and len(result.history) == 8
    assert [r["phase"] for r in result.history] == [0.0] * 4 + [1.0] * 4
    assert (tmp_path / "checkpoint_pbr.pt").is_file() and (tmp_path / "checkpoint.pt").is_file()
    # The start is the PBR solution expressed in the basis: the planes' fit leaves a small G-buffer error.
    assert result.history[-1]["start_mse"] < 0.01
    with pytest.raises(ValueError, match="init='pbr'"):
        replace(cfg, material="pbr").check()


def test_reg_start_anchors_the_neural_phase_to_its_pbr_start(example, truth_prediction, tmp_path):
    """reg="start": the neural phase is pulled towards the start it was fitted to (the PBR solution in the basis):
    zero at its first step (the start itself), positive once the photos move it; only with init="pbr"."""
    from neumatex_core.tto import solve

    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=1.0)  # fmt: skip
    result = solve(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap,
                   perturbed(truth_prediction, 0.2), example.basis)  # fmt: skip
    neural = [r["reg"] for r in result.history if r["phase"] == 1.0]
    assert len(neural) == 4 and neural[0] == pytest.approx(0.0, abs=1e-9) and max(neural) > 0
    with pytest.raises(ValueError, match="reg='start'"):
        replace(cfg, init="lmrm").check()


def test_consistency_costs_a_change_that_varies_over_a_material_not_one_it_shares(example, truth_prediction):
    """L_cons (reg "start", lambda_consistency): points that start alike must change alike ("change") or end alike
    ("value"), and with consistency_rho_value / _latent_value their base colours / latents end alike too. A
    change shared by every point of a material costs nothing, even when two materials change differently; a change
    that varies over one material costs the mean squared difference of its pairs; the TTO logs it (0 at the start)
    and the check refuses it with an anchor to the LMRM."""
    from neumatex_core.tto import solve
    from neumatex_core.tto.loss import consistency

    g = torch.Generator().manual_seed(3)
    points = torch.rand(512, 3, generator=g) * 2 - 1
    target = torch.zeros(512, 9)
    target[256:] = 1.0  # two materials, 3 (> 4 sigma) apart in G-buffer space
    anchor = Anchor(points, None, target, torch.ones_like(target))
    first, second = torch.randint(0, 512, (4096,), generator=g), torch.randint(0, 512, (4096,), generator=g)

    def changed_by(change):
        return lambda p, uv: target[torch.cdist(p, points).argmin(1)] + change(p)

    shared = torch.linspace(-0.2, 0.3, 9)
    assert consistency(changed_by(lambda p: shared.expand(p.shape[0], 9)), anchor, first, second, 0.25) == 0
    per_material = changed_by(lambda p: torch.where(torch.cdist(p, points).argmin(1, keepdim=True) < 256, 0.3, -0.2)
                              .expand(p.shape[0], 9))  # fmt: skip
    assert float(consistency(per_material, anchor, first, second, 0.25)) < 1e-6
    varying = changed_by(lambda p: 0.1 * p[:, :1].expand(p.shape[0], 9))
    same = (first < 256) == (second < 256)
    expected = float((0.01 * (points[first, 0] - points[second, 0]) ** 2)[same].mean())
    assert float(consistency(varying, anchor, first, second, 0.25)) == pytest.approx(expected, rel=1e-4)
    # of="value": points that start alike must end alike, whatever the start was: two uniform materials cost
    # nothing (their pairs across are not compared), a value varying over one costs what the change did above.
    uniform = changed_by(lambda p: torch.zeros(p.shape[0], 9))
    assert float(consistency(uniform, anchor, first, second, 0.25, of="value")) < 1e-6
    assert float(consistency(varying, anchor, first, second, 0.25, of="value")) == pytest.approx(expected, rel=1e-4)
    noisy_start = Anchor(points, None, target + 0.05 * torch.randn(512, 9, generator=g), torch.ones_like(target))
    assert float(consistency(uniform, noisy_start, first, second, 0.25, of="value")) < 1e-6  # ends alike: free
    assert float(consistency(uniform, noisy_start, first, second, 0.25)) > 1e-3  # "change" keeps the start's noise
    # rho_value / latent_value: "change" for everything plus that part's values; on the clean start a change
    # varying over every channel costs its change (mean over 9) and the part's value differences at weight 2 (mean
    # over its channels) on top; on the noisy start, a uniform result pays only the change term (the part ends
    # alike whatever the start's noise)
    for part in ({"rho_value": 2.0}, {"latent_value": 2.0}):
        assert float(consistency(varying, anchor, first, second, 0.25, **part)) == pytest.approx(3 * expected,
                                                                                                rel=1e-4)
        assert float(consistency(uniform, noisy_start, first, second, 0.25, **part)) == pytest.approx(
            float(consistency(uniform, noisy_start, first, second, 0.25)), rel=1e-5)

    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=0.0, lambda_consistency=1.0)  # fmt: skip
    result = solve(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap,
                   perturbed(truth_prediction, 0.2), example.basis)  # fmt: skip
    cons = [r["consistency"] for r in result.history if r["phase"] == 1.0]
    assert len(cons) == 4 and cons[0] == pytest.approx(0.0, abs=1e-9) and max(cons) > 0
    assert all("consistency" not in r for r in result.history if r["phase"] == 0.0)
    # with rho_value the start itself pays: its base colours differ between alike points, its changes do not
    result = solve(replace(cfg, consistency_rho_value=1.0), example.mesh, example.envmap, example.photos,
                   example.capture.tonemap, perturbed(truth_prediction, 0.2), example.basis)  # fmt: skip
    assert [r["consistency"] for r in result.history if r["phase"] == 1.0][0] > 1e-6
    with pytest.raises(ValueError, match="lambda_consistency"):
        replace(cfg, init="lmrm", reg="uncertainty").check()
    with pytest.raises(ValueError, match="consistency_rho_value"):
        replace(cfg, lambda_consistency=0.0, consistency_rho_value=1.0).check()


def test_select_anchor_keeps_the_result_that_reproduces_held_out_photos_better(example, truth_prediction, tmp_path):
    """select_anchor: both phases fit all photos but the held-out ones (spread over the capture), the neural phase
    anchored and free, each scored on the held-out photos; the margin decides (a huge one keeps the anchor, a
    hugely negative one drops it), and the result is then bit for bit the plain TTO on every photo with the chosen
    weight. The held-out photos are spread over the capture but each has a fitted photo within 30 degrees, so the
    preset views' bottom view (-Y, the only one that sees the underside) is never held out. A PhotoSet subset keeps
    each photo's foreground pixels."""
    from neumatex_core.tto import solve
    from neumatex_core.tto.pbr_start import photo_psnr, validation_frames

    photos = example.photos
    from neumatex_core.geometry.camera import preset_views

    views, origin = preset_views(16), np.zeros(3)
    assert validation_frames(views, 4, origin) == [2, 8, 14, 21]  # the even spread's 20 is -Y: its slot takes 21
    assert 20 not in validation_frames(views, 11, origin)
    assert validation_frames(views[:5], 4, origin) == [0, 2, 3]  # 5 orbit views 21 degrees apart: 2 stay to fit
    with pytest.raises(ValueError, match="only 4"):
        validation_frames(views[:4], 4, origin)
    with pytest.raises(ValueError, match="none of the capture's 6"):
        validation_frames(views[17:], 2, origin)  # the canonical views are 90 degrees apart
    part = photos.subset([3, 1])
    for new, old in ((0, 3), (1, 1)):
        assert torch.equal(part.colour[part.pixel[:, 0] == new], photos.colour[photos.pixel[:, 0] == old])
    assert part.cameras == [photos.cameras[3], photos.cameras[1]] and part.count == 2

    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=1.0, select_anchor=True, select_margin_db=100.0, select_fraction=0.5)  # fmt: skip
    cfg.check()
    args = (example.mesh, example.envmap, photos, example.capture.tonemap, perturbed(truth_prediction, 0.2),
            example.basis)  # fmt: skip
    steps: list[int] = []
    kept = solve(cfg, *args, checkpoint_dir=tmp_path, progress=lambda s, n, row: steps.append(s))
    assert steps == list(range(1, cfg.run_steps() + 1)) and cfg.run_steps() == 4 + 2 * 2 + 8 and kept.finished
    assert {p.name for p in tmp_path.iterdir()} >= {"select_pbr.pt", "select_anchored.pt", "select_free.pt",
                                                     "checkpoint_pbr.pt", "checkpoint.pt"}  # fmt: skip
    sel = kept.selection
    assert sel["anchor_kept"] == 1.0 and sel["validation_photos"] == 4.0
    assert math.isfinite(sel["validation_psnr_anchored"]) and math.isfinite(sel["validation_psnr_free"])
    plain = solve(replace(cfg, select_anchor=False), *args)
    assert torch.equal(kept.params.tensor, plain.params.tensor)
    free = solve(replace(cfg, select_margin_db=-100.0), *args)
    assert free.selection["anchor_kept"] == 0.0
    assert free.selection["validation_psnr_free"] == pytest.approx(sel["validation_psnr_free"], abs=1e-6)
    plain_free = solve(replace(cfg, select_anchor=False, lambda_reg=0.0), *args)
    assert torch.equal(free.params.tensor, plain_free.params.tensor)
    assert all(r["reg"] == 0.0 for r in free.history if r["phase"] == 1.0)
    # the clean score is deterministic in its seed (common random numbers for the two results)
    held = photos.subset(validation_frames(photos.cameras, 4, example.mesh.bounding_sphere()[0]))
    score = photo_psnr(plain.params, plain.mesh, example.envmap, held, example.capture.tonemap, cfg, 7)
    assert score == photo_psnr(plain.params, plain.mesh, example.envmap, held, example.capture.tonemap, cfg, 7)
    # validation_spp is its samples per pixel, validation_stride the step between its pixels (other draws either
    # way). On this small scene the gap between the anchored and the free result at 16 samples, or on every other
    # pixel, over five seeds, is the one at cfg's 32 on every pixel within 4 standard errors of the difference (the
    # seeds' spread); on the benchmark's and Cycles' captures either moved choices, so the defaults stay (design
    # note 42)
    def gap(seed: int, **scoring: int) -> float:
        c, tonemap = replace(cfg, **scoring), example.capture.tonemap
        return (photo_psnr(plain.params, plain.mesh, example.envmap, held, tonemap, c, seed)
                - photo_psnr(plain_free.params, plain_free.mesh, example.envmap, held, tonemap, c, seed))

    full = np.array([gap(s) for s in range(5)])
    assert (cfg.validation_spp, cfg.validation_stride) == (32, 1)
    for scoring in ({"validation_spp": 16}, {"validation_stride": 2}):
        fewer = np.array([gap(s, **scoring) for s in range(5)])
        assert fewer[0] != full[0]
        assert abs(fewer.mean() - full.mean()) < 4 * math.sqrt((fewer.var(ddof=1) + full.var(ddof=1)) / 5)
    with pytest.raises(ValueError, match="select_anchor"):
        replace(cfg, reg="none").check()


def test_select_uniform_chooses_between_uniform_and_textured_on_held_out_photos(example, truth_prediction,
                                                                                tmp_path):
    """select_uniform: the same choice as select_anchor, between one uniform material (the consistency term with the
    base colours' values too, consistency_rho_value UNIFORM_RHO_VALUE) and the term as configured ("textured");
    uniform, the more constrained, is kept unless textured gains more than the margin, and the result is then bit
    for bit the plain TTO with the chosen config. The progress counts every step the choice runs
    (TTOConfig.run_steps); select_fraction shortens the candidates' phases and nothing else."""
    from neumatex_core.tto import solve
    from neumatex_core.tto.config import UNIFORM_RHO_VALUE

    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=0.0, lambda_consistency=1.0, select_uniform=True, select_fraction=1.0,
                           select_margin_db=100.0)  # fmt: skip
    cfg.check()
    assert cfg.run_steps() == 3 * 4 + 2 * 4 and cfg.total_steps() == 8
    args = (example.mesh, example.envmap, example.photos, example.capture.tonemap, perturbed(truth_prediction, 0.2),
            example.basis)  # fmt: skip
    steps: list[int] = []
    kept = solve(cfg, *args, checkpoint_dir=tmp_path, progress=lambda s, n, row: steps.append(s))
    assert steps == list(range(1, cfg.run_steps() + 1)) and kept.finished
    assert {p.name for p in tmp_path.iterdir()} >= {"select_pbr.pt", "select_uniform.pt", "select_textured.pt"}
    sel = kept.selection
    assert sel["uniform_kept"] == 1.0 and sel["validation_photos"] == 4.0
    assert math.isfinite(sel["validation_psnr_uniform"]) and math.isfinite(sel["validation_psnr_textured"])
    # the evidence of light painted into the textured candidate's base colour is recorded (tto/baked_light.py)
    assert all(math.isfinite(sel[k]) for k in ("light_slope", "light_correlation", "texture_spread"))
    assert sel["texture_spread"] > 0 and -1.0 <= sel["light_correlation"] <= 1.0
    textured = replace(cfg, select_uniform=False)
    uniform = replace(textured, consistency_rho_value=UNIFORM_RHO_VALUE)
    plain_uniform = solve(uniform, *args)
    assert torch.equal(kept.params.tensor, plain_uniform.params.tensor)
    # a shorter choice (select_fraction: each candidate's neural phase runs half the steps) is counted as such and
    # changes only the candidates, not the TTO with the chosen config that follows
    short = replace(cfg, select_fraction=0.5)
    assert short.select_steps() == 2 and short.run_steps() == 4 + 2 * 2 + 8
    steps.clear()
    quick = solve(short, *args, progress=lambda s, n, row: steps.append(s))
    assert steps == list(range(1, short.run_steps() + 1))
    assert quick.selection["validation_psnr_uniform"] != sel["validation_psnr_uniform"]
    assert torch.equal(quick.params.tensor, plain_uniform.params.tensor)
    chose_textured = solve(replace(cfg, select_margin_db=-100.0), *args)
    assert chose_textured.selection["uniform_kept"] == 0.0
    assert chose_textured.selection["light_slope"] == sel["light_slope"]  # the same candidates, the same evidence
    assert chose_textured.selection["validation_psnr_textured"] == pytest.approx(sel["validation_psnr_textured"],
                                                                                 abs=1e-6)  # fmt: skip
    plain_textured = solve(textured, *args)
    assert torch.equal(chose_textured.params.tensor, plain_textured.params.tensor)
    assert not torch.equal(plain_textured.params.tensor, kept.params.tensor)  # the base colours' values did change it
    # a capture too small to hold 4 photos out gets the fallback, textured (what uniform costs a textured object is
    # the larger risk), and says so
    few = (args[0], args[1], example.photos.subset([0, 1, 2, 3]), *args[3:])
    steps.clear()
    fallback = solve(cfg, *few, progress=lambda s, n, row: steps.append(s))
    assert fallback.selection == {"uniform_kept": 0.0, "validation_photos": 0.0}
    assert steps[-1] == cfg.run_steps()  # the progress still ends at 100%
    assert torch.equal(fallback.params.tensor, solve(textured, *few).params.tensor)
    for bad in (dict(lambda_consistency=0.0), dict(init="lmrm", reg="none"), dict(select_anchor=True, lambda_reg=1.0)):
        with pytest.raises(ValueError, match="select_uniform"):
            replace(cfg, **bad).check()


@pytest.fixture
def start_fits(monkeypatch) -> list[int]:
    """One entry per call of tto/pbr_start.py `fit_start_to_pbr` (1500 Adam steps each at the cpu preset)."""
    from neumatex_core.tto import pbr_start

    calls: list[int] = []
    fit = pbr_start.fit_start_to_pbr

    def counted(*a, **k):
        calls.append(1)
        return fit(*a, **k)

    monkeypatch.setattr(pbr_start, "fit_start_to_pbr", counted)
    return calls


def resumed_after_stop(cfg: TTOConfig, args: tuple, folder, before_end: int):
    """`solve(cfg, *args)` with checkpoints in `folder`, stopped `before_end` steps before its end (asserted), then
    run again from those checkpoints: the resumed result."""
    from neumatex_core.tto import solve

    seen: list[int] = []
    stopped = solve(cfg, *args, checkpoint_dir=folder, progress=lambda s, n, row: seen.append(s),
                    should_stop=lambda: bool(seen) and seen[-1] >= cfg.run_steps() - before_end)  # fmt: skip
    assert not stopped.finished and seen[-1] == cfg.run_steps() - before_end
    return solve(cfg, *args, checkpoint_dir=folder)


def test_select_reuse_start_goes_on_from_the_start_the_choice_made(example, truth_prediction, tmp_path, start_fits):
    """select_reuse_start: after the choice, the TTO with the chosen config is its neural phase alone, on every
    photo, from the start the choice made (the PBR phase on all photos but the held-out ones, fitted once for both
    candidates and the TTO after): no second PBR phase and no second start fit. The choice is the one the TTO that
    runs both phases again makes; the progress counts the steps it runs; stopped in the last phase and resumed, the
    result is bit for bit the same; with photo exposures, the held-out photos' start at 1."""
    from neumatex_core.tto import solve

    calls = start_fits
    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=0.0, lambda_consistency=1.0, select_uniform=True, select_fraction=0.5,
                           select_reuse_start=True, pbr_fit_steps=50)  # fmt: skip
    assert cfg.run_steps() == 4 + 2 * 2 + 4
    args = (example.mesh, example.envmap, example.photos, example.capture.tonemap, perturbed(truth_prediction, 0.2),
            example.basis)  # fmt: skip
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    steps: list[int] = []
    reused = solve(cfg, *args, checkpoint_dir=tmp_path / "a", progress=lambda s, n, row: steps.append(s))
    assert steps == list(range(1, cfg.run_steps() + 1)) and reused.finished
    assert len(calls) == 1  # one start fit for the two candidates and the TTO after
    names = {p.name for p in (tmp_path / "a").iterdir()}
    assert "checkpoint.pt" in names and "checkpoint_pbr.pt" not in names  # no second PBR phase
    assert [r["phase"] for r in reused.history] == [0.0] * 4 + [1.0] * 4
    again = solve(replace(cfg, select_reuse_start=False), *args)
    assert len(calls) == 3  # the choice's fit, then the TTO after fits its own start again
    assert again.selection == reused.selection and reused.selection["validation_photos"] == 4.0
    assert not torch.equal(again.params.tensor, reused.params.tensor)  # its start came from every photo's PBR fit
    # stopped two steps before the end, then resumed from the checkpoints: the same result
    resumed = resumed_after_stop(cfg, args, tmp_path / "b", 2)
    assert resumed.finished and torch.equal(resumed.params.tensor, reused.params.tensor)
    exposed = solve(replace(cfg, photo_exposure=True), *args)
    assert exposed.exposure is not None and len(exposed.exposure) == example.photos.count


def test_select_continue_goes_on_from_the_chosen_candidate(example, truth_prediction, tmp_path, monkeypatch):
    """select_continue: the TTO after the choice starts from the chosen candidate's planes and decoder (not from the
    choice's start again) and runs only the neural steps that candidate did not, still anchored to the start; the
    progress counts those steps, their schedule starts at select_continue_lr x lr, the history holds the candidate's
    rows before them, and stopped in the last phase and resumed, the result is bit for bit the same."""
    from neumatex_core.tto import pbr_start, solve
    from neumatex_core.tto.params import NeuralTriplane

    entries: list[dict[str, torch.Tensor]] = []
    exits: list[dict[str, torch.Tensor]] = []
    run = pbr_start.optimise

    def recorded(problem, config, *a, **k):
        def state() -> dict[str, torch.Tensor]:
            found = {"planes": problem.params.tensor.detach().clone()}
            if isinstance(problem.params, NeuralTriplane):
                found.update({k: v.detach().clone() for k, v in problem.params.decoder.state_dict().items()})
                found["anchor"] = problem.anchor.target.clone()
            return found
        entries.append(state())
        result = run(problem, config, *a, **k)
        exits.append(state())
        return result

    monkeypatch.setattr(pbr_start, "optimise", recorded)
    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=0.0, lambda_consistency=1.0, select_uniform=True, select_fraction=0.5,
                           select_reuse_start=True, select_continue=True, select_continue_lr=0.5, pbr_fit_steps=50,
                           train_decoder=True, decoder_lr=0.01)  # fmt: skip
    assert cfg.select_steps() == 2 and cfg.continue_steps() == 2 and cfg.run_steps() == 4 + 2 * 2 + 2
    args = (example.mesh, example.envmap, example.photos, example.capture.tonemap, perturbed(truth_prediction, 0.2),
            example.basis)  # fmt: skip
    steps: list[int] = []
    went_on = solve(cfg, *args, checkpoint_dir=tmp_path, progress=lambda s, n, row: steps.append(s))
    assert steps == list(range(1, cfg.run_steps() + 1)) and went_on.finished
    assert len(entries) == 4  # the PBR phase, the two candidates, the remaining steps
    chosen = 1 + int(went_on.selection["uniform_kept"] == 0.0)
    assert set(entries[3]) == set(exits[chosen]) and len(entries[3]) > 2  # planes, decoder weights, anchor
    for key, value in entries[3].items():
        assert torch.equal(value, exits[chosen][key]), key  # where the chosen candidate ended; the anchor its start's
    assert not torch.equal(entries[3]["planes"], entries[chosen]["planes"])
    assert [r["phase"] for r in went_on.history] == [0.0] * 4 + [1.0] * 4
    assert went_on.history[6]["lr"] == 0.5 * went_on.history[4]["lr"]  # the remaining steps' schedule from lr / 2
    # the same choice made without select_continue runs all four steps again from the start
    entries.clear(), exits.clear()
    again = solve(replace(cfg, select_continue=False), *args)
    assert again.selection == went_on.selection and torch.equal(entries[3]["planes"], entries[1]["planes"])
    assert not torch.equal(again.params.tensor, went_on.params.tensor)
    # stopped one step before the end, then resumed from the checkpoints: the same result
    (tmp_path / "b").mkdir()
    resumed = resumed_after_stop(cfg, args, tmp_path / "b", 1)
    assert resumed.finished and torch.equal(resumed.params.tensor, went_on.params.tensor)
    exposed = solve(replace(cfg, photo_exposure=True), *args)  # the candidate's exposures, the held-out photos' at 1
    assert exposed.exposure is not None and len(exposed.exposure) == example.photos.count


def test_the_choice_runs_its_candidates_side_by_side_with_the_same_result(example, truth_prediction, tmp_path):
    """With two torch threads the choice's two candidates (each neural phase and its held-out score) run side by side in
    two Python threads of one torch thread each (`side_by_side`; the demo's choice 56 -> 50 s, docs/design-notes.md item
    44), and give what one torch thread gives one after the other, bit for bit: scores, choice and result, also when
    stopped during the choice and resumed. The progress still counts every step once, in order, and torch's thread
    count is given back; with one thread they run one after the other in the caller's thread."""
    import threading

    from neumatex_core.device import side_by_side
    from neumatex_core.tto import solve

    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=0.0, lambda_consistency=1.0, select_uniform=True, select_fraction=0.5,
                           select_reuse_start=True, pbr_fit_steps=50)  # fmt: skip
    args = (example.mesh, example.envmap, example.photos, example.capture.tonemap, perturbed(truth_prediction, 0.2),
            example.basis)  # fmt: skip

    def run() -> tuple[object, list[int], set[str]]:
        steps: list[int] = []
        threads: set[str] = set()

        def progress(s: int, _n: int, row: dict[str, float]) -> None:
            steps.append(s)
            if row["phase"] == 1.0:
                threads.add(threading.current_thread().name)
        return solve(cfg, *args, progress=progress), steps, threads

    assert torch.get_num_threads() == 1  # this module's (one_thread)
    alone, alone_steps, alone_threads = run()
    assert alone_threads == {threading.current_thread().name}
    torch.set_num_threads(2)
    try:
        paired, paired_steps, paired_threads = run()
        assert torch.get_num_threads() == 2
        # stopped during the choice (both candidates stop and keep their checkpoints), then resumed: the same result,
        # and the shared frozen decoders are only read (a thread writing one broke the other's backward pass)
        shared = [p for d in (args[4].material_decoder, args[4].pbr_decoder) for p in d.parameters()]
        versions = [p._version for p in shared]
        seen: list[int] = []
        stopped = solve(cfg, *args, checkpoint_dir=tmp_path, progress=lambda s, n, row: seen.append(s),
                        should_stop=lambda: bool(seen) and seen[-1] >= cfg.pbr_steps + 1)  # fmt: skip
        assert not stopped.finished and {"select_uniform.pt", "select_textured.pt"} <= {
            p.name for p in tmp_path.iterdir()}
        resumed = solve(cfg, *args, checkpoint_dir=tmp_path)
        assert resumed.finished and torch.equal(resumed.params.tensor, paired.params.tensor)
        assert [p._version for p in shared] == versions
        with pytest.raises(ZeroDivisionError):  # a task's error reaches the caller, and the threads are given back
            side_by_side([lambda: 1, lambda: 1 // 0], torch.device("cpu"))
        assert side_by_side([lambda: 1, lambda: 2], torch.device("cpu")) == [1, 2] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(1)
    assert len(paired_threads) == 2 and threading.current_thread().name not in paired_threads
    assert alone_steps == paired_steps == list(range(1, cfg.run_steps() + 1))
    assert paired.selection == alone.selection and paired.finished
    assert torch.equal(paired.params.tensor, alone.params.tensor)


def test_bsdf_refinement_recovers_what_the_encoder_conversion_loses(example, truth_prediction):
    """The encoder conversion (pbr_to_neural) of a rough grey metal keeps ~60% of its albedo in the shipped basis;
    the BSDF-space refinement of the start (refine_to_pbr_bsdf) brings the neural material's hemispherical albedo
    to PBR's. Albedo by 20k cosine samples: standard error < 0.005, so 0.03 is 6 SE; the gap before is 0.23
    measured, asserted > 0.1."""
    import copy

    from neumatex_core.fields.triplane import Triplane
    from neumatex_core.materials.base import cosine_sample
    from neumatex_core.materials.neural_basis import NeuralMaterial
    from neumatex_core.materials.pbr import PBRMaterial
    from neumatex_core.materials.pbr_to_neural import pbr_to_neural
    from neumatex_core.tto.params import NeuralTriplane
    from neumatex_core.tto.pbr_start import fit_planes, refine_to_pbr_bsdf

    basis = example.basis
    points, _ = example.mesh.sample_surface(4096, seed=0)
    values = torch.tensor([0.6, 0.6, 0.6, 0.5, 1.0]).expand(points.shape[0], 5)
    rho, latent = pbr_to_neural(basis, values[:, :3], values[:, 3], values[:, 4])
    planes = truth_prediction.triplane.planes.detach().clone().requires_grad_(True)
    neural = NeuralTriplane(Triplane.from_planes(planes), copy.deepcopy(truth_prediction.material_decoder), basis)
    fit_planes(neural, points, rho, latent, 0, 300)

    g = torch.Generator().manual_seed(3)
    n = 20_000
    wo, wi = cosine_sample(torch.rand(n, 2, generator=g)), cosine_sample(torch.rand(n, 2, generator=g))
    want = (PBRMaterial(torch.full((n, 3), 0.6), torch.full((n,), 0.5), torch.ones(n)).eval(wi, wo) * math.pi).mean(0)

    def albedo_gap() -> float:
        """max |albedo neural - albedo PBR| over RGB and a few surface points."""
        with torch.no_grad():
            gaps = []
            for i in (0, 1000, 2000, 3000):
                got = neural.gbuffer(points[i:i + 1], None).expand(n, 9)
                have = (NeuralMaterial(basis, got[:, :3], got[:, 3:]).eval(wi, wo) * math.pi).mean(0)
                gaps.append(float((have - want).abs().max()))
        return max(gaps)

    before = albedo_gap()
    assert before > 0.1
    refine_to_pbr_bsdf(neural, basis, points, values, 0, 300)
    after = albedo_gap()
    assert after < 0.03, (before, after)


def test_the_start_fit_takes_its_schedule_from_the_config(example, monkeypatch):
    """tto/pbr_start.py `fit_start` fits the planes with the config's pbr_fit_steps, pbr_fit_lr and pbr_fit_batch (the
    eval variant `pbr_start_default_fit750` changes all three, docs/design-notes.md item 46), and the cpu preset's
    are the defaults `fit_planes` itself has."""
    import copy

    from neumatex_core.tto import pbr_start
    from neumatex_core.tto.optimise import TTOResult
    from neumatex_core.tto.params import PBRTriplane

    prediction = random_prediction(3)
    pbr = PBRTriplane(Triplane.from_planes(prediction.triplane.planes.detach().clone()),
                      copy.deepcopy(prediction.pbr_decoder))  # fmt: skip
    seen: list[tuple[int, float, int]] = []

    def fit_planes(neural, points, rho_d, latent, seed, steps, lr, batch) -> float:
        seen.append((steps, lr, batch))
        return 0.0

    monkeypatch.setattr(pbr_start, "fit_planes", fit_planes)
    cfg = TTOConfig.preset("tiny", init="pbr", reg="start", lambda_consistency=0.1, pbr_fit_steps=750, pbr_fit_lr=0.3,
                           pbr_fit_batch=4096)  # fmt: skip
    cfg.check()
    pbr_start.fit_start(cfg, TTOResult(pbr, finished=True), example.mesh, example.envmap, example.photos,
                        example.capture.tonemap, prediction, example.basis, True)  # fmt: skip
    assert seen == [(750, 0.3, 4096)]
    cpu = TTOConfig.preset("cpu")
    assert (cpu.pbr_fit_steps, cpu.pbr_fit_lr, cpu.pbr_fit_batch) == (pbr_start.FIT_STEPS, pbr_start.FIT_LR,
                                                                      pbr_start.FIT_BATCH)  # fmt: skip


def test_iterate_averaging_returns_the_tails_mean_and_resumes(example, truth_prediction, tmp_path):
    """average_tail 0.5 over 8 steps: the result is the mean of the tensors after steps 5-8 (not the last one), and
    a run stopped inside the tail and resumed from its checkpoint ends bit for bit where an uninterrupted one does."""
    cfg = TTOConfig.preset("tiny", steps=8, pixels=64, spp=2, max_bounces=1, checkpoint_every=0, init="lmrm",
                           average_tail=0.5)  # fmt: skip

    def problem():
        return build_problem(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap,
                             perturbed(truth_prediction, 0.2), example.basis)  # fmt: skip

    p = problem()
    seen: list[torch.Tensor] = []
    whole = optimise(p, cfg, progress=lambda step, total, row: seen.append(p.params.tensor.detach().clone()))
    assert len(seen) == 8
    mean = torch.stack(seen[4:]).mean(0)
    assert torch.allclose(whole.params.tensor, mean, atol=1e-6)
    assert not torch.allclose(whole.params.tensor, seen[-1], atol=1e-6)  # the iterates moved: a real average
    checkpoint = tmp_path / "checkpoint.pt"
    first = optimise(problem(), cfg, should_stop=stop_after(6), checkpoint=checkpoint)
    assert not first.finished and first.steps_done == 6
    second = optimise(problem(), cfg, checkpoint=checkpoint)
    assert torch.equal(second.params.tensor, whole.params.tensor)


def test_settling_phase_traces_the_same_rays_at_more_samples_on_its_own_schedule(example, truth_prediction,
                                                                                  monkeypatch):
    """settle_fraction 0.5 over 8 steps: steps 0-3 draw 64 pixels x 2 spp, steps 4-7 16 x 8 (the same rays); the
    rate falls by a cosine from lr to lr x lr_final over steps 0-3, then from lr x settle_lr to that x settle_lr_final
    over steps 4-7; steps 4-7 take settle_photo_loss; Adam gets the config's epsilon and betas; the PBR phase of init
    "pbr" neither settles nor takes them; and the cached estimator, whose cache holds one sample count, is refused."""
    from neumatex_core.tto import pbr_start
    from neumatex_core.tto.optimise import learning_rate, make_optimizer

    cfg = TTOConfig.preset("tiny", steps=8, pixels=64, spp=2, max_bounces=1, checkpoint_every=0, init="lmrm",
                           lr=0.1, lr_final=0.1, settle_fraction=0.5, settle_spp=8, settle_lr=0.5, adam_eps=1e-3,
                           adam_beta1=0.8, settle_photo_loss="decorrelated_debiased")  # fmt: skip
    cfg.check()
    with pytest.raises(ValueError, match="spp >= 4"):
        replace(cfg, settle_spp=2).check()
    kinds: list[str] = []
    optimise_module = importlib.import_module("neumatex_core.tto.optimise")  # the package's `optimise` is the function
    loss = optimise_module.photometric_loss
    monkeypatch.setattr(optimise_module, "photometric_loss", lambda *a: kinds.append(a[5]) or loss(*a))
    assert [cfg.batch_at(s) for s in (0, 3, 4, 7)] == [(64, 2), (64, 2), (16, 8), (16, 8)]
    rates = [learning_rate(cfg, s) for s in range(8)]
    assert rates[0] == pytest.approx(0.1) and rates[4] == pytest.approx(0.05)
    assert rates[0] > rates[1] > rates[2] > rates[3] > 0.01 and rates[4] > rates[5] > rates[6] > rates[7] > 0.005
    low = replace(cfg, settle_lr_final=0.01)  # the settling's cosine ends lower; the steps before it are the same
    assert [learning_rate(low, s) for s in range(4)] == rates[:4]
    assert [learning_rate(low, s) for s in range(4, 8)] == pytest.approx(
        [0.05 * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * (s - 4) / 4))) for s in range(4, 8)])
    plain = replace(cfg, settle_fraction=0.0)
    assert plain.batch_at(7) == (64, 2)
    assert [learning_rate(plain, s) for s in range(8)] == pytest.approx(
        [0.1 * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * s / 8))) for s in range(8)])
    p = build_problem(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap,
                      truth_prediction, example.basis)  # fmt: skip
    adam = make_optimizer(p.params, cfg).defaults
    assert (adam["eps"], adam["betas"]) == (1e-3, (0.8, 0.999))
    drawn: list[tuple[int, int]] = []
    batch = p.photos.batch
    monkeypatch.setattr(p.photos, "batch", lambda pixels, spp, g: drawn.append((pixels, spp)) or batch(pixels, spp, g))
    result = optimise(p, cfg)
    assert drawn == [(64, 2)] * 4 + [(16, 8)] * 4
    assert kinds == ["l2"] * 4 + ["decorrelated_debiased"] * 4
    assert replace(cfg, settle_fraction=0.0).loss_at(7) == "l2"
    assert [row["lr"] for row in result.history] == pytest.approx(rates)
    with pytest.raises(ValueError, match="settle_fraction"):
        replace(cfg, estimator="cached").check()
    phases: list[TTOConfig] = []
    monkeypatch.setattr(pbr_start, "optimise", lambda problem, config, *a, **k: phases.append(config))
    pbr_start._pbr_phase(cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap,
                         truth_prediction, example.basis, True, None, None, None)  # fmt: skip
    assert (phases[0].settle_fraction, phases[0].adam_eps, phases[0].adam_beta1, phases[0].material) == (
        0.0, 1e-8, 0.9, "pbr")
    assert phases[0].loss_at(7) == "l2"


def test_smoothness_term_pulls_each_texels_change_towards_its_neighbours(example, truth_prediction, monkeypatch):
    """neighbour_variation is 0 on constant planes and 4 on a +-1 checkerboard (every neighbour differs by 2); a UV
    texture [H, W, C] is measured over H and W, from an origin. With lambda_smooth the TTO's change to noisy planes
    (the tensor minus its start) ends smoother than without (the same seed, so the same photo batches) while the
    start's own texture is not smoothed away, the term is logged, and the PBR phase of init "pbr" drops it."""
    from neumatex_core.fields.triplane import neighbour_variation
    from neumatex_core.tto import pbr_start
    from neumatex_core.tto.params import NeuralUV

    assert float(neighbour_variation(torch.full((3, 4, 8, 8), 0.7))) == 0.0
    i = torch.arange(8)
    checker = ((i[:, None] + i[None, :]) % 2 * 2 - 1).float().expand(3, 4, 8, 8)
    assert float(neighbour_variation(checker)) == pytest.approx(4.0)
    ramp = torch.linspace(0, 1, 5)[:, None, None].expand(5, 6, 9)  # [H, W, C]: rows differ by 0.25, columns alike
    uv = NeuralUV(ramp, example.basis)
    assert float(uv.texel_variation(torch.zeros_like(ramp)).detach()) == pytest.approx(0.5 * 0.25**2)
    assert float(uv.texel_variation(ramp).detach()) == 0.0
    cfg = TTOConfig.preset("tiny", steps=8, pixels=64, spp=2, max_bounces=1, checkpoint_every=0, init="lmrm",
                           lr=0.02)  # fmt: skip
    noisy = perturbed(truth_prediction, 0.3)
    start = noisy.triplane.planes.detach().clone()
    change, texture = {}, {}
    for weight in (0.0, 1000.0):
        smooth_cfg = replace(cfg, lambda_smooth=weight)
        smooth_cfg.check()
        p = build_problem(smooth_cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap, noisy,
                          example.basis)  # fmt: skip
        result = optimise(p, smooth_cfg)
        change[weight] = float(neighbour_variation(result.params.tensor.detach() - start))
        texture[weight] = float(neighbour_variation(result.params.tensor.detach()))
        assert ("smooth" in result.history[-1]) == (weight > 0)
    assert change[1000.0] < 0.5 * change[0.0]
    assert texture[1000.0] > 0.9 * float(neighbour_variation(start))  # the start's texture stays
    with pytest.raises(ValueError, match="lambda_smooth"):
        replace(cfg, lambda_smooth=-1.0).check()
    phases: list[TTOConfig] = []
    monkeypatch.setattr(pbr_start, "optimise", lambda problem, config, *a, **k: phases.append(config))
    pbr_start._pbr_phase(replace(cfg, lambda_smooth=10.0), example.mesh, example.envmap, example.photos,
                         example.capture.tonemap, truth_prediction, example.basis, True, None, None, None)  # fmt: skip
    assert phases[0].lambda_smooth == 0.0


def test_coarse_steps_move_the_planes_in_blocks_before_the_settling(example, truth_prediction, monkeypatch):
    """coarse_projection is U U^T (U the bilinear upsampling from a grid `factor` times coarser): symmetric and
    positive semi-definite (a descent direction stays one), a constant comes back factor^2 times larger and a +-1
    checkerboard about vanishes; a UV texture [H, W, C] is projected over H and W. With coarse_factor the TTO's
    change to noisy planes before the settling is smoother than without (the same seed, so the same photo batches),
    the settling steps move every texel, and the PBR phase of init "pbr" drops it."""
    from neumatex_core.fields.triplane import coarse_projection, neighbour_variation
    from neumatex_core.tto import pbr_start
    from neumatex_core.tto.params import NeuralUV

    g = torch.Generator().manual_seed(0)
    a, b = torch.randn(3, 4, 24, 24, generator=g), torch.randn(3, 4, 24, 24, generator=g)
    assert float((coarse_projection(a, 4) * b).sum()) == pytest.approx(float((a * coarse_projection(b, 4)).sum()),
                                                                       rel=1e-4)  # fmt: skip
    assert float((coarse_projection(a, 4) * a).sum()) > 0
    assert torch.allclose(coarse_projection(torch.full((3, 4, 24, 24), 0.5), 4), torch.full((3, 4, 24, 24), 8.0))
    i = torch.arange(24)
    checker = ((i[:, None] + i[None, :]) % 2 * 2 - 1).float().expand(3, 4, 24, 24)
    assert float(coarse_projection(checker, 4).abs().max()) < 0.05 * 16
    uv = NeuralUV(torch.zeros(24, 24, 9), example.basis)
    uv.tensor.grad = checker[0, :1].permute(1, 2, 0).expand(24, 24, 9).clone()
    uv.coarsen_gradient(4)
    assert uv.tensor.grad.shape == (24, 24, 9) and float(uv.tensor.grad.abs().max()) < 0.05 * 16
    cfg = TTOConfig.preset("tiny", steps=8, pixels=64, spp=2, max_bounces=1, checkpoint_every=0, init="lmrm",
                           lr=0.02)  # fmt: skip
    assert replace(cfg, coarse_factor=4, settle_fraction=0.5).coarse_at(3) == 4
    assert replace(cfg, coarse_factor=4, settle_fraction=0.5).coarse_at(4) == 1
    noisy = perturbed(truth_prediction, 0.3)
    start = noisy.triplane.planes.detach().clone()
    change = {}
    for factor in (1, 8):
        coarse_cfg = replace(cfg, coarse_factor=factor)
        coarse_cfg.check()
        p = build_problem(coarse_cfg, example.mesh, example.envmap, example.photos, example.capture.tonemap, noisy,
                          example.basis)  # fmt: skip
        moved = optimise(p, coarse_cfg).params.tensor.detach() - start
        change[factor] = float(neighbour_variation(moved)) / float(moved.square().mean())
    assert change[8] < 0.2 * change[1]
    with pytest.raises(ValueError, match="coarse_factor"):
        replace(cfg, coarse_factor=0).check()
    phases: list[TTOConfig] = []
    monkeypatch.setattr(pbr_start, "optimise", lambda problem, config, *a, **k: phases.append(config))
    pbr_start._pbr_phase(replace(cfg, coarse_factor=4), example.mesh, example.envmap, example.photos,
                         example.capture.tonemap, truth_prediction, example.basis, True, None, None, None)  # fmt: skip
    assert phases[0].coarse_factor == 1


def _pbr_scene(example: Example, prediction: LMRMPrediction, values: list[float]):
    """A PBR triplane holding one PBR material (base colour, roughness, metallic) all over the example's mesh (its
    planes fitted by Adam, the LMRM's PBR head frozen), and photos of it: 6 of the example's views rendered at 64 spp,
    one bounce, so PBR is exact up to that noise."""
    import copy

    from neumatex_core.tto.data import PhotoSet
    from neumatex_core.tto.params import PBRTriplane

    planes = prediction.triplane.planes.detach().clone().requires_grad_(True)
    pbr = PBRTriplane(Triplane.from_planes(planes), copy.deepcopy(prediction.pbr_decoder))
    points, _ = example.mesh.sample_surface(4096, seed=0)
    want = torch.tensor(values).expand(points.shape[0], 5)
    opt = torch.optim.Adam([pbr.tensor], lr=0.05)
    for _ in range(200):
        loss = ((pbr.gbuffer(points, None) - want) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    scene = Scene(example.mesh.with_smooth_normals() if example.mesh.vertex_normals is None else example.mesh,
                  example.envmap, pbr.field())  # fmt: skip
    tracer = PathTracer(PathTracerConfig(max_bounces=1, spp=64))
    views = (0, 4, 8, 12, 17, 19)
    cams = [example.photos.cameras[v] for v in views]
    with torch.no_grad():
        images = [example.capture.tonemap.apply(tracer.render(scene, cams[k], seed=v)).numpy()
                  for k, v in enumerate(views)]  # fmt: skip
    masks = [example.capture.load_mask(v) for v in views]
    return pbr, PhotoSet(images, cams, example.mesh, masks)


def test_choose_basis_takes_the_alternative_where_the_default_cannot_hold_the_pbr_solution(example):
    """TTOConfig.alternative_basis (tto/pbr_start.py `choose_basis`): the PBR solution of a gold metal expressed in
    the default basis turns grey, so its start loses to PBR on the photos by more than the margin, and the start in
    basis v4, which holds it, is taken (measured: PBR 30.2 dB, default 18.5, v4 26.6). The photos are renders of the
    PBR material itself. Then the rule's other branches, on a short fit: the alternative is not tried when the
    default's start is within the margin of PBR, and not taken when it does not beat the default's by the margin."""
    from neumatex_core.materials.neural_basis import BASIS_V4, installed_bases
    from neumatex_core.tto.optimise import TTOResult
    from neumatex_core.tto.pbr_start import choose_basis

    assert BASIS_V4 in installed_bases()
    prediction = random_prediction(3)  # decoders that can express any material (the example's fit holds its own)
    pbr, photos = _pbr_scene(example, prediction, [1.0, 0.71, 0.29, 0.3, 1.0])
    cfg = TTOConfig.preset("tiny", max_bounces=1, init="pbr", reg="start", lambda_consistency=0.1,
                           alternative_basis=BASIS_V4, pbr_fit_steps=1500)  # fmt: skip
    cfg.check()
    first = TTOResult(pbr, finished=True)
    args = (first, example.mesh, example.envmap, photos, photos, example.capture.tonemap, prediction, example.basis,
            True)  # fmt: skip
    start = choose_basis(cfg, *args)
    assert start is not None
    rec = start.record
    assert rec["basis_pbr_psnr"] - rec["basis_start_psnr"] > cfg.basis_margin_db + 5
    assert rec["basis_alternative_psnr"] - rec["basis_start_psnr"] > cfg.basis_margin_db + 3
    assert start.switched and start.basis.basis_id == BASIS_V4 and rec["basis_switched"] == 1.0
    assert start.mse < 0.01 and start.planes.shape == pbr.tensor.shape

    short = replace(cfg, pbr_fit_steps=20)
    tried = choose_basis(replace(short, basis_margin_db=-100.0), *args)
    assert tried is not None and tried.switched
    own, other = tried.record["basis_start_psnr"], tried.record["basis_alternative_psnr"]
    gap = tried.record["basis_pbr_psnr"] - own
    kept = choose_basis(replace(short, basis_margin_db=gap + 0.5), *args)  # PBR not far enough ahead: not tried
    assert kept is not None and not kept.switched and kept.basis is example.basis
    assert "basis_alternative_psnr" not in kept.record and kept.record["basis_switched"] == 0.0
    # tried (PBR ahead by more than the margin), but the alternative not ahead by the margin itself: not taken
    assert other - own < gap  # measured at 20 fit steps: 4.2 < 22.2 dB
    declined = choose_basis(replace(short, basis_margin_db=(other - own + gap) / 2), *args)
    assert declined is not None and not declined.switched
    assert declined.record["basis_alternative_psnr"] == pytest.approx(other, abs=1e-6)
    # With config.appearance_start the chosen start's own record (its cells) comes along with the scores.
    appeared = choose_basis(replace(short, basis_margin_db=-100.0, appearance_start=True), *args)
    assert appeared is not None and appeared.switched and appeared.record["appearance_cells"] > 0
    assert choose_basis(replace(cfg, alternative_basis=""), *args) is None
    with pytest.raises(ValueError, match="alternative_basis"):
        replace(cfg, init="lmrm", reg="none", lambda_consistency=0.0).check()
    with pytest.raises(ValueError, match="not installed"):
        replace(cfg, alternative_basis="nmx-basis-v9").check()


def test_choose_basis_makes_both_starts_side_by_side_with_the_same_result(example, monkeypatch):
    """With two torch threads `choose_basis` makes the start in the alternative basis beside the start in the
    default one (`side_by_side`, before it is known to be needed: docs/design-notes.md item 47), each in its own
    thread, and the choice, its record and the start are what one thread gives one after the other, bit for bit; where
    the alternative is not needed its start is dropped and the record is the same as without it."""
    import threading

    from neumatex_core.materials.neural_basis import BASIS_V4
    from neumatex_core.tto import pbr_start
    from neumatex_core.tto.optimise import TTOResult

    prediction = random_prediction(3)
    pbr, photos = _pbr_scene(example, prediction, [1.0, 0.71, 0.29, 0.3, 1.0])
    cfg = TTOConfig.preset("tiny", max_bounces=1, init="pbr", reg="start", lambda_consistency=0.1,
                           alternative_basis=BASIS_V4, pbr_fit_steps=20, basis_margin_db=-100.0)  # fmt: skip
    args = (TTOResult(pbr, finished=True), example.mesh, example.envmap, photos, photos, example.capture.tonemap,
            prediction, example.basis, True)  # fmt: skip
    fitted_in: list[tuple[str, str]] = []
    real_fit = pbr_start.fit_start

    def fit_start(*a, **k):  # type: ignore[no-untyped-def]
        fitted_in.append((a[7].basis_id, threading.current_thread().name))
        return real_fit(*a, **k)

    monkeypatch.setattr(pbr_start, "fit_start", fit_start)
    assert torch.get_num_threads() == 1  # this module's (one_thread)
    alone = pbr_start.choose_basis(cfg, *args)
    here = threading.current_thread().name
    assert [t for _, t in fitted_in] == [here, here]
    fitted_in.clear()
    torch.set_num_threads(2)
    try:
        paired = pbr_start.choose_basis(cfg, *args)
        assert torch.get_num_threads() == 2
        assert {b for b, _ in fitted_in} == {example.basis.basis_id, BASIS_V4}
        assert len({t for _, t in fitted_in}) == 2 and here not in {t for _, t in fitted_in}
        # not needed (the default basis's start within the margin of PBR): made, dropped, and not recorded
        gap = alone.record["basis_pbr_psnr"] - alone.record["basis_start_psnr"]
        kept = pbr_start.choose_basis(replace(cfg, basis_margin_db=gap + 0.5), *args)
    finally:
        torch.set_num_threads(1)
    assert alone is not None and paired is not None and alone.switched and paired.switched
    assert paired.record == alone.record and paired.mse == alone.mse
    assert torch.equal(paired.planes, alone.planes)
    assert kept is not None and not kept.switched and "basis_alternative_psnr" not in kept.record
    assert kept.record["basis_start_psnr"] == alone.record["basis_start_psnr"]


def test_the_decoder_is_fine_tuned_in_the_default_basis_only_unless_asked(example, truth_prediction):
    """decoder_in_other_basis off: the neural phase fine-tunes the LMRM's material decoder only in the default
    basis, the one it was trained for (in basis v4 the fine-tuning cost the Cycles metals 0.6-2.3 dB relit:
    docs/design-notes.md item 41). The PBR phase tunes its head either way. Where the default basis is kept the result
    is bit for bit the tuned one; where v4 is taken (by the choice, or named as `basis`) the material decoder stays
    the LMRM's."""
    from neumatex_core.materials.neural_basis import BASIS_V4, load_basis
    from neumatex_core.tto import solve

    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=0.0, lambda_consistency=1.0, train_decoder=True, alternative_basis=BASIS_V4,
                           pbr_fit_steps=50)  # fmt: skip
    frozen_there = replace(cfg, decoder_in_other_basis=False)
    args = (example.mesh, example.envmap, example.photos, example.capture.tonemap, perturbed(truth_prediction, 0.2))
    lmrm = truth_prediction.material_decoder.state_dict()

    def is_lmrms(result) -> bool:
        state = result.params.decoder.state_dict()
        return all(torch.equal(state[k], lmrm[k]) for k in lmrm)

    kept = solve(replace(frozen_there, basis_margin_db=100.0), *args, example.basis)
    assert kept.selection["basis_switched"] == 0.0 and not is_lmrms(kept) and kept.params.decoder_parameters()
    tuned_kept = solve(replace(cfg, basis_margin_db=100.0), *args, example.basis)
    assert torch.equal(kept.params.tensor, tuned_kept.params.tensor)
    taken = solve(replace(frozen_there, basis_margin_db=-100.0), *args, example.basis)
    assert taken.basis is not None and taken.basis.basis_id == BASIS_V4
    assert is_lmrms(taken) and not taken.params.decoder_parameters()
    tuned_taken = solve(replace(cfg, basis_margin_db=-100.0), *args, example.basis)
    assert not is_lmrms(tuned_taken) and not torch.equal(taken.params.tensor, tuned_taken.params.tensor)
    named = solve(replace(frozen_there, alternative_basis="", basis=BASIS_V4), *args, load_basis(basis_id=BASIS_V4))
    assert is_lmrms(named) and torch.equal(named.params.tensor, taken.params.tensor)


def test_the_tto_runs_in_a_basis_of_another_latent_size(example, truth_prediction):
    """Basis v5 (12 latent numbers) as `basis`: the neural triplane reads the LMRM's material decoder resized
    (`MaterialDecoder.with_latent_dim`: its rho_d rows and first six latent rows kept, the others fresh, the same at
    every call), the PBR solution is fitted in the new basis about as closely as in the default one, and the TTO runs
    to a finite material of 15 G-buffer channels. The choice between bases and the UV field refuse another size
    (docs/design-notes.md item 78)."""
    from neumatex_core.materials.neural_basis import BASIS_V4, BASIS_V5, load_basis
    from neumatex_core.tto import solve

    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=0.0, lambda_consistency=1.0, train_decoder=True, pbr_fit_steps=300)  # fmt: skip
    args = (example.mesh, example.envmap, example.photos, example.capture.tonemap, perturbed(truth_prediction, 0.2))
    in_v1 = solve(cfg, *args, example.basis)
    in_v5 = solve(replace(cfg, basis=BASIS_V5, decoder_in_other_basis=False), *args, load_basis(basis_id=BASIS_V5))
    assert in_v5.params.field().basis.basis_id == BASIS_V5
    lmrm = truth_prediction.material_decoder.net[-1].weight
    resized = in_v5.params.decoder.net[-1].weight
    assert resized.shape == (15, lmrm.shape[1]) and torch.equal(resized[:9], lmrm)
    points = example.mesh.sample_surface(256, seed=0)[0]
    values = in_v5.params.gbuffer(points, None)
    assert values.shape == (256, 15) and torch.isfinite(values).all()

    def start_mse(result) -> float:
        return next(row["start_mse"] for row in result.history if row.get("phase") == 1.0)

    print("start fit error v1", start_mse(in_v1), "v5", start_mse(in_v5))
    assert start_mse(in_v5) < 2 * start_mse(in_v1)
    for bad in ({"alternative_basis": BASIS_V5}, {"basis": BASIS_V4, "alternative_basis": BASIS_V5},
                {"basis": BASIS_V5, "field": "uv", "init": "random", "reg": "none"}):
        with pytest.raises(ValueError, match="has 12 latent numbers"):
            replace(cfg, **bad).check()


def test_solve_runs_the_neural_phase_in_the_basis_it_chose(example, truth_prediction):
    """With alternative_basis, `solve` chooses the basis after the PBR phase and starts the neural phase there: the
    result is bit for bit the plain TTO in the chosen basis (kept: the configured one; taken: the alternative, whose
    result says so, `TTOResult.basis`), and the selection holds the scores. Under select_uniform the basis is chosen
    once, on the held-out photos, for both candidates and the TTO that follows."""
    from neumatex_core.materials.neural_basis import BASIS_V4, load_basis
    from neumatex_core.tto import solve

    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=0.0, lambda_consistency=1.0, alternative_basis=BASIS_V4)  # fmt: skip
    args = (example.mesh, example.envmap, example.photos, example.capture.tonemap, perturbed(truth_prediction, 0.2))
    plain = replace(cfg, alternative_basis="")
    kept = solve(replace(cfg, basis_margin_db=100.0), *args, example.basis)
    assert kept.basis is None and kept.selection["basis_switched"] == 0.0
    assert "basis_alternative_psnr" not in kept.selection
    assert torch.equal(kept.params.tensor, solve(plain, *args, example.basis).params.tensor)
    taken = solve(replace(cfg, basis_margin_db=-100.0), *args, example.basis)
    assert taken.basis is not None and taken.selection["basis_switched"] == 1.0
    assert taken.basis.basis_id == taken.params.field().basis.basis_id == BASIS_V4
    in_v4 = solve(replace(plain, basis=BASIS_V4), *args, load_basis(basis_id=BASIS_V4))
    assert torch.equal(taken.params.tensor, in_v4.params.tensor)
    choosing = solve(replace(cfg, basis_margin_db=-100.0, select_uniform=True), *args, example.basis)
    assert choosing.basis is not None and choosing.basis.basis_id == BASIS_V4
    assert choosing.selection["basis_switched"] == 1.0
    assert {"uniform_kept", "basis_pbr_psnr", "basis_start_psnr"} <= set(choosing.selection)


def test_a_fine_tuned_decoder_starts_from_the_fit_the_basis_choice_made(example, truth_prediction, start_fits):
    """With train_decoder, the start's fit leaves the decoder as it is (at the fit's learning rate it saturated:
    docs/design-notes.md item 39), so the planes that `choose_basis` fitted are the neural phase's start, not fitted
    again (1500 Adam steps each time), and the result is bit for bit the plain TTO's, which fits its own start; the
    TTO then fine-tunes the decoder."""
    from neumatex_core.materials.neural_basis import BASIS_V4
    from neumatex_core.tto import pbr_start, solve

    calls = start_fits
    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=0.0, lambda_consistency=1.0, train_decoder=True, pbr_fit_steps=50)  # fmt: skip
    args = (example.mesh, example.envmap, example.photos, example.capture.tonemap, perturbed(truth_prediction, 0.2))
    plain = solve(cfg, *args, example.basis)
    assert len(calls) == 1
    kept = solve(replace(cfg, alternative_basis=BASIS_V4, basis_margin_db=100.0), *args, example.basis)
    assert len(calls) == 2  # choose_basis's fit only
    assert kept.selection["basis_switched"] == 0.0
    assert torch.equal(kept.params.tensor, plain.params.tensor)
    tuned, want = kept.params.decoder.state_dict(), plain.params.decoder.state_dict()
    assert all(torch.equal(tuned[k], want[k]) for k in want)
    lmrm = truth_prediction.material_decoder.state_dict()
    assert not all(torch.equal(want[k], lmrm[k]) for k in want)  # the TTO fine-tuned it

    points, _ = example.mesh.sample_surface(2048, seed=0)
    neural = kept.params
    before = {k: v.clone() for k, v in neural.decoder.state_dict().items()}
    for w in neural.decoder_parameters():
        w.grad = None
    pbr_start.fit_planes(neural, points, torch.full((2048, 3), 0.5), torch.zeros(2048, 6), 0, 20)
    assert neural.decoder_parameters()  # still trainable for the TTO
    assert all(torch.equal(before[k], v) for k, v in neural.decoder.state_dict().items())
    # and no gradient was computed for its weights (they were a quarter of the fit's time, thrown away)
    assert all(w.grad is None for w in neural.decoder_parameters())


def test_shuffled_pixels_draw_every_pixel_once_an_epoch_whatever_the_batches(example):
    # random reshuffling (TTOConfig.pixel_order "shuffled"): positions 0..size-1 are one permutation, the next size
    # another, and a draw's pixels depend only on its positions, not on how the steps cut them
    size = example.photos.size
    whole = shuffled_pixels(size, 0, 2 * size + 5, seed=3)
    for epoch in range(2):
        assert torch.equal(whole[epoch * size:(epoch + 1) * size].sort().values, torch.arange(size))
    assert not torch.equal(whole[:size], whole[size:2 * size])
    cuts = [0, 7, size - 3, size + 1, 2 * size + 5]
    pieces = [shuffled_pixels(size, a, b - a, seed=3) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    assert torch.equal(torch.cat(pieces), whole)
    assert not torch.equal(shuffled_pixels(size, 0, size, seed=4), whole[:size])
    # a TTO's steps: step k starts where the steps before it stopped (the settling's fewer, longer pixels included)
    cfg = TTOConfig.preset("tiny", steps=9, pixels=64, spp=2, settle_fraction=1 / 3, settle_spp=4)
    counts = [cfg.batch_at(k)[0] for k in range(cfg.steps)]
    assert counts[0] == 64 and counts[-1] == 32
    assert [cfg.pixels_before(k) for k in range(cfg.steps + 1)] == [sum(counts[:k]) for k in range(cfg.steps + 1)]
    g = torch.Generator().manual_seed(0)
    batch = example.photos.shuffled_batch(cfg.pixels_before(7), counts[7], 2, 3, g)
    assert torch.equal(batch.index, whole[cfg.pixels_before(7):cfg.pixels_before(8)])


def kept_score(result) -> float:
    """The held-out PSNR of the candidate a TTO's choice kept (select_uniform)."""
    s = result.selection
    return s["validation_psnr_uniform"] if s["uniform_kept"] else s["validation_psnr_textured"]


def test_select_basis_joins_another_basis_to_the_choice_and_gives_that_basis_plain_result(example, truth_prediction,
                                                                                          tmp_path):
    """TTOConfig.select_basis: the choice's two candidates also run in basis v6 (16 latent numbers, its decoder
    fine-tuned) from the same PBR solution, on the same held-out photos. Each basis keeps its candidate by the
    choice's rule, and the other basis is taken when its kept candidate scores better. The result, its basis and
    each side's scores are bit for bit those of the plain TTO in the basis it took: the configured one's when the
    margin keeps it, v6's when v6 is taken. The progress counts the two extra candidates; a stop during them resumes
    to the same result (docs/design-notes.md item 80)."""
    from neumatex_core.materials.neural_basis import BASIS_V6, load_basis
    from neumatex_core.tto import solve
    from neumatex_core.tto.pbr_start import in_select_basis

    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=0.0, lambda_consistency=1.0, select_uniform=True, select_fraction=0.5,
                           select_reuse_start=True, train_decoder=True, decoder_in_other_basis=False,
                           pbr_fit_steps=50, select_margin_db=0.0, select_basis=BASIS_V6)  # fmt: skip
    assert cfg.run_steps() == 4 + 4 * 2 + 4
    args = (example.mesh, example.envmap, example.photos, example.capture.tonemap, perturbed(truth_prediction, 0.2))
    v6 = load_basis(basis_id=BASIS_V6)
    plain = solve(replace(cfg, select_basis=""), *args, example.basis)
    in_v6 = solve(in_select_basis(cfg), *args, v6)
    assert in_v6.params.field().basis.basis_id == BASIS_V6 and in_v6.params.trained_decoder() is not None

    steps: list[int] = []
    chosen = solve(cfg, *args, example.basis, checkpoint_dir=tmp_path, progress=lambda s, n, row: steps.append(s))
    assert steps == list(range(1, cfg.run_steps() + 1))
    (tmp_path / "stopped").mkdir()
    assert {"select_uniform_other.pt", "select_textured_other.pt"} <= {p.name for p in tmp_path.iterdir()}
    s = chosen.selection
    for name in ("uniform", "textured"):  # each side's candidates are the plain TTO's
        assert s[f"validation_psnr_{name}"] == plain.selection[f"validation_psnr_{name}"]
        assert s[f"select_basis_psnr_{name}"] == in_v6.selection[f"validation_psnr_{name}"]
    assert s["select_basis_uniform_kept"] == in_v6.selection["uniform_kept"]
    print("held-out PSNR, configured basis", kept_score(plain), "v6", kept_score(in_v6))
    assert s["select_basis_taken"] == float(kept_score(in_v6) > kept_score(plain))
    resumed = resumed_after_stop(cfg, (*args, example.basis), tmp_path / "stopped", 4 + 2 + 1)  # v6 candidate 1
    assert resumed.selection == chosen.selection and torch.equal(resumed.params.tensor, chosen.params.tensor)
    # with the margin each way, each basis in turn: the plain TTO in that basis at that margin, bit for bit (a
    # margin this large also decides uniform/textured, in the choice and in the plain TTO alike)
    for margin, alone, basis in ((-100.0, in_select_basis(cfg), v6), (100.0, replace(cfg, select_basis=""),
                                                                        example.basis)):
        forced = solve(replace(cfg, select_margin_db=margin), *args, example.basis)
        reference = solve(replace(alone, select_margin_db=margin), *args, basis)
        assert forced.selection["select_basis_taken"] == float(basis is v6)
        assert forced.params.field().basis.basis_id == basis.basis_id
        assert (forced.basis is None) == (basis is not v6)
        assert torch.equal(forced.params.tensor, reference.params.tensor)
        trained, want = forced.params.trained_decoder(), reference.params.trained_decoder()
        assert trained is not None and want is not None
        assert all(torch.equal(a, b) for a, b in zip(trained.state_dict().values(), want.state_dict().values(),
                                                     strict=True))
    # With config.appearance_start each basis's start records its cells, the other basis's under its prefix.
    appeared = solve(replace(cfg, appearance_start=True), *args, example.basis).selection
    assert appeared["appearance_cells"] > 0 and appeared["select_basis_appearance_cells"] > 0
    for bad in ({"select_uniform": False}, {"init": "lmrm"}, {"basis": BASIS_V6}, {"select_basis": "nmx-basis-v9"}):
        with pytest.raises(ValueError, match="select_basis"):
            replace(cfg, **bad).check()


def test_select_lmrm_start_joins_the_lmrm_start_to_the_choice_and_gives_its_plain_result(example, truth_prediction,
                                                                                         tmp_path):
    """TTOConfig.select_lmrm_start: each basis's two candidates run a second time from the LMRM's start
    (`LMRM_START_FULL`: the start nearly all the LMRM's, anchored where it made it), from the same PBR solution and
    scored on the same held-out photos; the side whose kept candidate scores best goes on. Each side's scores are
    those of the plain TTO with that start and basis, and the result is the plain TTO of the side taken, bit for bit.
    The progress counts the four sides' candidates; a stop during an LMRM side resumes to the same result
    (docs/design-notes.md item 98)."""
    from neumatex_core.materials.neural_basis import BASIS_V6, load_basis
    from neumatex_core.tto import solve
    from neumatex_core.tto.config import LMRM_START_FULL
    from neumatex_core.tto.pbr_start import in_select_basis

    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=0.0, lambda_consistency=1.0, select_uniform=True, select_fraction=0.5,
                           select_reuse_start=True, select_continue=True, train_decoder=True,
                           decoder_in_other_basis=False, pbr_fit_steps=50, select_margin_db=0.0,
                           select_basis=BASIS_V6, select_lmrm_start=True)  # fmt: skip
    assert cfg.run_steps() == 4 + 4 * 2 * 2 + 2
    args = (example.mesh, example.envmap, example.photos, example.capture.tonemap, perturbed(truth_prediction, 0.2))
    v6 = load_basis(basis_id=BASIS_V6)
    pbr_v1 = replace(cfg, select_basis="", select_lmrm_start=False)
    lmrm_v1 = replace(pbr_v1, **LMRM_START_FULL)
    sides = {"": solve(pbr_v1, *args, example.basis),
             "select_basis_": solve(in_select_basis(replace(cfg, select_lmrm_start=False)), *args, v6),
             "select_lmrm_": solve(lmrm_v1, *args, example.basis),
             "select_basis_lmrm_": solve(in_select_basis(replace(cfg, select_lmrm_start=False, **LMRM_START_FULL)),
                                         *args, v6)}  # fmt: skip

    steps: list[int] = []
    chosen = solve(cfg, *args, example.basis, checkpoint_dir=tmp_path, progress=lambda s, n, row: steps.append(s))
    assert steps == list(range(1, cfg.run_steps() + 1))
    assert {"select_uniform_lmrm.pt", "select_textured_other_lmrm.pt"} <= {p.name for p in tmp_path.iterdir()}
    s = chosen.selection
    for prefix, plain in sides.items():  # each side's candidates are its plain TTO's
        for name in ("uniform", "textured"):
            assert s[f"{prefix or 'validation_'}psnr_{name}"] == plain.selection[f"validation_psnr_{name}"]
    for prefix in ("select_lmrm_", "select_basis_lmrm_"):  # each LMRM side's start records the LMRM's share of it
        for key in ("lmrm_start_weight_rho", "lmrm_start_weight_latent"):
            assert s[f"{prefix}{key}"] == sides[prefix].selection[key]
    assert s["select_lmrm_lmrm_start_weight_rho"] > 0 and s["select_basis_lmrm_lmrm_start_weight_latent"] == 0.0
    scores = [kept_score(plain) for plain in sides.values()]
    best = scores.index(max(scores))  # the first of equal scores: a side is taken only by scoring better
    print("held-out PSNR of the sides (v1, v6, v1 from the LMRM, v6 from the LMRM):", scores)
    assert s["select_lmrm_taken"] == float(scores[2] > max(scores[:2]))
    final = list(sides.values())[best]
    assert chosen.params.field().basis.basis_id == final.params.field().basis.basis_id
    assert torch.equal(chosen.params.tensor, final.params.tensor)
    # the LMRM's side in the configured basis forced (every later side taken): its plain TTO, bit for bit
    two = replace(cfg, select_basis="", select_margin_db=-100.0)
    forced = solve(two, *args, example.basis)
    reference = solve(replace(lmrm_v1, select_margin_db=-100.0), *args, example.basis)
    assert forced.selection["select_lmrm_taken"] == 1.0 and torch.equal(forced.params.tensor, reference.params.tensor)
    (tmp_path / "stopped").mkdir()
    resumed = resumed_after_stop(two, (*args, example.basis), tmp_path / "stopped", 2 + 1)  # the LMRM's candidate 1
    assert resumed.selection == forced.selection and torch.equal(resumed.params.tensor, forced.params.tensor)
    for bad in ({"select_uniform": False}, {"reg": "none"}):
        with pytest.raises(ValueError, match="select_lmrm_start"):
            replace(two, **bad).check()


def test_without_the_alternative_basis_the_choice_is_the_same_where_the_configured_basis_holds_the_start(
        example, truth_prediction):
    """The default since item 81 (docs/design-notes.md) tries basis v6 beside v1 and no longer has v4 as the
    alternative for v1's start. Where v1 holds the PBR start (the alternative not taken: here a margin no start can
    lose by), the TTO with the alternative and without it are the same bit for bit, so the default before's results
    stand for the new one there; only the alternative's record goes. Where the alternative is taken (any start loses
    by more than a margin of -100 dB), v1's candidates start in v4 with it and in v1 without it."""
    from neumatex_core.materials.neural_basis import BASIS_V4, BASIS_V6
    from neumatex_core.tto import solve

    cfg = TTOConfig.preset("tiny", steps=4, pbr_steps=4, pixels=64, spp=1, max_bounces=1, init="pbr", reg="start",
                           lambda_reg=0.0, lambda_consistency=1.0, select_uniform=True, select_fraction=0.5,
                           select_reuse_start=True, train_decoder=True, decoder_in_other_basis=False,
                           pbr_fit_steps=50, select_margin_db=0.0, select_basis=BASIS_V6, alternative_basis=BASIS_V4,
                           basis_margin_db=100.0)  # fmt: skip
    args = (example.mesh, example.envmap, example.photos, example.capture.tonemap, perturbed(truth_prediction, 0.2),
            example.basis)  # fmt: skip
    assert torch.get_num_threads() == 1  # this module's (one_thread): the evaluation's rows are made at one thread
    with_alternative = solve(cfg, *args)
    alone = solve(replace(cfg, alternative_basis=""), *args)
    assert with_alternative.selection["basis_switched"] == 0.0
    basis_keys = {k for k in with_alternative.selection if k.startswith("basis_")}
    assert basis_keys and not basis_keys & set(alone.selection)
    assert {k: v for k, v in with_alternative.selection.items() if k not in basis_keys} == alone.selection
    assert torch.equal(with_alternative.params.tensor, alone.params.tensor)
    assert (with_alternative.basis is None) == (alone.basis is None)
    switched = solve(replace(cfg, basis_margin_db=-100.0), *args)
    assert switched.selection["basis_switched"] == 1.0
    assert switched.selection["validation_psnr_uniform"] != alone.selection["validation_psnr_uniform"]
