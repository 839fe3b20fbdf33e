"""Adam with one normaliser per tensor (TTOConfig.adam_normalise "tensor"; docs/design-notes.md item 52).

Adam divides each element's first moment m by the root of its own second moment v, so every element moves by
about the learning rate a step whatever its gradient's signal-to-noise: a texel whose photo gradient is mostly
Monte Carlo noise walks as fast as one the photos constrain (item 50). This variant divides every element of a
tensor by the same number, the root mean square over the tensor of sqrt(v) (bias-corrected moments, as Adam):
elements whose gradients are consistently large take the large steps and noisy, weakly reached ones small steps in
proportion to their averaged gradient. Nicolet et al. 2021 ("Large steps in inverse rendering of geometry") divide
by the maximum; the RMS keeps a typical element's step near the learning rate, so the schedule tuned for Adam holds.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch


class UniformAdam(torch.optim.Optimizer):
    """Adam (betas, eps, per-group lr) whose step for tensor p is lr * m_hat / (sqrt(mean(v_hat)) + eps)."""

    def __init__(self, params: Iterable[Any], lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8) -> None:
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps})

    @torch.no_grad()
    def step(self, closure: Any = None) -> None:  # type: ignore[override]
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state[p]
                if not state:
                    state["step"] = torch.zeros((), dtype=torch.float64)
                    state["exp_avg"] = torch.zeros_like(p)
                    state["exp_avg_sq"] = torch.zeros_like(p)
                state["step"] += 1
                t = float(state["step"])
                m, v = state["exp_avg"], state["exp_avg_sq"]
                m.mul_(beta1).add_(p.grad, alpha=1 - beta1)
                v.mul_(beta2).addcmul_(p.grad, p.grad, value=1 - beta2)
                scale = float((v.mean() / (1 - beta2**t)).sqrt()) + group["eps"]
                p.add_(m, alpha=-group["lr"] / ((1 - beta1**t) * scale))
