"""Shared test settings: where the shared meshes and environment maps live."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("NEUMATEX_SHARED", REPO.parent / "shared"))
MESHES = SHARED / "data" / "meshes"
ENVMAPS = SHARED / "data" / "envmaps"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The shared data folder (meshes/, envmaps/); tests that need it fail loudly when it is missing."""
    data = SHARED / "data"
    assert data.is_dir(), f"shared data not found at {data}; set NEUMATEX_SHARED"
    return data


@pytest.fixture(scope="module")
def one_thread():
    """One torch thread for a module's tests: torch's intra-op threads stall 10-70x when another process holds a
    core (bench/README.md), and these tests are small. Use with `pytestmark = pytest.mark.usefixtures("one_thread")`."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def example():  # -> tto_fixtures.Example
    """The bundled capture's TTO setup (tests/tto_fixtures.py `load_example`), once per module."""
    from tto_fixtures import load_example

    return load_example()


@pytest.fixture(scope="module")
def truth_prediction(example):  # -> LMRMPrediction
    """A prediction fitted to the example's ground truth (tests/tto_fixtures.py `gt_prediction`), once per module."""
    from tto_fixtures import gt_prediction

    return gt_prediction(example)
