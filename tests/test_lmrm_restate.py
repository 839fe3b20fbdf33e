"""One LMRM's prediction restated through another checkpoint's decoders (neumatex_core/lmrm/restate.py): the fit
reaches the predicting model's heads through the readout's decoders, leaves both untouched, and the pipeline's lmrm
stage stores the restated prediction when `lmrm_readout` is set (docs/design-notes.md item 97)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from tto_fixtures import EXAMPLE

from neumatex_core.fields.decoders import MaterialDecoder, PBRDecoder, UncertaintyDecoder
from neumatex_core.fields.triplane import Triplane
from neumatex_core.lmrm import LMRMConfig, LMRMNet, save_lmrm
from neumatex_core.lmrm.inference import LMRMPrediction
from neumatex_core.lmrm.restate import heads, restate
from neumatex_core.materials.neural_basis import load_basis
from neumatex_core.pipeline import ExtractConfig, load_prediction, run_stage

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def scaled_decoders(seed: int) -> tuple[MaterialDecoder, UncertaintyDecoder, PBRDecoder]:
    torch.manual_seed(seed)
    decoders = (MaterialDecoder(12, 16), UncertaintyDecoder(12, 16), PBRDecoder(12, 16))
    with torch.no_grad():  # outputs that vary over the features (at their initial scale they sit near 0.5)
        for d in decoders:
            for w in d.parameters():
                w.mul_(4.0)
    return decoders


def test_the_fit_reaches_the_predictions_heads_through_the_readouts_decoders_and_touches_neither() -> None:
    decoders = scaled_decoders(1)
    # the prediction: other planes read by the same decoders, so its heads are reachable exactly
    readout = LMRMPrediction(Triplane(channels=4, resolution=8, init_std=0.5), *decoders)
    prediction = LMRMPrediction(Triplane(channels=4, resolution=8, init_std=0.5), *decoders)
    before = {k: v.clone() for k, v in readout.pbr_decoder.state_dict().items()}
    planes_before = readout.triplane.planes.detach().clone()
    points = torch.rand(2048, 3, generator=torch.Generator().manual_seed(3)) * 1.6 - 0.8
    restated, err = restate(prediction, readout, points, steps=400, lr=0.05, batch=512)
    assert err["pbr_start"] > 0.01 and err["material_start"] > 0.01
    assert err["pbr_end"] < err["pbr_start"] / 20 and err["material_end"] < err["material_start"] / 20
    with torch.no_grad():
        got, want = heads(restated, restated.triplane, points), heads(prediction, prediction.triplane, points)
    assert got.shape == (2048, 14)  # PBR base colour, roughness, metallic, rho_d, latent on the [0, 1] scale
    assert float(((got - want) ** 2).mean()) == pytest.approx((5 * err["pbr_end"] + 9 * err["material_end"]) / 14)
    # the restated prediction reads through the readout's decoders, which the fit did not change
    assert restated.pbr_decoder is readout.pbr_decoder and restated.uncertainty_decoder is readout.uncertainty_decoder
    assert restated.material_decoder is readout.material_decoder
    assert all(torch.equal(before[k], v) for k, v in readout.pbr_decoder.state_dict().items())
    assert torch.equal(readout.triplane.planes, planes_before)  # the fit starts from a copy of the readout's planes
    assert not restated.triplane.planes.requires_grad


def test_a_readout_for_another_basis_is_refused() -> None:
    mat, unc, pbr = scaled_decoders(2)
    prediction = LMRMPrediction(Triplane(channels=4, resolution=8), mat, unc, pbr)
    readout = LMRMPrediction(Triplane(channels=4, resolution=8), mat.with_latent_dim(4), unc, pbr)
    with pytest.raises(ValueError, match="4 channels, the prediction's 6"):
        restate(prediction, readout, torch.zeros(8, 3), steps=1, lr=0.05, batch=4)


def tiny_checkpoint(folder: Path, seed: int) -> Path:
    """A small, untrained LMRM checkpoint whose outputs vary over the surface."""
    torch.manual_seed(seed)
    net = LMRMNet(LMRMConfig(view_resolution=32, view_channels=8, view_layers=1, feature_channels=8,
                             plane_resolution=16, plane_channels=8, triplane_channels=8, decoder_hidden=16))
    save_lmrm(net, folder / f"lmrm-{seed}.safetensors", folder / f"lmrm-{seed}.json", load_basis(), {"note": "test"})
    return folder / f"lmrm-{seed}.safetensors"


def test_the_lmrm_stage_stores_the_prediction_restated_through_the_readout(tmp_path) -> None:
    predictor, reader = tiny_checkpoint(tmp_path, 0), tiny_checkpoint(tmp_path, 1)

    def stage(work: Path, **kw: str) -> tuple[LMRMPrediction, dict]:
        cfg = ExtractConfig.preset("tiny", device="cpu", **{"lmrm_weights": str(predictor), **kw})
        for s in ("validate", "prepare_views", "lmrm"):
            run_stage(s, EXAMPLE, work, cfg)
        return load_prediction(work)

    own, own_record = stage(tmp_path / "own")
    restated, record = stage(tmp_path / "restated", lmrm_readout=str(reader))
    read, _ = stage(tmp_path / "read", lmrm_weights=str(reader))  # the readout's own prediction
    assert "restated" not in own_record["lmrm"]
    fit = record["lmrm"]["restated"]
    assert fit["readout"]["sha256"] != record["lmrm"]["sha256"] and fit["seconds"] > 0
    # two untrained models' decoders: the readout's reach the predictor's heads only in part (3.6 and 2.6-fold)
    assert fit["fit"]["material_end"] < fit["fit"]["material_start"] / 2
    assert fit["fit"]["pbr_end"] < fit["fit"]["pbr_start"] / 2
    # the stored decoders are the readout's; the stored planes are neither model's own prediction
    for kind in ("material_decoder", "uncertainty_decoder", "pbr_decoder"):
        got, want = getattr(restated, kind).state_dict(), getattr(read, kind).state_dict()
        assert all(torch.equal(got[k], want[k]) for k in want)
    assert not torch.equal(restated.triplane.planes, read.triplane.planes)
    points = torch.rand(512, 3, generator=torch.Generator().manual_seed(0)) * 1.2 - 0.6
    with torch.no_grad():
        to_own = float(((heads(restated, restated.triplane, points) - heads(own, own.triplane, points)) ** 2).mean())
        read_own = float(((heads(read, read.triplane, points) - heads(own, own.triplane, points)) ** 2).mean())
    assert to_own < read_own / 1.5  # nearer what the predictor's decoders give than the readout's prediction (2.2x)
