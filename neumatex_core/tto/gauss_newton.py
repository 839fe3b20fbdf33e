"""A diagonal Gauss-Newton step for the TTO's field tensor (`TTOConfig.optimizer` "gauss_newton"; docs/design-notes.md
item 57).

Why not Adam there: Adam divides each parameter's gradient by the root of its mean square, and where the gradient
is mostly Monte Carlo noise (a texel that few photo pixels reach) that mean square is the noise's, so the parameter
walks by about the learning rate a step whatever the photos say about it (items 49, 50). The photo loss is a sum
of squared residuals, L = sum_k r_k^2, whose Gauss-Newton curvature 2 sum_k J_k J_k^T depends on how strongly the
photos see each parameter, not on the residuals' noise. Its diagonal h is estimated without per-pixel Jacobians
(Hutchinson's trick on J^T): with z_k independent signs, the gradient of the probe P = sqrt(2) sum_k z_k r_k is
sqrt(2) J^T z, whose square has expectation 2 sum_k J_k^2 = h, one extra backward pass through the step's graph
(`curvature_probe`). The step is then a damped fraction of the diagonal Newton step,

    delta = -lr * m / (h + damping * mean(h)),  clamped to |delta| <= max_step,

m and h the bias-corrected moving averages of the gradient (beta1) and of the probe's squared gradient (beta2):
every parameter converges at the same rate lr per step, and the noise a step leaves behind shrinks with the
parameter's curvature (a texel seen by many pixels moves little on noise, one seen by few is moved by its few
pixels' signal, not by a fixed step). The other parameter groups (the decoder, the photos' exposures) take Adam
steps with the same moving averages, as torch.optim.Adam does.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any

import torch


class DiagonalGaussNewton(torch.optim.Optimizer):
    """Groups with `curvature` True take the damped diagonal Gauss-Newton step above (their curvature comes from
    `fold_curvature` before each `step`); the others plain Adam. Hyper-parameters per group: lr, betas, eps (Adam),
    damping (relative to the group's mean curvature), max_step (parameter units) and warmup (steps over which the
    curvature groups' rate ramps up linearly from lr / warmup, while h is still the mean of few probes); block_dim
    (None: diagonal) solves the step in blocks of the parameters along that dimension instead (`_block_newton`)."""

    def __init__(self, groups: Iterable[dict[str, Any]], lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8, damping: float = 1e-2, max_step: float = 0.2, warmup: int = 0) -> None:
        defaults = {"lr": lr, "betas": betas, "eps": eps, "damping": damping, "max_step": max_step,
                    "warmup": warmup, "block_dim": None, "curvature": False}  # fmt: skip
        super().__init__(list(groups), defaults)

    @torch.no_grad()
    def fold_curvature(self, probe_grads: Sequence[torch.Tensor | None]) -> None:
        """The probe's gradients [shape of each parameter] of the curvature groups' parameters (in order), this step's
        estimate of sqrt(h): folded into the moving average of h by the next `step`."""
        params = [p for group in self.param_groups if group["curvature"] for p in group["params"]]
        if len(params) != len(probe_grads):
            raise ValueError(f"fold_curvature: {len(probe_grads)} probe gradients for {len(params)} parameters")
        for p, q in zip(params, probe_grads, strict=True):
            self.state[p]["probe"] = torch.zeros_like(p) if q is None else q

    @torch.no_grad()
    def step(self, closure: Callable[[], float] | None = None) -> float | None:  # type: ignore[override]
        """One step of every group (`closure` is not used: the TTO computes its loss and curvature itself)."""
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if "step" not in state:
                    state["step"] = torch.zeros((), dtype=torch.float64)
                    state["exp_avg"] = torch.zeros_like(p)
                    state["exp_avg_sq"] = torch.zeros_like(p)
                state["step"] += 1
                t = float(state["step"])
                m, v = state["exp_avg"], state["exp_avg_sq"]
                m.lerp_(p.grad, 1 - beta1)
                m_hat = m / (1 - beta1**t)
                if group["curvature"]:
                    if "probe" not in state:
                        raise RuntimeError("DiagonalGaussNewton.step: no curvature folded in for this step")
                    q = state.pop("probe")
                    # h is the mean of t one-probe estimates (relative error about sqrt(2 / t)): ramp the step up
                    lr = group["lr"] * min(1.0, t / max(group["warmup"], 1))
                    if group["block_dim"] is None:
                        v.lerp_(q * q, 1 - beta2)
                        h = v / (1 - beta2**t)
                        delta = m_hat / (h + group["damping"] * h.mean().clamp_min(1e-30))
                    else:
                        delta = self._block_newton(state, q, m_hat, group, 1 - beta2**t)
                    p.add_((-lr * delta).clamp_(-group["max_step"], group["max_step"]))
                else:
                    v.mul_(beta2).addcmul_(p.grad, p.grad, value=1 - beta2)
                    denom = (v / (1 - beta2**t)).sqrt_().add_(group["eps"])
                    p.addcdiv_(m_hat, denom, value=-group["lr"])
        return None

    @staticmethod
    def _block_newton(state: dict[str, Any], q: torch.Tensor, m_hat: torch.Tensor, group: dict[str, Any],
                      correction: float) -> torch.Tensor:
        """The Newton step m_hat solved block by block: the parameters along `block_dim` (a texel's channels, which
        the decoder mixes) share a C x C Gauss-Newton block, the moving average of the probe's outer products."""
        dim, beta2 = group["block_dim"], group["betas"][1]
        qb = q.movedim(dim, -1)
        shape = qb.shape
        qb = qb.reshape(-1, shape[-1])
        if "block" not in state:
            state["block"] = torch.zeros(qb.shape[0], shape[-1], shape[-1], dtype=q.dtype, device=q.device)
        block = state["block"]
        block.lerp_(qb.unsqueeze(2) * qb.unsqueeze(1), 1 - beta2)
        h = block / correction
        diag_mean = torch.diagonal(h, dim1=1, dim2=2).mean().clamp_min(1e-30)
        eye = torch.eye(shape[-1], dtype=q.dtype, device=q.device)
        rhs = m_hat.movedim(dim, -1).reshape(-1, shape[-1], 1)
        delta = torch.linalg.solve(h + group["damping"] * diag_mean * eye, rhs)
        return delta.reshape(shape).movedim(-1, dim)


def sign_probe(residuals: Sequence[torch.Tensor], generator: torch.Generator) -> torch.Tensor:
    """P = sqrt(2) sum_k z_k r_k over every residual tensor (any shapes; the loss they make is sum r^2), z_k
    independent signs from `generator`: the gradient of P squared estimates the Gauss-Newton diagonal of that loss."""
    total = torch.zeros((), device=residuals[0].device)
    for r in residuals:
        z = torch.randint(0, 2, r.shape, generator=generator, device=r.device).to(r.dtype) * 2 - 1
        total = total + (z * r).sum()
    return total * 2**0.5
