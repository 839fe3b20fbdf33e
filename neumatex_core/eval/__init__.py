"""Metrics and the benchmark harness (paper tables)."""

from neumatex_core.eval.metrics import masked_mse, psnr

__all__ = ["masked_mse", "psnr"]
