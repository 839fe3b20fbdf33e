"""Test-time optimisation with uncertainty-guided regularisation (docs/architecture.md section 6, paper eq. 9-11).

- `config.py`: `TTOConfig` (presets tiny / cpu / gpu; switches field, init, reg, material);
- `data.py`: `PhotoSet` (random foreground pixel batches of the photos);
- `loss.py`: photometric L2 after the tonemap, the weighted anchor (`Anchor`, uncertainty and oracle weights);
- `params.py`: what is optimised per variant (triplane or UV textures; neural or PBR);
- `optimise.py`: `build_problem` and `optimise` (Adam, checkpoints, cooperative stop, resume; the cached light
  transport estimator);
- `pbr_start.py`: `solve`, any variant end to end, including init="pbr" (PBR TTO, then neural from its solution).
"""

from neumatex_core.tto.config import TTOConfig
from neumatex_core.tto.data import PhotoSet
from neumatex_core.tto.loss import Anchor, oracle_weights, photometric_loss, uncertainty_weights
from neumatex_core.tto.optimise import TTOProblem, TTOResult, build_problem, optimise
from neumatex_core.tto.pbr_start import solve

__all__ = ["Anchor", "PhotoSet", "TTOConfig", "TTOProblem", "TTOResult", "build_problem", "optimise",
           "oracle_weights", "photometric_loss", "solve", "uncertainty_weights"]
