"""TTO's objective (paper eq. 9-11): L = L_photo + lambda_reg * L_reg.

- L_photo: mean over pixels and channels of (T(s * render) - photo)^2, T the capture's tonemap (display values) and
  s the pixel's photo's exposure multiplier (given by the capture, times the one TTO fits with `photo_exposure`).
  With a Monte Carlo render r^ its expectation is (E[T(s r^)] - photo)^2 + Var(T(s r^)), and the variance term's
  gradient pulls the material towards what renders with less noise (dimmer, blurrier highlights). The
  "decorrelated" form (Azinovic et al. 2019, "Inverse Path Tracing") multiplies the errors of two independent
  halves of each pixel's samples, (T(s a^) - photo)(T(s b^) - photo), whose expectation is the squared error of
  the expected render alone; "linear_decorrelated" takes such products in linear radiance over every pair of
  samples. Both measured worse than the L2 on the benchmark (docs/design-notes.md, item 28). Against a noise-free
  photo the L2 of an spp-sample render is also least at a brighter material (T is concave, so E[T(r^)] < T(E[r^]));
  "decorrelated_debiased" takes that gap, estimated from each half's samples, out of "decorrelated" (item 53);
- L_reg: mean over surface points p and channels c of w_c(p) (G_c(p) - A_c(p))^2, where A is the anchor (the LMRM's
  G-buffers at p) and w the per-channel weights: exp(-log_var) of the LMRM's uncertainty ("uncertainty"),
  1 / max(e^2, eps) with e the LMRM's actual error against ground truth ("oracle"), or 0 ("none").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch

from neumatex_core.capture.tonemap import Tonemap

ORACLE_EPS = 1e-4  # floor of the oracle's squared error (a perfect LMRM channel would get an infinite weight)
LOG_VAR_MIN = -12.0  # floor of the predicted log-variances: weights at most e^12


PhotoLossKind = Literal["l2", "decorrelated", "linear_decorrelated", "decorrelated_debiased"]
DARK_FLOOR = 0.01  # linear radiance (x exposure) below which "linear_decorrelated" weighs a pixel as if at it
CLIPPED = 0.999  # display value from which a photo's pixel counts as clipped (its radiance is only a lower bound)


def held_radiance(tonemap: Tonemap, x: torch.Tensor) -> torch.Tensor:
    """x [..., 3] (linear radiance, detached) held between DARK_FLOOR / exposure and just below the clip, where the
    tonemap's derivatives are taken (the sRGB ones are unbounded at 0, and 0 above the clip)."""
    return x.detach().clamp(DARK_FLOOR / tonemap.exposure, CLIPPED / tonemap.exposure)


def tonemap_slope(tonemap: Tonemap, x: torch.Tensor) -> torch.Tensor:
    """dT/dx [..., 3] at linear radiance x [..., 3] (detached), with x floored at DARK_FLOOR / exposure and held
    just below the clip (the sRGB slope is unbounded at 0, and 0 above the clip)."""
    with torch.enable_grad():
        at = held_radiance(tonemap, x).requires_grad_(True)
        (slope,) = torch.autograd.grad(tonemap.apply(at).sum(), at)
    return slope


def tonemap_curvature(tonemap: Tonemap, x: torch.Tensor) -> torch.Tensor:
    """d^2T/dx^2 [..., 3] at linear radiance x [..., 3] (detached), x held between DARK_FLOOR / exposure and just
    below the clip as in `tonemap_slope` (the sRGB curvature is unbounded at 0)."""
    with torch.enable_grad():
        at = held_radiance(tonemap, x).requires_grad_(True)
        (slope,) = torch.autograd.grad(tonemap.apply(at).sum(), at, create_graph=True)
        if not slope.requires_grad:  # a linear transfer: the slope is constant
            return torch.zeros_like(at)
        (curvature,) = torch.autograd.grad(slope.sum(), at)
    return curvature


def photometric_loss(radiance: torch.Tensor, target: torch.Tensor, spp: int, tonemap: Tonemap,
                     scale: torch.Tensor | None = None, kind: PhotoLossKind = "l2",
                     weight_target: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """L_photo of path samples radiance [n * spp, 3] (linear, samples of one pixel contiguous and independent)
    against target display values [n, 3]; scale [n] (unitless): each pixel's photo's exposure multiplier on top of
    T's (None: 1). Returns (objective, mse): the objective TTO descends and, detached, the mean of
    (T(scale * mean over the spp samples) - target)^2, what TTO logs. kind "l2": the objective is that mse;
    "decorrelated" (spp >= 2): the mean of (T(scale * a) - target)(T(scale * b) - target) with a, b the means of
    the first spp // 2 and the other samples, an unbiased estimate of the squared error of E[T(scale * a)] (T's
    concavity still biases that at spp // 2 samples); "linear_decorrelated" (spp >= 2): the errors in linear radiance
    against the photo's linear value x = T^-1(target), the product averaged over every pair of distinct samples
    (e_i e_j, i != j: the squared error of the pixel's mean minus its sample variance / spp), weighted by T'(x)^2 (so
    it is the tonemapped squared error to first order), with no bias from T's curvature either; in a clipped photo
    pixel (target >= CLIPPED) a sample only counts below the clip; "decorrelated_debiased" (spp >= 4): "decorrelated"
    with each half's tonemapped mean less its expected gap to the tonemap of its expectation (T'' Var / (2 n), from
    the half's n samples, held fixed), least where the render's expectation matches a noise-free photo.
    weight_target [n, 3] (display values; None: target) is where the linear form's slope is taken: in a noisy photo
    the pixel's own value is correlated with its noise, and weights that grow as the photo's noise darkens it pull the
    material darker (`PhotoSet.smoothed_colour` is much less so)."""
    samples = radiance.reshape(-1, spp, 3)
    s = 1.0 if scale is None else scale.reshape(-1, 1)
    with torch.set_grad_enabled(kind == "l2" and torch.is_grad_enabled()):  # the other kinds only log it
        error = tonemap.apply(samples.mean(1) * s) - target
        mse = (error * error).mean()
    if kind == "l2":
        return mse, mse.detach()
    if spp < 2:
        raise ValueError(f"the {kind} photometric loss needs spp >= 2, got {spp}")
    if kind == "decorrelated_debiased":
        # Each half's tonemapped mean less its expected gap to the tonemap of its expectation (the delta method: T''
        # Var / (2 n) for a mean of n samples, T concave, so an n-sample render's tonemap lies below a noise-free
        # photo's at the same radiance), estimated from the half's own samples and held fixed; the product of the
        # halves' errors has no variance term. (The L2 less an estimate of its variance term is unbounded below: the
        # TTO raised the render's variance without end; docs/design-notes.md item 53.)
        if spp < 4:
            raise ValueError(f"the {kind} photometric loss needs spp >= 4 (two samples a half), got {spp}")
        half_errors = []
        for half in (samples[:, : spp // 2], samples[:, spp // 2 :]):
            mean = half.mean(1) * s
            shown = tonemap.apply(mean)
            gap = tonemap_curvature(tonemap, mean) * half.detach().var(1) * s * s / (2 * half.shape[1])
            half_errors.append(shown - torch.maximum(gap, -shown.detach()) - target)
        return (half_errors[0] * half_errors[1]).mean(), mse
    if kind == "decorrelated":
        a, b = samples[:, : spp // 2].mean(1) * s, samples[:, spp // 2 :].mean(1) * s
        return ((tonemap.apply(a) - target) * (tonemap.apply(b) - target)).mean(), mse
    if kind != "linear_decorrelated":
        raise ValueError(f"unknown photometric loss {kind!r}")
    x = tonemap.display_to_linear(target)
    clipped = (target >= CLIPPED).unsqueeze(1)
    lin = samples if scale is None else samples * scale.reshape(-1, 1, 1)
    errors = torch.where(clipped, torch.minimum(lin, x.unsqueeze(1)), lin) - x.unsqueeze(1)  # [n, spp, 3]
    # the mean over every ordered pair i != j of samples of e_i e_j (the U-statistic of the two-halves product:
    # the same expectation, less variance), from the sum and the sum of squares
    total = errors.sum(1)
    pairs = (total * total - (errors * errors).sum(1)) / (spp * (spp - 1))
    at = x if weight_target is None else tonemap.display_to_linear(weight_target)
    return (tonemap_slope(tonemap, at) ** 2 * pairs).mean(), mse


@dataclass
class Anchor:
    """Where and what L_reg pulls towards: points [P, 3] (and uvs [P, 2] for UV fields), target [P, K] G-buffer
    values, weight [P, K] per-channel weights."""

    points: torch.Tensor
    uv: torch.Tensor | None
    target: torch.Tensor
    weight: torch.Tensor

    def to(self, device: torch.device | str) -> Anchor:
        uv = None if self.uv is None else self.uv.to(device)
        return Anchor(self.points.to(device), uv, self.target.to(device), self.weight.to(device))


def uncertainty_weights(log_var: torch.Tensor) -> torch.Tensor:
    """exp(-log_var) [P, K] of the predicted log-variances (floored at LOG_VAR_MIN)."""
    return torch.exp(-log_var.clamp_min(LOG_VAR_MIN))


def oracle_weights(predicted: torch.Tensor, truth: torch.Tensor, eps: float = ORACLE_EPS) -> torch.Tensor:
    """1 / max((predicted - truth)^2, eps) [P, K]: the weights of a perfectly calibrated uncertainty."""
    return 1.0 / ((predicted - truth) ** 2).clamp_min(eps)


def regulariser(gbuffer: Callable[[torch.Tensor, torch.Tensor | None], torch.Tensor], anchor: Anchor,
                index: torch.Tensor) -> torch.Tensor:
    """L_reg over the anchor points `index` [n]: mean of weight * (gbuffer(points, uv) - target)^2."""
    uv = None if anchor.uv is None else anchor.uv[index]
    diff = gbuffer(anchor.points[index], uv) - anchor.target[index]
    return (anchor.weight[index] * diff * diff).mean()


def consistency(gbuffer: Callable[[torch.Tensor, torch.Tensor | None], torch.Tensor], anchor: Anchor,
                first: torch.Tensor, second: torch.Tensor, sigma: float, of: str = "change",
                rho_value: float = 0.0, latent_value: float = 0.0) -> torch.Tensor:
    """L_cons over the anchor point pairs (first[n], second[n]): the weighted mean of (d_a - d_b)^2 (mean over the
    K channels), weight exp(-|target_a - target_b|^2 / (2 sigma^2)), so only points that start alike (the same
    material in the anchor's target, the start) are compared. of="change": d = gbuffer(points) - target, points
    that start alike must change alike: a change shared by the whole material (a coat or a sheen the start lacks)
    costs nothing, one that varies over its surface (the capture's light painted onto it) does, and the start's own
    spatial pattern is kept. of="value": d = gbuffer(points), points that start alike must end alike (an
    edge-preserving smoothing guided by the start, which also removes the start's noise); "value_latent" /
    "value_rho": "value" for the latent (channels 3:) / the base colour rho_d (0:3), "change" for the others.
    rho_value / latent_value add, per pair and at that weight relative to the above, the mean over rho_d's 3
    channels / the latent's of (value_a - value_b)^2: that part ends alike while the rest only changes alike.
    Measured in docs/design-notes.md, items 34 and 35."""
    parts, weight = _consistency_parts(gbuffer, anchor, first, second, sigma, of, rho_value, latent_value)
    cost = (parts[0][0] ** 2).mean(1)
    for d, part_weight in parts[1:]:
        cost = cost + part_weight * (d**2).mean(1)
    return (weight * cost).sum() / weight.sum().clamp_min(1e-12)


def _consistency_parts(gbuffer: Callable[[torch.Tensor, torch.Tensor | None], torch.Tensor], anchor: Anchor,
                       first: torch.Tensor, second: torch.Tensor, sigma: float, of: str, rho_value: float,
                       latent_value: float) -> tuple[list[tuple[torch.Tensor, float]], torch.Tensor]:
    """The pairs' differences that `consistency` compares, each with its weight relative to the first (the change or
    value difference [n, K], then rho_d's [n, 3] and the latent's [n, K - 3] value differences where weighed), and the
    pairs' weights [n]."""
    both = torch.cat([first, second])
    uv = None if anchor.uv is None else anchor.uv[both]
    value = gbuffer(anchor.points[both], uv)
    change = value - anchor.target[both]
    if of == "value_latent":  # the latent (channels 3:) by value, the base colour rho_d (0:3) by its change
        change = torch.cat([change[:, :3], value[:, 3:]], 1)
    if of == "value_rho":  # the base colour rho_d (channels 0:3) by value, the latent (3:) by its change
        change = torch.cat([value[:, :3], change[:, 3:]], 1)
    da, db = (value if of == "value" else change).split(first.shape[0])
    gap = anchor.target[first] - anchor.target[second]
    weight = torch.exp(-(gap * gap).sum(1) / (2 * sigma * sigma))
    parts = [(da - db, 1.0)]
    for part, weight_of_part in ((slice(0, 3), rho_value), (slice(3, None), latent_value)):
        if weight_of_part > 0:
            va, vb = value[:, part].split(first.shape[0])
            parts.append((va - vb, weight_of_part))
    return parts, weight


def consistency_residuals(gbuffer: Callable[[torch.Tensor, torch.Tensor | None], torch.Tensor], anchor: Anchor,
                          first: torch.Tensor, second: torch.Tensor, sigma: float, of: str = "change",
                          rho_value: float = 0.0, latent_value: float = 0.0) -> list[torch.Tensor]:
    """Residuals r whose sum of squares is `consistency` (same arguments): each difference of the pairs scaled by
    sqrt(part weight x pair weight / (sum of pair weights x channels)); the Gauss-Newton probe's input
    (tto/gauss_newton.py)."""
    parts, weight = _consistency_parts(gbuffer, anchor, first, second, sigma, of, rho_value, latent_value)
    share = weight / weight.sum().clamp_min(1e-12)
    return [d * (share * part_weight / d.shape[1]).sqrt().unsqueeze(1) for d, part_weight in parts]


def photo_residuals(radiance: torch.Tensor, target: torch.Tensor, spp: int, tonemap: Tonemap,
                    scale: torch.Tensor | None = None) -> torch.Tensor:
    """[n, 3] residuals whose sum of squares is the L2 photometric loss of `photometric_loss` (same arguments):
    (T(scale * pixel mean) - target) / sqrt(3 n), differentiable; the Gauss-Newton probe's input for every photo loss
    kind (the others are the L2 without its noise terms, whose curvature the L2's approximates)."""
    s = 1.0 if scale is None else scale.reshape(-1, 1)
    error = tonemap.apply(radiance.reshape(-1, spp, 3).mean(1) * s) - target
    return error / error.numel() ** 0.5
