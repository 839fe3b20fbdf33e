"""Distilling a known per-point material into a triplane field (Adam on the G-buffer MSE), and `fit_on_points`, the
Adam loop of the fits to values known at surface points (tto/pbr_start.py `fit_planes`, lmrm/restate.py).

Used to make test and benchmark objects whose triplane encodes a known material (until the LMRM predicts
triplanes), and usable as an initialisation. `target(points [N, 3]) -> (rho_d [N, 3], latent [N, K])` (K: the
basis's latent size) is any function of the surface points; `points` are samples of the surface (e.g. `Mesh` area
samples).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import torch

from neumatex_core.fields.decoders import MaterialDecoder
from neumatex_core.fields.neural_field import TriplaneMaterialField
from neumatex_core.fields.triplane import Triplane
from neumatex_core.materials.neural_basis import NeuralBasis

Target = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


def fit_on_points(parameters: Iterable[torch.Tensor], batch_loss: Callable[[torch.Tensor], torch.Tensor], n: int,
                  steps: int, lr: float, batch: int, seed: int, device: torch.device) -> None:
    """`steps` Adam steps on `parameters` (in place), each on `batch_loss(idx)` for `batch` indices [batch] into n
    points drawn with replacement (a generator seeded `seed` on `device`), at `lr` cosine-decayed to 0."""
    opt = torch.optim.Adam(list(parameters), lr=lr)
    g = torch.Generator(device=device).manual_seed(seed)
    for step in range(steps):
        for group in opt.param_groups:
            group["lr"] = lr * 0.5 * (1 + math.cos(math.pi * step / steps))
        idx = torch.randint(0, n, (batch,), generator=g, device=device)
        loss = batch_loss(idx)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()


def fit_triplane(points: torch.Tensor, target: Target, basis: NeuralBasis, channels: int = 8, resolution: int = 32,
                 steps: int = 300, lr: float = 0.02, batch: int = 8192,
                 seed: int = 0) -> tuple[TriplaneMaterialField, float]:
    """(field, final G-buffer MSE over all points): a triplane + decoder fitted to `target` at `points` [N, 3].

    MSE on (rho_d, (latent + 1) / 2), the G-buffer metric's scale. Deterministic for a seed on one device.
    """
    g = torch.Generator().manual_seed(seed)
    device = points.device
    triplane = Triplane(channels, resolution, init_std=0.1, generator=g).to(device)
    torch.manual_seed(seed)
    decoder = MaterialDecoder(triplane.feature_dim, latent_dim=basis.arch.latent_dim).to(device)
    with torch.no_grad():
        rho_t, lat_t = target(points)
        want = torch.cat([rho_t, (lat_t + 1) / 2], dim=-1)
    opt = torch.optim.Adam([*triplane.parameters(), *decoder.parameters()], lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    n = points.shape[0]
    for _ in range(steps):
        idx = torch.randint(0, n, (min(batch, n),), generator=g).to(device)
        rho, lat = decoder(triplane.features(points[idx]))
        loss = ((torch.cat([rho, (lat + 1) / 2], dim=-1) - want[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    triplane.requires_grad_(False)
    decoder.requires_grad_(False)
    field = TriplaneMaterialField(triplane, decoder, basis)
    with torch.no_grad():
        rho, lat = field.gbuffer(points)
        mse = float(((torch.cat([rho, (lat + 1) / 2], dim=-1) - want) ** 2).mean())
    return field, mse
