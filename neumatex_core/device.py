"""Device choice, written once: CUDA when present, else CPU. All core code is device-agnostic."""

from __future__ import annotations

import torch


def default_device() -> torch.device:
    """The device new tensors go to unless a caller says otherwise."""
    return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")


def resolve_device(name: str = "auto") -> torch.device:
    """The torch device a config names: "auto" is `default_device()`, anything else ("cpu", "cuda", "cuda:1") as
    given."""
    return default_device() if name == "auto" else torch.device(name)
