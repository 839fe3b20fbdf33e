"""Default torch device: CUDA when present, else CPU. All core code is device-agnostic."""

from __future__ import annotations

import torch


def default_device() -> torch.device:
    """The device new tensors go to unless a caller says otherwise."""
    return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
