"""LMRM: shapes and the inference interface, beta-NLL gradients, training determinism and resume, DDP under
torchrun (one CPU process, gloo), the shipped checkpoint and its basis check, and the shipped model beating the
mean-material baseline on a held-out synthetic object.

Training data here: 3 tiny synthetic objects (24 px, 2 spp, direct light) and the 'test' model preset, so the
file runs in about two minutes on one core.
"""

from __future__ import annotations

import copy
import json
import math
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import ENVMAPS, MESHES, REPO
from safetensors.torch import load_file

from neumatex_core.capture.tonemap import srgb_eotf
from neumatex_core.eval.metrics import psnr
from neumatex_core.fields import MaterialDecoder, Triplane
from neumatex_core.geometry.mesh import load_mesh
from neumatex_core.lmrm import LMRM, LMRMConfig, LMRMError, LMRMNet, LMRMPrediction, load_lmrm, load_lmrm_from
from neumatex_core.lmrm.data import Augment, LMRMDataset, load_synth_object
from neumatex_core.lmrm.inference import DEFAULT_RECORD, DEFAULT_WEIGHTS
from neumatex_core.lmrm.losses import MSE_FLOOR, beta_nll, object_weights
from neumatex_core.lmrm.model import IN_CHANNELS, RATIO_INPUT, RATIO_MAX, angle_bin, lift_binned, lift_to_planes
from neumatex_core.lmrm.train import TrainLMRMConfig, init_minutes, train_lmrm
from neumatex_core.materials.neural_basis import load_basis
from neumatex_core.synth import SynthConfig, generate

TINY = dict(resolution=24, spp=2, max_bounces=1, photos=0, relight_maps=0, workers=1, progress=False,
            meshes=str(MESHES), envmaps=str(ENVMAPS))  # fmt: skip


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("lmrm") / "train"
    result = generate(SynthConfig(out=str(out), n=3, split="train", seed=321, **TINY))  # type: ignore[arg-type]
    assert result.complete
    return out


def tiny_train(data: Path, out: Path, **kw) -> TrainLMRMConfig:
    base = TrainLMRMConfig(data=str(data), cache=str(data.parent / "cache"), out=str(out), preset="test", steps=4,
                           pbr_steps=2, batch_size=2, points=256, warmup=1, val_modulo=0, checkpoint_every=1,
                           threads=1, device="cpu")  # fmt: skip
    return replace(base, **kw)


# -- model and interface -----------------------------------------------------------------------------------
def test_lift_to_planes_means_points_into_their_texels():
    pts = torch.tensor([[-0.9, -0.9, -0.9], [-0.8, -0.95, 0.5], [0.9, 0.9, 0.9]])
    feats = torch.tensor([[1.0], [3.0], [5.0]])
    planes = lift_to_planes(feats, pts, 4)  # [3, 2F + 1, R, R]
    assert planes.shape == (3, 3, 4, 4)
    # XY plane: points 0 and 1 share texel (row 0, col 0): mean 2, mean square 5, count 2.
    assert planes[0, 0, 0, 0] == pytest.approx(2.0) and planes[0, 1, 0, 0] == pytest.approx(5.0)
    assert planes[0, 2, 0, 0] == pytest.approx(torch.log1p(torch.tensor(2.0)).item() / 5)
    assert planes[0, 0, 3, 3] == pytest.approx(5.0)
    assert planes[0, :, 1:3, 1:3].abs().sum() == 0  # nothing lands in the middle


def test_predict_shapes_and_interface(tiny_data):
    cfg = LMRMConfig.preset("test")
    torch.manual_seed(0)
    lmrm = LMRM(LMRMNet(cfg), {"basis_id": "x"})
    obj = load_synth_object(sorted(tiny_data.glob("train-*"))[0])
    mesh = load_mesh(obj.folder / "mesh.obj")
    pred = lmrm.predict(obj.rgb, obj.cameras, mesh, obj.envmap)
    assert isinstance(pred, LMRMPrediction) and isinstance(pred.material_decoder, MaterialDecoder)
    assert isinstance(pred.triplane, Triplane)
    assert pred.triplane.planes.shape == (3, cfg.triplane_channels, cfg.plane_resolution, cfg.plane_resolution)
    pts = obj.position[obj.mask][:100]
    rho, lat, log_var = pred.gbuffers(pts)
    assert rho.shape == (100, 3) and lat.shape == (100, 6) and log_var.shape == (100, 9)
    assert float(rho.detach().min()) >= 0 and float(rho.detach().max()) <= 1 and float(lat.detach().abs().max()) <= 1
    again_rho, again_lat = pred.material_decoder(pred.triplane.features(pts))
    assert torch.equal(again_rho, rho) and torch.equal(again_lat, lat)
    base, rough, metal = pred.pbr(pts)
    assert base.shape == (100, 3) and rough.shape == (100,) and metal.shape == (100,)
    # The triplane is optimisable (TTO), the decoders are frozen.
    assert pred.triplane.planes.requires_grad
    assert not any(p.requires_grad for p in pred.material_decoder.parameters())
    # Views of another size are resampled; without lighting the prediction still works.
    small = torch.nn.functional.interpolate(obj.rgb.permute(0, 3, 1, 2), size=(12, 12), mode="area")
    pred2 = lmrm.predict(small.permute(0, 2, 3, 1), [c.resized(12, 12) for c in obj.cameras], mesh, None)
    assert pred2.triplane.planes.shape == pred.triplane.planes.shape
    inputs = lmrm.prepare(obj.rgb, obj.cameras, mesh, None)
    assert inputs.inputs.shape == (23, IN_CHANNELS, cfg.view_resolution, cfg.view_resolution)
    with pytest.raises(LMRMError, match="cameras"):
        lmrm.predict(obj.rgb, obj.cameras[:5], mesh)
    with pytest.raises(LMRMError, match="unit sphere"):
        lmrm.predict(obj.rgb, obj.cameras, replace(mesh, vertices=mesh.vertices * 3))


def test_the_ratio_path_puts_the_lifted_shading_normalised_colour_into_the_triplane(tiny_data):
    # LMRMConfig.ratio_path: the triplane's first six channels are the per-texel mean and mean square of the
    # linear pixel over the diffuse lighting cue, computed here from the views without the network, whatever
    # its weights; the other channels are the U-Net's, and a record without the flag reads as the plain model.
    cfg = replace(LMRMConfig.preset("test"), triplane_channels=8, ratio_path=True)
    obj = load_synth_object(sorted(tiny_data.glob("train-*"))[0])
    mesh = load_mesh(obj.folder / "mesh.obj")
    planes = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        lmrm = LMRM(LMRMNet(cfg), {"basis_id": "x"})
        inputs = lmrm.prepare(obj.rgb, obj.cameras, mesh, obj.envmap)
        planes.append(lmrm.predict(obj.rgb, obj.cameras, mesh, obj.envmap).triplane.planes.detach())
    assert planes[0].shape == (3, 8, cfg.plane_resolution, cfg.plane_resolution)
    m = inputs.mask
    ratio = inputs.inputs.permute(0, 2, 3, 1)[m][:, RATIO_INPUT] * RATIO_MAX  # [P, 3] in [0, RATIO_MAX]
    pts = inputs.position[m]
    assert float(ratio.max()) > 0.1  # the views are lit: a colour reaches the path
    expected = lift_to_planes(ratio, pts, cfg.plane_resolution)[:, :6]
    torch.testing.assert_close(planes[0][:, :6], expected)
    torch.testing.assert_close(planes[1][:, :6], expected)  # not learnt: the same for other weights
    assert not torch.allclose(planes[0][:, 6:], planes[1][:, 6:])  # the U-Net's channels are
    # Without lighting the ratio input is zero, and so is the path.
    dark = LMRM(LMRMNet(cfg), {"basis_id": "x"}).predict(obj.rgb, obj.cameras, mesh, None)
    assert float(dark.triplane.planes.detach()[:, :6].abs().max()) == 0
    assert "ratio_path" not in LMRMConfig().to_dict()  # records of earlier models stay as they were
    assert LMRMConfig.from_dict(cfg.to_dict()) == cfg and LMRMConfig.from_dict(LMRMConfig().to_dict()) == LMRMConfig()
    with pytest.raises(ValueError, match="triplane_channels > 6"):
        replace(cfg, triplane_channels=6)


def test_lift_binned_by_angle_means_each_texels_points_per_viewing_angle():
    # Two points in one texel seen at n . v = 0.1 (grazing) and 0.9 (head-on), one alone in another; 3 bins.
    pts = torch.tensor([[-0.9, -0.9, -0.9], [-0.8, -0.95, 0.5], [0.9, 0.9, 0.9]])
    feats = torch.tensor([[1.0, 10.0], [3.0, 30.0], [5.0, 50.0]])
    planes = lift_binned(feats, pts, angle_bin(torch.tensor([0.1, 0.9, 0.5]), 3), 4, 3)  # [3, bins * (F + 1), R, R]
    assert planes.shape == (3, 9, 4, 4)
    one = torch.log1p(torch.tensor(1.0)).item() / 5
    xy = planes[0, :, 0, 0].reshape(3, 3)  # bins x (F features, count)
    torch.testing.assert_close(xy[0], torch.tensor([1.0, 10.0, one]))  # grazing: point 0
    torch.testing.assert_close(xy[1], torch.tensor([2.0, 20.0, 0.0]))  # no point: the texel's mean, count 0
    torch.testing.assert_close(xy[2], torch.tensor([3.0, 30.0, one]))  # head-on: point 1
    torch.testing.assert_close(planes[0, :, 3, 3].reshape(3, 3)[:, :2], torch.tensor([[5.0, 50.0]] * 3))
    assert planes[0, 8, 3, 3] == 0 and planes[0, 5, 3, 3] == pytest.approx(one)  # point 2 is in the middle bin
    # Weighted by their counts the bins give back the texel's plain mean (`lift_to_planes`).
    many = torch.rand(500, 3) * 2 - 1
    f, cos = torch.rand(500, 4), torch.rand(500)
    binned = lift_binned(f, many, angle_bin(cos, 2), 3, 2).reshape(3, 2, 5, 3, 3)
    counts = torch.expm1(binned[:, :, 4:] * 5)
    torch.testing.assert_close((binned[:, :, :4] * counts).sum(1) / counts.sum(1), lift_to_planes(f, many, 3)[:, :4])


def _widened_pair(source_cfg: LMRMConfig, target_cfg: LMRMConfig, tmp_path: Path) -> tuple[LMRMNet, LMRMNet, list[str]]:
    """A model of source_cfg (seed 0), saved, and a model of target_cfg (seed 1) started from it by `init_from`
    (`--init`): (source, target, the names of the target's tensors that grew)."""
    from safetensors.torch import save_file

    from neumatex_core.lmrm.train import init_from

    torch.manual_seed(0)
    source = LMRMNet(source_cfg)
    save_file({k: v.contiguous() for k, v in source.state_dict().items()}, str(tmp_path / "source.safetensors"))
    torch.manual_seed(1)
    target = LMRMNet(target_cfg)
    assert init_from(target, tmp_path / "source.safetensors") == len(source.state_dict())
    return source, target, sorted(k for k, v in target.state_dict().items() if v.shape != source.state_dict()[k].shape)


def test_a_model_widens_into_the_angle_bins_unchanged_and_then_learns_them(tiny_data, tmp_path):
    # `--init` from a model without angle bins: its layers that read the new channels start as before with zeros
    # there (`widened`), so the wider model predicts exactly what the plain one did; training then moves them.
    from neumatex_core.lmrm.losses import LossWeights, lmrm_loss
    from neumatex_core.lmrm.train import widened

    plain_cfg = replace(LMRMConfig.preset("test"), triplane_channels=8, ratio_path=True)
    wide_cfg = replace(plain_cfg, angle_bins=3)
    assert "angle_bins" not in plain_cfg.to_dict() and LMRMConfig.from_dict(wide_cfg.to_dict()) == wide_cfg
    plain, wide, grown = _widened_pair(plain_cfg, wide_cfg, tmp_path)
    assert grown == ["plane_net.enc1.0.0.weight", "plane_net.skip.weight"]
    n_new = 3 * (wide_cfg.feature_channels + 1)
    for k in grown:
        assert float(wide.state_dict()[k][:, -n_new:].abs().max()) == 0
    ds = LMRMDataset([tiny_data], tiny_data.parent / "cache")
    s = ds.sample(0, torch.Generator().manual_seed(0), Augment(), 256)
    with torch.no_grad():
        p_plain, (h_plain,) = plain([s.inputs], [s.points])
        p_wide, (h_wide,) = wide([s.inputs], [s.points])
    torch.testing.assert_close(p_wide, p_plain)
    torch.testing.assert_close(h_wide.latent, h_plain.latent)
    # The new channels carry signal and get a gradient: one Adam step makes them non-zero.
    opt = torch.optim.Adam(wide.parameters(), lr=1e-3)
    _, (heads,) = wide([s.inputs], [s.points])
    lmrm_loss(heads, s.targets, LossWeights(mat=1.0, unc=0.0, pbr=0.0))[0].backward()
    opt.step()
    assert float(wide.state_dict()["plane_net.skip.weight"][:, -n_new:].abs().max()) > 0
    # Only a gain in input channels widens: fewer channels or another output size are not copied.
    assert widened(torch.ones(4, 3), torch.zeros(5, 6)) is None
    assert widened(torch.ones(4, 6), torch.zeros(4, 3)) is None
    torch.testing.assert_close(widened(torch.ones(4, 3), torch.zeros(4, 5)), torch.cat([torch.ones(4, 3),
                                                                                        torch.zeros(4, 2)], 1))


def test_gloss_bins_sort_pixels_by_the_reflected_lights_brightness_and_widen_a_model_with_angle_bins(tiny_data,
                                                                                                        tmp_path):
    # `gloss_bin`: log(sharpest glossy cue / diffuse cue) against GLOSS_EDGES, read from view_inputs' squashed cues.
    from neumatex_core.lmrm.model import CUE_INPUT, GLOSS_EDGES, gloss_bin

    raw = torch.ones(3, CUE_INPUT.stop - CUE_INPUT.start)
    raw[:, 3:6] = torch.tensor([[0.2], [0.6], [1.2]])  # the sharp reflection at 0.2, 0.6, 1.2 times the diffuse light
    assert math.log(0.2) < GLOSS_EDGES[0] < math.log(0.6) < GLOSS_EDGES[1] < math.log(1.2)
    assert gloss_bin(raw / (1 + raw)).tolist() == [0, 1, 2]
    # A model with angle bins widens into one with gloss bins too, unchanged until trained.
    angle_cfg = replace(LMRMConfig.preset("test"), triplane_channels=8, ratio_path=True, angle_bins=2)
    both_cfg = replace(angle_cfg, gloss_bins=True)
    assert "gloss_bins" not in angle_cfg.to_dict() and LMRMConfig.from_dict(both_cfg.to_dict()) == both_cfg
    angle, both, _ = _widened_pair(angle_cfg, both_cfg, tmp_path)
    weight = both.state_dict()["plane_net.skip.weight"]
    assert weight.shape[1] - angle.state_dict()["plane_net.skip.weight"].shape[1] == 3 * (both_cfg.feature_channels + 1)
    ds = LMRMDataset([tiny_data], tiny_data.parent / "cache")
    samples = [ds.sample(i, torch.Generator().manual_seed(i), Augment.none(), 128) for i in range(2)]
    with torch.no_grad():
        torch.testing.assert_close(both([s.inputs for s in samples], [s.points for s in samples])[0],
                                   angle([s.inputs for s in samples], [s.points for s in samples])[0])


def test_ratio_bins_put_the_colours_own_binned_lift_last_in_the_triplane_and_widen_a_model_unchanged(tiny_data,
                                                                                                        tmp_path):
    # `ratio_bins`: the triplane's last channels are the shading-normalised colour lifted per angle bin (each bin's
    # mean RGB and log count), not learnt; a model without them widens into one with them (the decoders per plane).
    from neumatex_core.lmrm.model import RATIO_BIN_CHANNELS, RATIO_PATH_CHANNELS
    from neumatex_core.lmrm.train import widened

    angle_cfg = replace(LMRMConfig.preset("test"), triplane_channels=8, ratio_path=True, angle_bins=2)
    ratio_cfg = replace(angle_cfg, ratio_bins=True, triplane_channels=8 + 2 * RATIO_BIN_CHANNELS)
    assert "ratio_bins" not in angle_cfg.to_dict() and LMRMConfig.from_dict(ratio_cfg.to_dict()) == ratio_cfg
    with pytest.raises(ValueError, match="ratio_bins"):
        replace(angle_cfg, ratio_bins=True, angle_bins=0)
    with pytest.raises(ValueError, match="triplane_channels"):
        replace(angle_cfg, ratio_bins=True)  # 8 channels cannot hold 6 + 2 x 4 fixed ones
    angle, both, grown = _widened_pair(angle_cfg, ratio_cfg, tmp_path)
    assert grown == ["material_decoder.net.0.weight", "pbr_decoder.net.0.weight", "uncertainty_decoder.net.0.weight"]
    ds = LMRMDataset([tiny_data], tiny_data.parent / "cache")
    s = ds.sample(0, torch.Generator().manual_seed(0), Augment.none(), 128)
    with torch.no_grad():
        p_angle, (h_angle,) = angle([s.inputs], [s.points])
        p_both, (h_both,) = both([s.inputs], [s.points])
    torch.testing.assert_close(p_both[:, :, :8], p_angle)
    for name in ("rho_d", "latent", "log_var", "pbr"):
        torch.testing.assert_close(getattr(h_both, name), getattr(h_angle, name))
    # The new channels: the ratio input's lift per angle bin, as `lift_binned` makes it.
    obj, m = s.inputs, s.inputs.mask
    ratio = obj.inputs[:, RATIO_INPUT].permute(0, 2, 3, 1)[m] * RATIO_MAX
    cos_view = (obj.inputs[:, 4:7] * obj.inputs[:, 7:10]).sum(1)[m]
    expected = lift_binned(ratio, obj.position[m], angle_bin(cos_view, 2), ratio_cfg.plane_resolution, 2)
    torch.testing.assert_close(p_both[0, :, 8:], expected)
    assert p_both.shape[2] == RATIO_PATH_CHANNELS + 2 + 2 * RATIO_BIN_CHANNELS
    # `widened` by blocks: each plane's block grows at its own end.
    grown_by_plane = widened(torch.arange(6.0).reshape(1, 6), torch.zeros(1, 9), blocks=3)
    assert grown_by_plane is not None and grown_by_plane.tolist() == [[0, 1, 0, 2, 3, 0, 4, 5, 0]]
    assert widened(torch.ones(1, 4), torch.zeros(1, 9), blocks=3) is None


def test_pbr_gbuffer_channels_are_read_by_name(tmp_path):
    """OpenEXR sorts channels by name; the PBR G-buffer must come back as base rgb, roughness, metallic."""
    from neumatex_core.imageio import write_image
    from neumatex_core.lmrm.data import read_channels
    from neumatex_core.synth.writer import GBUFFER_CHANNELS

    names = GBUFFER_CHANNELS["pbr"]
    pixels = np.broadcast_to(np.arange(1, 6, dtype=np.float32), (2, 3, 5)).copy()
    write_image(tmp_path / "pbr.exr", pixels, names)
    assert read_channels(tmp_path / "pbr.exr", names)[0, 0].tolist() == [1, 2, 3, 4, 5]
    with pytest.raises(ValueError, match="missing"):
        read_channels(tmp_path / "pbr.exr", ("R", "G", "B"))


# -- losses ------------------------------------------------------------------------------------------------
def test_beta_nll_gradients():
    torch.manual_seed(0)
    mean = torch.randn(64, 9, requires_grad=True)
    target = torch.randn(64, 9)
    log_var = torch.randn(64, 9, requires_grad=True)
    per_channel = beta_nll(mean, log_var, target, beta=0.5)
    assert per_channel.shape == (9,)
    per_channel.sum().backward()
    # Stop-gradient on the mean: the NLL never moves the material prediction.
    assert mean.grad is None or float(mean.grad.abs().max()) == 0.0
    # d/dlv of var^beta (detached) * (lv + e^2 / var) / 2, averaged over the 64 points.
    var = log_var.detach().exp()
    e2 = (target - mean.detach()) ** 2
    expected = var**0.5 * 0.5 * (1 - e2 / var) / 64
    assert torch.allclose(log_var.grad, expected, rtol=1e-5, atol=1e-8)
    # Zero gradient exactly at the squared error; pushes towards it from either side.
    lv = torch.log(e2).clone().requires_grad_(True)
    beta_nll(mean.detach(), lv, target).sum().backward()
    assert float(lv.grad.abs().max()) < 1e-6
    for offset, sign in ((1.0, 1.0), (-1.0, -1.0)):
        lv2 = (torch.log(e2[:4, :1]) + offset).requires_grad_(True)
        beta_nll(mean.detach()[:4, :1], lv2, target[:4, :1]).sum().backward()
        assert bool((torch.sign(lv2.grad) == sign).all())
    # beta = 0 is the plain Gaussian NLL.
    lv3 = torch.zeros(5, 1, requires_grad=True)
    beta_nll(torch.zeros(5, 1), lv3, torch.full((5, 1), 2.0), beta=0.0).sum().backward()
    assert torch.allclose(lv3.grad, torch.full((5, 1), 0.5 * (1 - 4.0) / 5))


def test_object_weights_give_the_gradient_of_mean_log_mse():
    """The objects' MSEs weighted by object_weights move the model as mean log-MSE (mean PSNR over objects) does."""
    torch.manual_seed(1)
    target = torch.rand(3, 50)
    pred = (target + torch.randn(3, 50) * torch.tensor([[0.03], [0.1], [0.5]])).requires_grad_(True)  # 3 objects
    mse = ((pred - target) ** 2).mean(1)  # [3]
    w = object_weights(mse[:, None])[:, 0]
    assert w.requires_grad is False and abs(float(w.mean()) - 1.0) < 1e-6
    assert float(w[0]) > float(w[1]) > float(w[2])  # the object with the smallest error weighs most
    (grad_w,) = torch.autograd.grad((w * mse).sum(), pred, retain_graph=True)
    (grad_log,) = torch.autograd.grad(torch.log(mse).sum(), pred)
    scale = 1.0 / float((1.0 / mse.detach()).mean())  # the batch's common factor
    assert torch.allclose(grad_w, scale * grad_log, rtol=1e-5, atol=1e-9)
    # An MSE under the floor weighs as the floor; columns (rho_d, latent) are weighted separately.
    two = object_weights(torch.tensor([[1e-8, 0.2], [MSE_FLOOR, 0.1]]))
    assert torch.allclose(two[:, 0], torch.ones(2)) and torch.allclose(two[:, 1], torch.tensor([2 / 3, 4 / 3]))


# -- training ----------------------------------------------------------------------------------------------
def test_the_mean_material_baseline_pools_every_training_objects_pixels():
    # training_mean is the benchmark's mean-material baseline: the pixel-weighted mean target over every object,
    # not over a subsample (64 of 2352 objects moved it by up to 0.1 dB on the test split; docs/lmrm.md).
    from neumatex_core.lmrm.data import N_TARGETS, training_mean

    g = torch.Generator().manual_seed(0)
    objects = [{"targets": torch.rand(int(torch.randint(5, 50, (1,), generator=g)), N_TARGETS, generator=g) + i / 50}
               for i in range(100)]  # fmt: skip

    class Objects:  # the two things training_mean asks of an LMRMDataset
        def __len__(self) -> int:
            return len(objects)

        def load(self, i: int) -> dict[str, torch.Tensor]:
            return objects[i]

    pooled = torch.cat([o["targets"] for o in objects]).double().mean(0).float()
    assert torch.allclose(training_mean(Objects()), pooled, atol=1e-6)
    four_spread = torch.cat([o["targets"] for o in objects[::33]]).double().mean(0).float()  # objects 0, 33, 66, 99
    assert torch.allclose(training_mean(Objects(), limit=4), four_spread, atol=1e-6)


def test_training_is_deterministic_and_resumes_exactly(tiny_data, tmp_path):
    full = train_lmrm(tiny_train(tiny_data, tmp_path / "full"))
    assert full.finished and full.steps_done == 4
    cut = train_lmrm(tiny_train(tiny_data, tmp_path / "cut", max_minutes=1e-9))
    assert not cut.finished and cut.steps_done == 1
    # The compute is summed over resumes: say the cut run had taken ten minutes.
    state = torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=False)
    assert state["seconds"] > 0
    torch.save({**state, "seconds": 600.0}, tmp_path / "cut" / "checkpoint.pt")
    resumed = train_lmrm(tiny_train(tiny_data, tmp_path / "cut"))
    assert resumed.finished and resumed.steps_done == 4
    training = json.loads((tmp_path / "cut" / "lmrm.json").read_text())["training"]
    assert training["minutes"] - training["minutes_this_run"] == pytest.approx(10.0, abs=0.011)
    assert training["minutes_with_init"] == training["minutes"]  # no --init
    # ... and a run started from those weights adds their lineage.
    train_lmrm(tiny_train(tiny_data, tmp_path / "child", steps=1, pbr_steps=1,
                          init=str(tmp_path / "cut" / "lmrm.safetensors")))  # fmt: skip
    child = json.loads((tmp_path / "child" / "lmrm.json").read_text())["training"]
    assert child["minutes_with_init"] == pytest.approx(child["minutes"] + training["minutes_with_init"], abs=0.011)
    assert init_minutes("") == 0.0 and init_minutes(str(tmp_path / "nowhere.safetensors")) == 0.0
    old = tmp_path / "old" / "lmrm.safetensors"  # records before the field: their minutes, or their last part's
    old.parent.mkdir()
    for training, minutes in (({"minutes": 7.0, "minutes_this_run": 5.0}, 7.0), ({"minutes_this_run": 5.0}, 5.0)):
        old.with_suffix(".json").write_text(json.dumps({"training": training}))
        assert init_minutes(str(old)) == minutes
    a = load_file(str(tmp_path / "full" / "lmrm.safetensors"))
    b = load_file(str(tmp_path / "cut" / "lmrm.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    curves = json.loads((tmp_path / "full" / "curves.json").read_text())
    assert [r["stage"] for r in curves["train"]] == [1, 1, 2, 2]
    assert (tmp_path / "full" / "curves.png").stat().st_size > 1000
    rec = json.loads((tmp_path / "full" / "lmrm.json").read_text())
    assert rec["basis_id"] == load_basis().basis_id and len(rec["data"]["manifest_sha256"]) == 64
    assert torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=False)["step"] == 4
    # Augmented samples differ from the plain ones but stay consistent in size.
    ds = LMRMDataset([tiny_data], tiny_data.parent / "cache")
    s1 = ds.sample(0, torch.Generator().manual_seed(1), Augment(), 128)
    s2 = ds.sample(0, torch.Generator().manual_seed(1), Augment.none(), 128)
    assert s1.points.shape == s2.points.shape == (128, 3)
    assert s1.inputs.inputs.shape[0] >= 16 and s2.inputs.inputs.shape[0] == 23


def test_log_mse_training_weights_each_objects_errors_by_their_inverse(tiny_data, tmp_path):
    """--log-mse: the same model and samples, but each object's MSEs weighted by their inverse (mean 1), so the
    material loss is the harmonic mean of the objects' MSEs, below their plain mean, and training then differs."""
    plain = train_lmrm(tiny_train(tiny_data, tmp_path / "plain", steps=4, pbr_steps=2))
    logged = train_lmrm(tiny_train(tiny_data, tmp_path / "log", steps=4, pbr_steps=2, log_mse=True))
    assert plain.finished and logged.finished
    a = json.loads((tmp_path / "plain" / "curves.json").read_text())["train"]
    b = json.loads((tmp_path / "log" / "curves.json").read_text())["train"]
    assert a[:2] == b[:2]  # stage 1 (PBR targets only) is untouched
    first = a[2], b[2]  # the first neural step: same weights, same samples, so the same unweighted errors
    assert first[0]["mse_rho"] == first[1]["mse_rho"] and first[0]["mse_lat"] == first[1]["mse_lat"]
    assert first[1]["l_mat"] < first[0]["l_mat"] - 1e-6  # harmonic mean of two unequal MSEs < their mean
    wa = load_file(str(tmp_path / "plain" / "lmrm.safetensors"))
    wb = load_file(str(tmp_path / "log" / "lmrm.safetensors"))
    assert any(not torch.equal(wa[k], wb[k]) for k in wa)


def test_resident_objects_train_like_the_files_and_are_read_once(tiny_data, tmp_path, monkeypatch):
    """`resident` (the GPU script's data path) keeps each object in memory after its first read and makes the samples
    from there: the same weights as reading the cache files at every step, with each object read once although the
    object list is re-read at every epoch (4 steps of 2 of the tiny set's objects: several epochs)."""
    plain = tiny_train(tiny_data, tmp_path / "plain", steps=4, pbr_steps=1)
    train_lmrm(plain)
    reads: list[str] = []
    real_load = torch.load

    def counting_load(f, *a, **kw):
        reads.append(str(f))
        return real_load(f, *a, **kw)

    monkeypatch.setattr("neumatex_core.lmrm.data.torch.load", counting_load)
    resident = replace(plain, out=str(tmp_path / "resident"), resident=True)
    train_lmrm(resident)
    a = load_file(str(tmp_path / "plain" / "lmrm.safetensors"))
    b = load_file(str(tmp_path / "resident" / "lmrm.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    n_objects = len(LMRMDataset([tiny_data], tiny_data.parent / "cache"))
    data_reads = [r for r in reads if r.endswith(".pt") and "cache" in r]
    # each object: build_cache's check of the file once and its one read into the store (training_mean included)
    assert len(data_reads) <= 2 * n_objects < 4 * 2 * 2


def test_the_family_head_learns_each_points_family_and_a_run_can_start_from_another_presets_weights(tiny_data,
                                                                                                     tmp_path):
    # LMRMConfig.family_head: a fourth decoder's logits, trained by cross-entropy against the family of each
    # point's region (the cache's `family`, from gbuffers/NNN_region.exr and material.json).
    from neumatex_core.lmrm.losses import LossWeights, lmrm_loss
    from neumatex_core.lmrm.train import init_from
    from neumatex_core.materials.prior import FAMILIES

    ds = LMRMDataset([tiny_data], tiny_data.parent / "cache")
    data = ds.load(0)
    everything = ds.sample(0, torch.Generator().manual_seed(0), Augment.none(), 0)
    assert torch.equal(everything.family, data["family"].long())  # all pixels, in order, with their family
    families = [r["family"] for r in json.loads((ds.folders[0] / "material.json").read_text())["regions"]]
    assert {FAMILIES[int(f)] for f in everything.family.unique()} <= set(families)
    samples = [ds.sample(i, torch.Generator().manual_seed(i), Augment.none(), 512) for i in range(len(ds))]
    labels = torch.cat([s.family for s in samples])
    majority = float(labels.bincount().max()) / len(labels)
    assert majority < 0.9  # the tiny set holds several families: telling them apart is something to learn

    torch.manual_seed(0)
    cfg = replace(LMRMConfig.preset("test"), family_head=True)
    net = LMRMNet(cfg)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    weights = LossWeights(mat=1.0, unc=0.0, pbr=0.0, family=1.0)

    def accuracy() -> float:
        with torch.no_grad():
            _, heads = net([s.inputs for s in samples], [s.points for s in samples])
        return float((torch.cat([h.family for h in heads]).argmax(-1) == labels).float().mean())

    for _ in range(80):
        _, heads = net([s.inputs for s in samples], [s.points for s in samples])
        loss = sum(lmrm_loss(h, s.targets, weights, family=s.family)[0] for h, s in zip(heads, samples, strict=True))
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert accuracy() > majority + 0.5 * (1 - majority)  # at least half of what the majority guess gets wrong
    with pytest.raises(ValueError, match="family"):
        lmrm_loss(heads[0], samples[0].targets, weights)  # a head with logits needs the points' family
    assert "family_head" not in LMRMConfig().to_dict() and LMRMConfig.from_dict(cfg.to_dict()) == cfg

    # --init: a run of another preset starts from the matching tensors; the head the source lacks starts fresh.
    train_lmrm(tiny_train(tiny_data, tmp_path / "plain", steps=1, pbr_steps=1))
    source = load_file(str(tmp_path / "plain" / "lmrm.safetensors"))
    torch.manual_seed(1)
    fresh = LMRMNet(cfg)
    family_before = {k: v.clone() for k, v in fresh.state_dict().items() if k.startswith("family_decoder")}
    assert init_from(fresh, tmp_path / "plain" / "lmrm.safetensors") == len(source)
    state = fresh.state_dict()
    assert all(torch.equal(state[k], v) for k, v in source.items())
    assert family_before and all(torch.equal(state[k], v) for k, v in family_before.items())
    with pytest.raises(ValueError, match="cannot read"):
        init_from(fresh, tmp_path / "missing.safetensors")


def test_torchrun_one_process_matches_plain_training(tiny_data, tmp_path):
    plain = tiny_train(tiny_data, tmp_path / "plain", steps=2, pbr_steps=1)
    train_lmrm(plain)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MASTER_ADDR": "127.0.0.1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=1", "--master_port=29517",
           "-m", "neumatex_core.cli", "train-lmrm", "--data", str(tiny_data),
           "--cache", str(tiny_data.parent / "cache"), "--out", str(tmp_path / "ddp"), "--preset", "test",
           "--steps", "2", "--pbr-steps", "1", "--batch-size", "2",
           "--points", "256", "--warmup", "1", "--val-modulo", "0", "--device", "cpu"]  # fmt: skip
    run = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    rec = json.loads((tmp_path / "ddp" / "lmrm.json").read_text())
    assert rec["training"]["world_size"] == 1 and rec["metrics"]["steps"] == 2
    a = load_file(str(tmp_path / "plain" / "lmrm.safetensors"))
    b = load_file(str(tmp_path / "ddp" / "lmrm.safetensors"))
    assert all(torch.allclose(a[k], b[k], atol=1e-6) for k in a)


# -- the shipped checkpoint ----------------------------------------------------------------------------------
def test_shipped_checkpoint_loads_and_checks_the_basis(tmp_path):
    assert DEFAULT_WEIGHTS.stat().st_size < 20 * 2**20
    lmrm = load_lmrm()
    rec = lmrm.record
    assert rec["basis_id"] == load_basis().basis_id
    assert rec["config"] == LMRMConfig().to_dict()  # the shipped model is the default CPU configuration
    assert rec["data"]["objects"] >= 100 and len(rec["data"]["manifest_sha256"]) == 64
    other = copy.deepcopy(load_basis())
    other.basis_id = "nmx-basis-v0-000000000000"
    with pytest.raises(LMRMError, match="trained for neural basis"):
        load_lmrm_from(DEFAULT_WEIGHTS, DEFAULT_RECORD, basis=other)
    weights, record = tmp_path / "w.safetensors", tmp_path / "r.json"
    shutil.copy(DEFAULT_WEIGHTS, weights)
    record.write_text(json.dumps({**rec, "basis_id": "nmx-basis-v9-ffffffffffff"}))
    with pytest.raises(LMRMError, match="nmx-basis-v9"):
        load_lmrm_from(weights, record)
    record.write_text(json.dumps(rec))
    weights.write_bytes(weights.read_bytes()[:-8] + b"\0" * 8)
    with pytest.raises(LMRMError, match="SHA-256"):
        load_lmrm_from(weights, record)
    with pytest.raises(LMRMError, match="missing"):
        load_lmrm_from(tmp_path / "none.safetensors", record)


def test_shipped_model_beats_the_mean_material(tmp_path):
    """On 4 held-out objects (test split, seed 77), pooled over their covered pixels, the shipped LMRM beats the
    training-set mean material on base colour and latents, and the per-pixel image colour on base colour. On the
    40 benchmark objects the margins are +1.1 / +0.6 dB and +4.8 dB with a per-object spread of 3 / 1.6 / 3 dB
    (bench/lmrm.py), so one object cannot carry a margin; 4 pooled objects carry a positive one."""
    out = tmp_path / "held-out"
    cfg = SynthConfig(out=str(out), n=4, split="test", seed=77, **{**TINY, "resolution": 64, "spp": 8,
                                                                   "max_bounces": 3})  # type: ignore[arg-type]
    generate(cfg)
    lmrm = load_lmrm()
    mean = torch.tensor(lmrm.record["metrics"]["training_mean"])
    preds, truths, images = [], [], []
    for i in range(4):
        obj = load_synth_object(out / f"test-{i:06d}")
        pred = lmrm.predict(obj.rgb, obj.cameras, load_mesh(obj.folder / "mesh.obj"), obj.envmap)
        with torch.no_grad():
            rho, lat, _ = pred.gbuffers(obj.position[obj.mask])
        preds.append(torch.cat([rho, lat], -1))
        truths.append(obj.targets[obj.mask][:, :9])
        images.append(srgb_eotf(obj.rgb[obj.mask]))
    pred_all, truth, image_all = torch.cat(preds), torch.cat(truths), torch.cat(images)
    base_all = mean[:9].expand_as(truth)

    def db(a: torch.Tensor, b: torch.Tensor) -> float:
        return psnr(a[None, :, None], b[None, :, None])

    ours_rho, mean_rho = db(pred_all[:, :3], truth[:, :3]), db(base_all[:, :3], truth[:, :3])
    image_rho = db(image_all, truth[:, :3])
    ours_lat = db((pred_all[:, 3:] + 1) / 2, (truth[:, 3:] + 1) / 2)
    mean_lat = db((base_all[:, 3:] + 1) / 2, (truth[:, 3:] + 1) / 2)
    print(f"LMRM {ours_rho:.2f} / {ours_lat:.2f} dB, mean {mean_rho:.2f} / {mean_lat:.2f}, image {image_rho:.2f}")
    assert ours_rho > mean_rho, (ours_rho, mean_rho)
    assert ours_lat > mean_lat, (ours_lat, mean_lat)
    assert ours_rho > image_rho + 1.0, (ours_rho, image_rho)
