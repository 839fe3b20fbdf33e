"""Job configuration: a pipeline preset ("tiny", "cpu", "gpu") plus overrides of ExtractConfig fields, with TTO
fields under "tto". Checked when the job is created, so a bad config is a 422 and never a failed job."""

from __future__ import annotations

from dataclasses import fields, replace
from typing import Any

from neumatex_core.pipeline import ExtractConfig

PRESETS = ("tiny", "cpu", "gpu")
NOT_OVERRIDABLE = {"preset_name", "lmrm_weights", "tto"}  # lmrm_weights would read a server path


def build_config(preset: str, overrides: dict[str, Any]) -> ExtractConfig:
    """ValueError in plain words for an unknown preset, field or bad value."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r} (expected one of {', '.join(PRESETS)})")
    top = {k: v for k, v in overrides.items() if k != "tto"}
    allowed = {f.name for f in fields(ExtractConfig)} - NOT_OVERRIDABLE
    unknown = sorted(set(top) - allowed)
    if unknown:
        raise ValueError(f"unknown or fixed config field(s) {unknown}; allowed: {sorted(allowed)} and 'tto'")
    tto_over = overrides.get("tto", {}) or {}
    if not isinstance(tto_over, dict):
        raise ValueError("config 'tto' must be an object of TTO fields")
    cfg = ExtractConfig.preset(preset, **top)
    tto_names = {f.name for f in fields(cfg.tto)}
    unknown = sorted(set(tto_over) - tto_names)
    if unknown:
        raise ValueError(f"unknown TTO field(s) {unknown}; allowed: {sorted(tto_names)}")
    cfg = replace(cfg, tto=replace(cfg.tto, **tto_over))
    for name, value in top.items():
        kind = type(getattr(ExtractConfig.preset(preset), name))
        if kind in (int, float) and not isinstance(value, int | float) or kind is str and not isinstance(value, str):
            raise ValueError(f"config field {name!r} must be a {kind.__name__}, got {value!r}")
    if cfg.init not in ("lmrm", "random", "pbr"):
        raise ValueError(f"config init must be 'lmrm', 'random' or 'pbr', got {cfg.init!r}")
    if cfg.device not in ("auto", "cpu", "cuda"):
        raise ValueError(f"config device must be 'auto', 'cpu' or 'cuda', got {cfg.device!r}")
    cfg.tto.check()
    return cfg


def default_queue(preset: str) -> str:
    return "gpu" if preset == "gpu" else "cpu"
