"""Metrics and the benchmark harness (paper tables).

- `metrics.py`: PSNR over covered pixels; `gbuffers.py`: a synthetic object's ground-truth G-buffers,
  PSNR_BaseColor / PSNR_Latents, the oracle's truth lookup; `variants.py`: the TTO variants of the paper's tables;
  `suite.py`: `neumatex eval` (tables, orderings, results page); `plots.py`: its paired-difference chart.
"""

from neumatex_core.eval.gbuffers import GroundTruth, gbuffer_psnr, ground_truth, truth_lookup
from neumatex_core.eval.metrics import masked_mse, psnr
from neumatex_core.eval.variants import TABLES, VARIANTS, variant_config

__all__ = ["TABLES", "VARIANTS", "GroundTruth", "gbuffer_psnr", "ground_truth", "masked_mse", "psnr", "truth_lookup",
           "variant_config"]
