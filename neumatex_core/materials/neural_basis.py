"""The universal neural material basis (paper eq. 1-2, docs/architecture.md section 3) and the NeuralMaterial it
defines.

Four small MLPs, trained once on the analytic layered material (`neumatex train-basis`, see `basis_training`):

- encoder   (22 normalised layered parameters -> latent l in [-1, 1]^6): makes ground truth, not used at run time;
- decoder   (l, wi, wo -> f_neu [3], 1/sr): the specular BSDF, 4 hidden layers x 64;
- auxiliary (l, wo -> T_neu [3] in [0, 1], R_neu in [0, 1]): transmission albedo to the Lambertian base and the
  reflected energy of f_neu (its directional albedo's luminance), 3 x 64;
- sampler   (l, wo -> mixture logits over {cosine, GGX 1, GGX 2} and the two GGX widths), 2 x 32.

The full BSDF is f = T_neu(wo) rho_d / pi + f_neu(wi, wo). T and R are functions of the viewer-side direction wo
(the paper's omega_i is the known direction; see `layered`).

Directions enter the decoder through features of the local frame (+Z normal): wi, wo, the half vector h,
cos(theta_d) = h.wo and log(sin^2 theta_h + 1e-6). The last one lets a small ReLU/SiLU network form a GGX peak
log D ~ c - 2 log(sin^2 theta_h + alpha^2) without needing extreme weights. f_neu = exp(network output): positive,
and the training loss lives in log space.

Shipped weights (`data/basis.safetensors`) carry a basis id; `data/basis.json` records the id, the SHA-256 of the
weights file and the training metrics. `load_basis` checks the hash, so an asset that names a basis id and hash
can only be decoded by exactly that basis. `data/basis.*` is the default basis (what new extractions, synthetic
data and the LMRM use); further bases live in `data/bases/<name>.safetensors|json` and are loaded by id
(`load_basis(basis_id=...)`, `check_basis_id`), so an asset made with another installed basis still decodes.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file
from torch import nn

from neumatex_core.hashing import sha256_file
from neumatex_core.materials.base import Material, cosine_pdf, cosine_sample, luminance
from neumatex_core.materials.layered import N_PARAMS
from neumatex_core.materials.microfacet import ALPHA_MIN, ggx_pdf_visible, ggx_sample_visible

DATA_DIR = Path(__file__).resolve().parent / "data"
DEFAULT_WEIGHTS = DATA_DIR / "basis.safetensors"
DEFAULT_RECORD = DATA_DIR / "basis.json"
EXTRA_DIR = DATA_DIR / "bases"  # further installed bases, found by id
# The ids of the further installed bases (EXTRA_DIR/<name>.json; docs/design-notes.md items 25, 30 and 33)
BASIS_V2 = "nmx-basis-v2-4af9689561fa"
BASIS_V3 = "nmx-basis-v3-5e859f599cbd"
BASIS_V4 = "nmx-basis-v4-2b82d9690606"
BASIS_V5 = "nmx-basis-v5-783ebde8beb7"  # 12 latent numbers (docs/design-notes.md items 77, 78)
BASIS_V6 = "nmx-basis-v6-32f5a921a961"  # 16 latent numbers, every sphere family >= 35 dB (item 78)
LATENT_DIM = 6
N_DIR_FEATURES = 11
P_COSINE_MIN = 0.1  # the cosine component keeps this share of the sampling mixture (no unreachable direction)
BLOCK_ROWS = 1 << 14  # rows an MLP evaluates at once without autograd (`MLP`): 8,192-16,384 measured fastest


class BasisError(ValueError):
    """The neural basis weights are missing, corrupt or not the ones an asset asks for."""


@dataclass
class BasisArchitecture:
    """Layer sizes of the four networks (the paper's sizes by default)."""

    latent_dim: int = LATENT_DIM
    encoder_hidden: list[int] = field(default_factory=lambda: [128, 128, 128])
    decoder_hidden: list[int] = field(default_factory=lambda: [64, 64, 64, 64])
    aux_hidden: list[int] = field(default_factory=lambda: [64, 64, 64])
    sampler_hidden: list[int] = field(default_factory=lambda: [32, 32])


class MLP(nn.Sequential):
    """Linear + SiLU stack with a linear output layer, on rows [N, n_in] -> [N, n_out].

    Without autograd (renders, scores, bakes) more than BLOCK_ROWS rows are evaluated in equal blocks of at most
    BLOCK_ROWS: a block's activations ([BLOCK_ROWS, 64] floats, 4 MB) stay in the cache where a 262,144-ray chunk's
    (64 MB) do not, so the stack runs about 1.5x faster, with each row's output the same bit for bit. Equal blocks
    (more than BLOCK_ROWS / 2 rows each): a matrix product of a few rows takes another kernel, whose sums differ in
    the last bit (docs/design-notes.md item 44). Under autograd the stack runs whole, so the weights' gradients are
    summed as before."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if torch.is_grad_enabled() or x.shape[0] <= BLOCK_ROWS:
            return super().forward(x)
        whole = super().forward  # (a comprehension cannot call the zero-argument super)
        return torch.cat([whole(block) for block in x.tensor_split(-(-x.shape[0] // BLOCK_ROWS))])


def mlp(n_in: int, hidden: list[int], n_out: int) -> MLP:
    """Linear + SiLU stack (width hidden[k] for layer k) with a linear output layer."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(n_in, width), nn.SiLU()]
        n_in = width
    layers.append(nn.Linear(n_in, n_out))
    return MLP(*layers)


def direction_features(wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """[N, 11] decoder features of local unit directions wi, wo [N, 3]: wi, wo, h, cos(theta_d), log sin^2(theta_h)."""
    h = wi + wo
    h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    cos_d = (h * wo).sum(-1, keepdim=True)
    sin2_h = (1 - h[:, 2:3] * h[:, 2:3]).clamp_min(0.0)
    return torch.cat([wi, wo, h, cos_d, torch.log(sin2_h + 1e-6) / 8 + 1], dim=-1)


class NeuralBasis(nn.Module):
    """The four networks. Latents [N, 6] in [-1, 1]; directions local unit vectors [N, 3]."""

    def __init__(self, arch: BasisArchitecture | None = None) -> None:
        super().__init__()
        self.arch = arch or BasisArchitecture()
        a = self.arch
        self.encoder = mlp(N_PARAMS, a.encoder_hidden, a.latent_dim)
        self.decoder = mlp(a.latent_dim + N_DIR_FEATURES, a.decoder_hidden, 3)
        self.aux = mlp(a.latent_dim + 3, a.aux_hidden, 4)
        self.sampler = mlp(a.latent_dim + 3, a.sampler_hidden, 5)
        self.basis_id = "untrained"
        self.content_hash = ""

    def encode(self, params: torch.Tensor) -> torch.Tensor:
        """Layered parameters [N, 22] in [0, 1] -> latents [N, 6] in [-1, 1]."""
        return torch.tanh(self.encoder(params * 2 - 1))

    def log_bsdf(self, latent: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """log f_neu [N, 3] (what the decoder network outputs); valid only for wi, wo above the surface."""
        return self.decoder(torch.cat([latent, direction_features(wi, wo)], dim=-1))

    def bsdf(self, latent: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """f_neu [N, 3] (1/sr, no cosine), zero when wi or wo is below the surface."""
        above = ((wi[:, 2] > 0) & (wo[:, 2] > 0)).unsqueeze(-1)
        f = torch.exp(self.log_bsdf(latent, wi, wo).clamp(max=12.0))
        return torch.where(above, f, torch.zeros_like(f))

    def transmission_reflectance(self, latent: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(T_neu [N, 3], R_neu [N]), both in [0, 1], at the viewer-side direction wo [N, 3]."""
        out = torch.sigmoid(self.aux(torch.cat([latent, wo], dim=-1)))
        return out[:, :3], out[:, 3]

    def lobes(self, latent: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Sampling mixture of f_neu: (probabilities [N, 3] over {cosine, GGX 1, GGX 2}, GGX widths [N, 2])."""
        out = self.sampler(torch.cat([latent, wo], dim=-1))
        probs = torch.softmax(out[:, :3], dim=-1)
        alphas = ALPHA_MIN + (1 - ALPHA_MIN) * torch.sigmoid(out[:, 3:5])
        return probs, alphas

    # -- files -------------------------------------------------------------------------------------------
    def save(self, weights: Path, record: Path, metrics: dict[str, object], version: str) -> str:
        """Write weights (safetensors, tensors contiguous float32) and the record; returns the basis id."""
        weights.parent.mkdir(parents=True, exist_ok=True)
        tensors = {k: v.detach().float().cpu().contiguous() for k, v in self.state_dict().items()}
        save_file(tensors, str(weights), metadata={"architecture": json.dumps(asdict(self.arch))})
        digest = sha256_file(weights)
        self.basis_id = f"nmx-basis-{version}-{digest[:12]}"
        self.content_hash = digest
        info = {"basis_id": self.basis_id, "sha256": digest, "weights": weights.name, "version": version,
                "architecture": asdict(self.arch), "metrics": metrics}  # fmt: skip
        record.write_text(json.dumps(info, indent=2) + "\n")
        return self.basis_id


def load_basis_from(weights: Path, record: Path, device: torch.device | str = "cpu") -> NeuralBasis:
    """Load a basis, checking the weights' SHA-256 against its record; raises BasisError naming the file."""
    if not record.is_file() or not weights.is_file():
        missing = record if not record.is_file() else weights
        raise BasisError(f"{missing}: neural basis file missing (train one with `neumatex train-basis`)")
    try:
        info = json.loads(record.read_text())
        expected = str(info["sha256"])
    except (ValueError, KeyError) as exc:
        raise BasisError(f"{record}: not a basis record ({exc})") from None
    digest = sha256_file(weights)
    if digest != expected:
        raise BasisError(f"{weights}: SHA-256 {digest[:12]}... does not match the record's {expected[:12]}... "
                         "(the weights were changed or corrupted)")
    arch = BasisArchitecture(**info["architecture"])
    basis = NeuralBasis(arch)
    basis.load_state_dict(load_file(str(weights)))
    basis.basis_id, basis.content_hash = str(info["basis_id"]), digest
    basis.requires_grad_(False)
    return basis.to(device).eval()


def installed_bases() -> dict[str, tuple[Path, Path]]:
    """basis id -> (weights, record) of every installed basis: the default one, then those in `EXTRA_DIR`."""
    bases: dict[str, tuple[Path, Path]] = {}
    for record in [DEFAULT_RECORD, *sorted(EXTRA_DIR.glob("*.json"))]:
        try:
            info = json.loads(record.read_text())
            bases.setdefault(str(info["basis_id"]), (record.with_name(str(info["weights"])), record))
        except (OSError, ValueError, KeyError) as exc:
            raise BasisError(f"{record}: not a basis record ({exc})") from None
    return bases


@lru_cache(maxsize=8)
def load_basis(device: str = "cpu", basis_id: str | None = None) -> NeuralBasis:
    """An installed basis (cached per device and id), frozen: the default one (`basis_id` None or ""), or the one
    named `basis_id`."""
    if not basis_id:
        return load_basis_from(DEFAULT_WEIGHTS, DEFAULT_RECORD, device)
    bases = installed_bases()
    if basis_id not in bases:
        raise BasisError(f"neural basis {basis_id} is not installed (installed: {', '.join(bases)})")
    return load_basis_from(*bases[basis_id], device)


def basis_record(record: Path = DEFAULT_RECORD) -> dict[str, object]:
    """The shipped basis's record: id, sha256, architecture, training metrics."""
    return dict(json.loads(record.read_text()))


def latent_channel_names(k: int) -> tuple[str, ...]:
    """EXR channel names of a K-latent image (an asset's latent.exr, a synthetic object's latent G-buffer): l0..l5
    for 6, l00..l15 for 16. EXR keeps channels sorted by name, so the digits are zero-padded to one width to keep
    the latent's order."""
    width = len(str(k - 1))
    return tuple(f"l{i:0{width}d}" for i in range(k))


def basis_latent_dim(basis_id: str) -> int:
    """The latent size of the installed basis `basis_id`, from its record (the weights are not read)."""
    architecture = basis_record(installed_bases()[basis_id][1])["architecture"]
    return int(architecture["latent_dim"])  # type: ignore[index]


def check_basis_id(basis_id: str, content_hash: str, basis: NeuralBasis | None = None) -> NeuralBasis:
    """The basis an asset names (`basis` or the default when it is that one, else the installed basis with that id),
    or a BasisError saying which one it needs and which one we have."""
    have = basis or load_basis()
    if basis_id == have.basis_id and (not content_hash or content_hash == have.content_hash):
        return have
    if basis_id in installed_bases():
        found = load_basis(str(next(have.parameters()).device), basis_id)
        if not content_hash or content_hash == found.content_hash:
            return found
    installed = ", ".join(installed_bases())
    raise BasisError(f"needs neural basis {basis_id} (sha256 {content_hash[:12]}...), but this installation has "
                     f"{installed}; install the NeuMatEx version that wrote it")


class NeuralMaterial(Material):
    """f = T_neu(wo) rho_d / pi + f_neu(wi, wo) at N points.

    base_color: [N, 3] rho_d in [0, 1]; latent: [N, 6] in [-1, 1]; both may require grad (the basis is frozen).
    Sampling: a cosine lobe for the diffuse part, chosen with probability lum(T rho_d) / (lum(T rho_d) + R_neu),
    else the sampler network's mixture for f_neu; P_COSINE_MIN of cosine always. Detached, exact pdf.
    """

    def __init__(self, basis: NeuralBasis, base_color: torch.Tensor, latent: torch.Tensor) -> None:
        if latent.dim() != 2 or latent.shape[-1] != basis.arch.latent_dim:
            raise ValueError(f"latent must be [N, {basis.arch.latent_dim}], got {tuple(latent.shape)}")
        if base_color.shape != (latent.shape[0], 3):
            raise ValueError(f"base_color must be [N, 3], got {tuple(base_color.shape)}")
        self.basis = basis
        self.base_color = base_color
        self.latent = latent
        self._aux_key: torch.Tensor | None = None
        self._aux: tuple[torch.Tensor, torch.Tensor] = (latent, latent)
        self._mixture_key: torch.Tensor | None = None
        self._mixture: tuple[torch.Tensor, torch.Tensor] = (latent, latent)

    def _transmission_reflectance(self, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # The path tracer asks several times per bounce with the same wo tensor: evaluate the aux network once.
        if self._aux_key is not wo:
            self._aux = self.basis.transmission_reflectance(self.latent, wo)
            self._aux_key = wo
        return self._aux

    def eval(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        t, _ = self._transmission_reflectance(wo)
        above = ((wi[:, 2] > 0) & (wo[:, 2] > 0)).unsqueeze(-1)
        diffuse = torch.where(above, t * self.base_color / math.pi, torch.zeros_like(t))
        return diffuse + self.basis.bsdf(self.latent, wi, wo)

    def lambert(self, wo: torch.Tensor) -> torch.Tensor:
        t, _ = self._transmission_reflectance(wo)
        return torch.where((wo[:, 2] > 0).unsqueeze(-1), t * self.base_color, torch.zeros_like(t))

    def eval_glossy(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        return self.basis.bsdf(self.latent, wi, wo)

    def mixture(self, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Detached (probabilities [N, 3] over {cosine, GGX 1, GGX 2}, widths [N, 2]) of `sample`."""
        # `pdf` (next-event estimation) and `sample` ask with the same wo tensor each bounce: run the sampler once
        if self._mixture_key is not wo:
            self._mixture = self._lobe_mixture(wo)
            self._mixture_key = wo
        return self._mixture

    def _lobe_mixture(self, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            t, r = self._transmission_reflectance(wo)
            diffuse = luminance(t.detach() * self.base_color.detach())
            p_diffuse = torch.where(diffuse + r > 0, diffuse / (diffuse + r.detach()).clamp_min(1e-12),
                                    torch.ones_like(diffuse))
            probs, alphas = self.basis.lobes(self.latent.detach(), wo)
            probs = (1 - p_diffuse).unsqueeze(-1) * probs
            probs[:, 0] += p_diffuse
            probs = (1 - P_COSINE_MIN) * probs
            probs[:, 0] += P_COSINE_MIN
            return probs, alphas

    def sample(self, wo: torch.Tensor, u_lobe: torch.Tensor, u_dir: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            probs, alphas = self.mixture(wo)
            candidates = torch.stack(
                [cosine_sample(u_dir), ggx_sample_visible(wo, alphas[:, 0], u_dir),
                 ggx_sample_visible(wo, alphas[:, 1], u_dir)], dim=1)  # fmt: skip
            choice = (u_lobe.unsqueeze(-1) >= probs.cumsum(-1)[:, :-1]).sum(-1)
            wi = candidates[torch.arange(wo.shape[0], device=wo.device), choice]
            return wi, self._pdf(wi, wo, probs, alphas)

    @staticmethod
    def _pdf(wi: torch.Tensor, wo: torch.Tensor, probs: torch.Tensor, alphas: torch.Tensor) -> torch.Tensor:
        pdfs = torch.stack([cosine_pdf(wi), ggx_pdf_visible(wi, wo, alphas[:, 0]),
                            ggx_pdf_visible(wi, wo, alphas[:, 1])], dim=-1)  # fmt: skip
        pdf = (probs * pdfs).sum(-1)
        valid = (wi[:, 2] > 0) & (wo[:, 2] > 0)
        return torch.where(valid, pdf, torch.zeros_like(pdf))

    def pdf(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            probs, alphas = self.mixture(wo)
            return self._pdf(wi, wo, probs, alphas)

    def albedo(self, wo: torch.Tensor) -> torch.Tensor:
        """T_neu rho_d + R_neu (grey: R_neu is a luminance) [N, 3]."""
        t, r = self._transmission_reflectance(wo)
        value = t * self.base_color + r.unsqueeze(-1)
        return torch.where((wo[:, 2] > 0).unsqueeze(-1), value, torch.zeros_like(value))

    def select(self, index: torch.Tensor) -> NeuralMaterial:
        return NeuralMaterial(self.basis, self.base_color[index], self.latent[index])
