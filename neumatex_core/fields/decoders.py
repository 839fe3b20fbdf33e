"""Small MLP decoders from triplane features [N, F] (F = 3C) to per-point G-buffers (paper eq. 3-6).

- `MaterialDecoder` (M_mat): rho_d [N, 3] in [0, 1] (sigmoid) and latent l [N, K] in [-1, 1] (tanh), K the
  basis's latent size (6; `with_latent_dim` adapts a decoder to a basis of another size);
- `UncertaintyDecoder` (M_unc): 9 log-variances [N, 9] (rho_d then l), unbounded;
- `PBRDecoder` (the LMRM's PBR head): base colour [N, 3], roughness [N], metallic [N], all in [0, 1] (sigmoid);
- `FamilyDecoder` (the LMRM's family head, not part of assets): logits [N, 8] of the material families
  (materials/prior.py FAMILIES).

Each is Linear+SiLU x `layers` (width `hidden`) with a linear output; `architecture()` gives the constructor
arguments, so an asset can rebuild the module from its record. `module_id` names a decoder by its class and the
SHA-256 of its weights: an asset records it and the reader checks it.
"""

from __future__ import annotations

import hashlib
import math
from typing import Any

import torch
from torch import nn

from neumatex_core.materials.neural_basis import LATENT_DIM, mlp
from neumatex_core.materials.prior import FAMILIES

N_MATERIAL = 3 + LATENT_DIM  # rho_d + latent: the material G-buffer's channels


class _Decoder(nn.Module):
    kind = "decoder"
    n_out = 0

    def __init__(self, in_features: int, hidden: int = 64, layers: int = 2, n_out: int | None = None) -> None:
        """n_out: the output width, where a subclass's depends on its arguments (else the class's `n_out`)."""
        super().__init__()
        self.in_features, self.hidden, self.layers = in_features, hidden, layers
        self.net = mlp(in_features, [hidden] * layers, self.n_out if n_out is None else n_out)

    def architecture(self) -> dict[str, Any]:
        """Constructor arguments (JSON-able): `type(self)(**architecture())` has the same shapes."""
        return {"in_features": self.in_features, "hidden": self.hidden, "layers": self.layers}


class MaterialDecoder(_Decoder):
    """M_mat: features [N, F] -> (rho_d [N, 3] in [0, 1], latent [N, latent_dim] in [-1, 1])."""

    kind = "material"

    def __init__(self, in_features: int, hidden: int = 64, layers: int = 2, latent_dim: int = LATENT_DIM) -> None:
        super().__init__(in_features, hidden, layers, 3 + latent_dim)
        self.latent_dim = latent_dim

    def architecture(self) -> dict[str, Any]:
        arch = super().architecture()  # the default size is left out, so earlier assets' records stay as they are
        return arch if self.latent_dim == LATENT_DIM else {**arch, "latent_dim": self.latent_dim}

    def with_latent_dim(self, latent_dim: int, seed: int = 0) -> MaterialDecoder:
        """A copy whose output holds `latent_dim` latent numbers, for a basis of that size: the hidden layers and
        rho_d's output rows are kept, and so are the first latent rows; added rows start as a fresh layer's would
        (from `seed`). Another basis's latents mean something else, so what the kept rows carry over is the
        features' scale: the PBR start fits the planes to the new basis's latents (tto/pbr_start.py)."""
        last = len(self.net) - 1  # the output layer's index in the stack
        fresh = _fresh_linear(self.hidden, 3 + latent_dim, seed)
        keep = min(latent_dim, self.latent_dim) + 3
        state = self.net.state_dict()
        for name in ("weight", "bias"):
            fresh[name][:keep] = state[f"{last}.{name}"][:keep]
            state[f"{last}.{name}"] = fresh[name]
        out = MaterialDecoder(self.in_features, self.hidden, self.layers, latent_dim)
        out.net.load_state_dict(state)
        out.to(state[f"{last}.weight"].device)
        return out.requires_grad_(any(w.requires_grad for w in self.parameters()))

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.net(features)
        return torch.sigmoid(out[:, :3]), torch.tanh(out[:, 3:])


class UncertaintyDecoder(_Decoder):
    """M_unc: features [N, F] -> log-variances [N, 9] of (rho_d, latent)."""

    kind = "uncertainty"
    n_out = N_MATERIAL

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.net(features)


class PBRDecoder(_Decoder):
    """PBR head: features [N, F] -> (base colour [N, 3], roughness [N], metallic [N]), all in [0, 1]."""

    kind = "pbr"
    n_out = 5

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        out = torch.sigmoid(self.net(features))
        return out[:, :3], out[:, 3], out[:, 4]


class FamilyDecoder(_Decoder):
    """The LMRM's family head: features [N, F] -> logits [N, len(FAMILIES)] of each point's material family."""

    kind = "family"
    n_out = len(FAMILIES)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.net(features)


# the decoders an asset may hold (assets/package.py); the family head is the LMRM's training signal only
DECODERS: dict[str, type[_Decoder]] = {cls.kind: cls for cls in (MaterialDecoder, UncertaintyDecoder, PBRDecoder)}


def _fresh_linear(in_features: int, out_features: int, seed: int) -> dict[str, torch.Tensor]:
    """The state of a fresh nn.Linear(in_features, out_features) drawn from `seed`: the same bits as after
    torch.manual_seed(seed), but from a private generator. Seeding torch's global generator is not safe in threads:
    the TTO's candidates make their decoder copies side by side, and interleaved draws gave a copy other rows in
    about a third of the copies (the demo's choice of material then changed from one run to the next)."""
    g = torch.Generator().manual_seed(seed)
    weight = torch.empty(out_features, in_features)
    nn.init.kaiming_uniform_(weight, a=math.sqrt(5), generator=g)  # nn.Linear.reset_parameters, in its order
    bound = 1 / math.sqrt(in_features)
    return {"weight": weight, "bias": torch.empty(out_features).uniform_(-bound, bound, generator=g)}


def state_hash(module: nn.Module) -> str:
    """SHA-256 over the module's state (names, shapes and float32 bytes, in key order)."""
    h = hashlib.sha256()
    for name, t in sorted(module.state_dict().items()):
        h.update(name.encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.detach().to("cpu", torch.float32).contiguous().numpy().tobytes())
    return h.hexdigest()


def module_id(module: nn.Module) -> str:
    """'<kind>-<first 16 hex digits of state_hash>', e.g. 'material-3fa2...'."""
    kind = getattr(module, "kind", type(module).__name__.lower())
    return f"{kind}-{state_hash(module)[:16]}"
