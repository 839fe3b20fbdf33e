"""LMRM inference: the shipped checkpoint and `LMRM.predict` (the interface the TTO and pipeline code use).

    lmrm = load_lmrm(device="cpu")                       # checks the checkpoint against the shipped neural basis
    pred = lmrm.predict(views, cameras, mesh, envmap)    # views [V, H, W, 3] tonemapped sRGB in [0, 1]
    rho_d, latent, log_var = pred.gbuffers(points)       # [N, 3], [N, 6], [N, 9] at surface points [N, 3]
    # G_mat(points) = pred.material_decoder(pred.triplane.features(points))

The mesh and cameras must be in the normalised frame (object inside the unit sphere, as `neumatex synth` writes
and `Mesh.normalized` / `Camera.normalized` make): the triplane covers [-1, 1]^3. Views of any size are resampled
to the model's `view_resolution` (in linear space); G-buffers of the views come from ray queries on the mesh.

Checkpoint files (`data/lmrm.safetensors` + `data/lmrm.json`): float32 weights of `LMRMNet`; the record holds the
format, the `LMRMConfig`, the SHA-256 of the weights, the neural basis id and hash the model was trained for, the
training data manifest hash and the training and validation metrics.
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file

from neumatex_core.capture.tonemap import srgb_eotf, srgb_oetf
from neumatex_core.fields.decoders import MaterialDecoder, PBRDecoder, UncertaintyDecoder
from neumatex_core.fields.triplane import Triplane
from neumatex_core.geometry.camera import Camera
from neumatex_core.geometry.gbuffer import render_gbuffer
from neumatex_core.geometry.mesh import Mesh
from neumatex_core.geometry.raycast import RayCaster
from neumatex_core.hashing import sha256_file
from neumatex_core.lighting.envmap import EnvironmentMap
from neumatex_core.lmrm.data import lighting_cues, prefiltered, to_camera_directions
from neumatex_core.lmrm.model import LMRMConfig, LMRMNet, ObjectInputs, view_inputs
from neumatex_core.materials.neural_basis import NeuralBasis, load_basis

DATA_DIR = Path(__file__).resolve().parent / "data"
DEFAULT_WEIGHTS = DATA_DIR / "lmrm.safetensors"
DEFAULT_RECORD = DATA_DIR / "lmrm.json"
FORMAT = "nmx-lmrm-1"
CUBE_TOLERANCE = 1e-3


class LMRMError(ValueError):
    """The LMRM checkpoint is missing, corrupt or incompatible, or predict() got unusable input."""


@dataclass
class LMRMPrediction:
    """The LMRM's output for one object: a triplane and the (frozen, copied) decoders that read it.

    G_mat(points) = material_decoder(triplane.features(points)); G_unc = uncertainty_decoder(same features).
    """

    triplane: Triplane
    material_decoder: MaterialDecoder
    uncertainty_decoder: UncertaintyDecoder
    pbr_decoder: PBRDecoder

    def gbuffers(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """At surface points [N, 3]: rho_d [N, 3] linear in [0, 1], latent [N, 6] in [-1, 1], log-variances [N, 9]
        of (rho_d, latent). Differentiable in the triplane (TTO optimises it); the decoders are frozen."""
        feats = self.triplane.features(points)
        rho_d, latent = self.material_decoder(feats)
        return rho_d, latent, self.uncertainty_decoder(feats)

    def pbr(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The PBR head at points [N, 3]: base colour [N, 3], roughness [N], metallic [N] (initialises the PBR
        baseline)."""
        out: tuple[torch.Tensor, torch.Tensor, torch.Tensor] = self.pbr_decoder(self.triplane.features(points))
        return out


class LMRM:
    """A loaded LMRM (network in eval mode on `device`) and its record. See the module docstring."""

    def __init__(self, net: LMRMNet, record: dict[str, Any], device: torch.device | str = "cpu") -> None:
        self.device = torch.device(device)
        self.net = net.to(self.device).eval()
        self.net.requires_grad_(False)
        self.record = record
        self.config: LMRMConfig = net.cfg

    @property
    def basis_id(self) -> str:
        return str(self.record.get("basis_id", ""))

    def prepare(self, views: torch.Tensor, cameras: list[Camera], mesh: Mesh,
                envmap: EnvironmentMap | None = None) -> ObjectInputs:
        """Network inputs for views [V, H, W, 3] (see `predict`)."""
        if views.dim() != 4 or views.shape[-1] != 3:
            raise LMRMError(f"views must be [V, H, W, 3] tonemapped sRGB, got {tuple(views.shape)}")
        v, h, w = int(views.shape[0]), int(views.shape[1]), int(views.shape[2])
        if len(cameras) != v or v == 0:
            raise LMRMError(f"got {v} views but {len(cameras)} cameras; give one camera per view")
        bad = [i for i, c in enumerate(cameras) if (c.width, c.height) != (w, h)]
        if bad:
            raise LMRMError(f"cameras {bad} are not {w}x{h} like the views (intrinsics must match the images)")
        if not bool(torch.isfinite(views).all()) or float(views.min()) < -1e-6 or float(views.max()) > 1 + 1e-6:
            raise LMRMError("views must be tonemapped display values in [0, 1] (finite)")
        extent = float(np.abs(mesh.vertices).max()) if mesh.vertices.size else 0.0
        if extent > 1 + CUBE_TOLERANCE:
            raise LMRMError(f"the mesh reaches {extent:.3f} from the origin; the LMRM wants it normalised into the "
                            "unit sphere (Mesh.normalized, Camera.normalized)")  # fmt: skip
        r = self.config.view_resolution
        views = views.detach().float().cpu().clamp(0, 1)
        if (h, w) != (r, r):
            lin = srgb_eotf(views).permute(0, 3, 1, 2)
            views = srgb_oetf(F.interpolate(lin, size=(r, r), mode="area").clamp(0, 1)).permute(0, 2, 3, 1)
            cameras = [c.resized(r, r) for c in cameras]
        caster = RayCaster(mesh)
        gbs = [render_gbuffer(mesh, c, caster) for c in cameras]
        mask = torch.stack([g.mask for g in gbs])
        position = torch.stack([g.position for g in gbs])
        normal = torch.stack([g.normal for g in gbs])
        to_cam = to_camera_directions(position, cameras)
        cues = None
        if envmap is not None:
            lighting = prefiltered(envmap.to("cpu"))
            cues = torch.zeros(*mask.shape, 12)
            cues[mask] = lighting_cues(lighting, normal[mask], to_cam[mask])
        inputs = view_inputs(views, mask, normal, to_cam, cues)
        d = self.device
        return ObjectInputs(inputs.to(d), mask.to(d), position.to(d))

    @torch.no_grad()
    def predict(self, views: torch.Tensor, cameras: list[Camera], mesh: Mesh,
                envmap: EnvironmentMap | None = None) -> LMRMPrediction:
        """Triplane and decoders for one object from its views [V, H, W, 3] (tonemapped sRGB in [0, 1], normally
        the 23 preset views), their cameras (intrinsics for H x W), the mesh (normalised frame) and, when known,
        the environment map (its pre-filtered lighting is an input; without it the lighting is treated as
        unknown)."""
        obj = self.prepare(views, cameras, mesh, envmap)
        if not bool(obj.mask.any()):
            raise LMRMError("the mesh covers no pixel of any view (wrong cameras or mesh frame?)")
        planes = self.net.planes([obj])[0]
        triplane = Triplane.from_planes(planes)
        triplane.requires_grad_(True)
        decoders = [copy.deepcopy(m) for m in (self.net.material_decoder, self.net.uncertainty_decoder,
                                               self.net.pbr_decoder)]  # fmt: skip
        for m in decoders:
            m.requires_grad_(False)
        mat, unc, pbr = decoders
        assert isinstance(mat, MaterialDecoder) and isinstance(unc, UncertaintyDecoder)
        assert isinstance(pbr, PBRDecoder)
        return LMRMPrediction(triplane, mat, unc, pbr)


def save_lmrm(net: LMRMNet, weights: Path, record: Path, basis: NeuralBasis, info: dict[str, Any]) -> dict[str, Any]:
    """Write the network (safetensors, float32) and its record (JSON: config, hashes, basis, `info`)."""
    weights.parent.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().float().cpu().contiguous() for k, v in net.state_dict().items()}
    save_file(tensors, str(weights), metadata={"format": FORMAT})
    rec = {"format": FORMAT, "config": net.cfg.to_dict(), "weights": weights.name, "sha256": sha256_file(weights),
           "basis_id": basis.basis_id, "basis_sha256": basis.content_hash, **info}  # fmt: skip
    record.write_text(json.dumps(rec, indent=1, sort_keys=True) + "\n")
    return rec


def load_lmrm_from(weights: Path, record: Path, device: torch.device | str = "cpu",
                   basis: NeuralBasis | None = None) -> LMRM:
    """Load a checkpoint, checking its weights' hash and that it was trained for `basis` (default: the shipped
    basis). Raises LMRMError naming the file and the problem."""
    for path in (record, weights):
        if not path.is_file():
            raise LMRMError(f"{path}: LMRM checkpoint file missing (train one with `neumatex train-lmrm --install`)")
    try:
        rec = json.loads(record.read_text())
        fmt, cfg = rec["format"], LMRMConfig.from_dict(rec["config"])
        expected, basis_id = str(rec["sha256"]), str(rec["basis_id"])
    except (ValueError, KeyError, TypeError) as exc:
        raise LMRMError(f"{record}: not an LMRM checkpoint record ({exc})") from None
    if fmt != FORMAT:
        raise LMRMError(f"{record}: checkpoint format {fmt!r}, this version reads {FORMAT!r}")
    digest = sha256_file(weights)
    if digest != expected:
        raise LMRMError(f"{weights}: SHA-256 {digest[:12]}... does not match the record's {expected[:12]}... "
                        "(the weights were changed or corrupted)")
    have = basis if basis is not None else load_basis()
    if basis_id != have.basis_id:
        raise LMRMError(f"{record}: the LMRM was trained for neural basis {basis_id}, but this installation has "
                        f"{have.basis_id}; retrain it (`neumatex train-lmrm`) on data made with this basis")
    net = LMRMNet(cfg)
    try:
        net.load_state_dict(load_file(str(weights)))
    except RuntimeError as exc:
        detail = " ".join(str(exc).split())[:300]
        raise LMRMError(f"{weights}: weights do not fit this version's LMRM network for the recorded config "
                        f"(retrain, or use the NeuMatEx version that wrote it): {detail}") from None
    return LMRM(net, rec, device)


def load_lmrm(device: torch.device | str = "cpu") -> LMRM:
    """The shipped LMRM checkpoint (neumatex_core/lmrm/data/), checked against the shipped neural basis."""
    return load_lmrm_from(DEFAULT_WEIGHTS, DEFAULT_RECORD, device)
