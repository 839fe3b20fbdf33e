"""Large Material Reconstruction Model (docs/architecture.md section 5): the 23 preset views of an object, its mesh,
cameras and (optionally) lighting -> a feature triplane decoded into base colour, the 6-D latent and per-channel
log-variances, in one forward pass.

- `load_lmrm(device) -> LMRM` (inference.py): the shipped checkpoint, checked against the neural basis;
- `LMRM.predict(views, cameras, mesh, envmap) -> LMRMPrediction` (triplane, material / uncertainty / PBR decoders,
  `gbuffers(points)`);
- model.py (network), data.py (synthetic training data, augmentation), losses.py (L_mat, beta-NLL),
  train.py (`neumatex train-lmrm`: two-stage curriculum, checkpoints, resume, DDP under torchrun).
"""

from neumatex_core.lmrm.inference import LMRM, LMRMError, LMRMPrediction, load_lmrm, load_lmrm_from, save_lmrm
from neumatex_core.lmrm.model import LMRMConfig, LMRMNet

__all__ = ["LMRM", "LMRMConfig", "LMRMError", "LMRMNet", "LMRMPrediction", "load_lmrm", "load_lmrm_from",
           "save_lmrm"]
