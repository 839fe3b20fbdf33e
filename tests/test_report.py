"""The extraction report: built for a tiny extraction, every image it references exists and is not a blank panel."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from tto_fixtures import EXAMPLE

from neumatex_core.lmrm import LMRMConfig, LMRMNet, save_lmrm
from neumatex_core.materials.neural_basis import load_basis
from neumatex_core.pipeline import ExtractConfig, extract
from neumatex_core.report_images import colour_bar, scalar_map

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def untrained_lmrm(folder: Path) -> Path:
    """A small untrained LMRM checkpoint: the report then has the LMRM's prediction and uncertainty panels."""
    import torch

    torch.manual_seed(0)
    net = LMRMNet(LMRMConfig(view_resolution=32, view_channels=8, view_layers=1, feature_channels=8,
                             plane_resolution=16, plane_channels=8, triplane_channels=8, decoder_hidden=16))
    save_lmrm(net, folder / "lmrm.safetensors", folder / "lmrm.json", load_basis(), {"note": "test"})
    return folder / "lmrm.safetensors"


def test_scalar_map_spans_the_colour_scale_even_for_a_narrow_range():
    values = 0.02 + 0.001 * np.arange(64, dtype=np.float32).reshape(8, 8)  # all inside [0.02, 0.083]: once white
    mask = np.ones((8, 8), bool)
    img, lo, hi = scalar_map(values, mask)
    assert lo == pytest.approx(0.02, abs=2e-3) and hi == pytest.approx(0.083, abs=2e-3)
    assert img.min() < 0.1 and img.max() > 0.9  # dark and bright ends both used
    assert np.ptp(colour_bar(32, 32), axis=(0, 1)).max() > 0.5


def test_report_of_a_tiny_extraction_has_no_blank_panels(tmp_path):
    cfg = ExtractConfig.preset("tiny", lmrm_weights=str(untrained_lmrm(tmp_path)), device="cpu")
    out = extract(EXAMPLE, tmp_path / "asset", cfg, None, None, tmp_path / "work")
    folder = out / "report"
    page = (folder / "index.html").read_text()
    assert page.startswith("<!doctype html>") and "Ran: preset tiny" in page
    assert "dB vs PBR" in page and "PBR fallback" in page and "std colour scale" in page and "relit under" in page
    sources = re.findall(r"<img src='([^']+)'", page)
    assert "curves.png" in sources and len(sources) >= 10
    for src in sources:
        path = folder / src
        assert path.is_file(), src
        pixels = np.asarray(Image.open(path).convert("RGB"), dtype=np.int16)
        spread = int(pixels.max()) - int(pixels.min())
        assert spread > 40, f"{src} is nearly uniform (values {pixels.min()}-{pixels.max()})"


def test_the_demo_example_is_a_clean_capture_with_preset_views_and_photos() -> None:
    """examples/coat-teapot (what `make demo` extracts): valid, 23 preset views and random-pose photos of >= 256 px,
    the ground-truth regions a clear coat next to a near-diffuse one (examples/README.md)."""
    import json

    from neumatex_core.capture import load_capture
    from neumatex_core.capture.validate import validate_capture

    demo = EXAMPLE.parent / "coat-teapot"
    assert validate_capture(demo) == [] and validate_capture(demo / "photos") == []
    cap, photos = load_capture(demo), load_capture(demo / "photos")
    assert len(cap.frames) == 23 and len(photos.frames) >= 6
    assert min(cap.load_image(0).shape[:2]) >= 256 and min(photos.load_image(0).shape[:2]) >= 256
    meta = json.loads((demo / "meta.json").read_text())
    assert meta["content"]["spp"] >= 256
    regions = json.loads((demo / "material.json").read_text())["regions"]
    assert {r["family"] for r in regions} == {"coated", "dusty"}
    assert max(r["params"]["coat_weight"] for r in regions) > 0.5
