"""LMRM training (`neumatex train-lmrm`, docs/architecture.md section 5).

- Two-stage curriculum: steps < `pbr_steps` train on PBR targets through the PBR head only; later steps train
  L_mat + lambda_unc beta-NLL (+ `lambda_pbr` L_pbr, so the PBR head stays usable) (losses.py).
- Adam with linear warm-up and cosine decay, gradient clipping; an exponential moving average (EMA) of the
  weights is what validation reads and what ships (small batches of whole objects make the raw weights jumpy).
- Data: the finished objects of the `data` folders, cached on first use (data.py); the object list is re-read at
  every epoch, so training can start while `neumatex synth` is still adding objects. Objects whose index is
  `val_modulo - 1` modulo `val_modulo` are held out for validation.
- Every step's randomness derives from (seed, step, rank), and a checkpoint holds the model, the optimiser, the
  epoch's object order and the history, so a resumed run continues exactly like an uninterrupted one.
- Checkpoint `out/checkpoint.pt` every `checkpoint_every` steps and at the end (or at `max_minutes`);
  `out/curves.json` and `out/curves.png`; the final weights `out/lmrm.safetensors` + `out/lmrm.json`, copied
  into the package with `--install`. The record's "training" says the compute used (issue 14 asks for it next to
  every shipped checkpoint): wall-clock minutes of this run, of all runs into this `out` (resumes summed; the
  checkpoint keeps the seconds) and with the `--init` weights' own lineage added (`init_minutes`).
- Multi-GPU / multi-process: run under torchrun; each rank takes its share of every global batch and
  DistributedDataParallel averages the gradients (gloo on CPU, NCCL on CUDA). Only rank 0 writes files.
"""

from __future__ import annotations

import functools
import json
import math
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from neumatex_core.config import option
from neumatex_core.eval.metrics import psnr
from neumatex_core.fields.triplane import PLANE_AXES
from neumatex_core.lmrm.data import Augment, LMRMDataset, Sample, make_sample, training_mean
from neumatex_core.lmrm.inference import DATA_DIR, save_lmrm
from neumatex_core.lmrm.losses import LossWeights, family_accuracy, lmrm_loss, material_mse, object_weights
from neumatex_core.lmrm.model import LMRMConfig, LMRMNet, LMRMPreset
from neumatex_core.lmrm.plots import line_chart
from neumatex_core.materials.neural_basis import load_basis


@dataclass
class TrainLMRMConfig:
    """`neumatex train-lmrm`: train (or resume) the LMRM on synthetic objects (`neumatex synth` folders); writes
    checkpoints, loss curves and the final weights; --install ships them in the package."""

    data: str = option("data/synth-train", "comma-separated synth output folders")
    cache: str = option("data/lmrm-cache", "folder for the per-object tensor cache")
    out: str = option("runs/lmrm/train", "output folder: checkpoint, curves, final weights")
    preset: LMRMPreset = option("cpu", "model size (LMRMConfig.preset)")
    steps: int = option(560, "optimisation steps in total")
    pbr_steps: int = option(100, "steps of stage 1 (PBR targets through the PBR head) before the neural stage")
    batch_size: int = option(4, "objects per step and process")
    points: int = option(2048, "supervised surface points per object and step")
    lr: float = option(1e-3, "peak learning rate (Adam)")
    warmup: int = option(30, "linear warm-up steps")
    ema: float = option(0.98, "decay of the exponential moving average of the weights (evaluated and shipped)")
    lambda_unc: float = option(0.1, "weight of the beta-NLL uncertainty loss")
    lambda_pbr: float = option(0.1, "weight of the PBR loss in the neural stage")
    lambda_family: float = option(0.1, "weight of the family head's cross-entropy in the neural stage (models with a "
                                       "family head, e.g. --preset cpu-family)")
    init: str = option("", "start a new run from these weights (an lmrm.safetensors): tensors of the same name and "
                           "shape are copied, heads the model adds start fresh (a checkpoint in --out still resumes)")
    log_mse: bool = option(False, "weight each object's material MSEs by their inverse (mean 1 over the batch): "
                                  "training follows mean PSNR over objects, the metric, not the pooled MSE")
    beta: float = option(0.5, "beta of the beta-NLL")
    clip: float = option(1.0, "gradient norm clipping")
    seed: int = option(0, "seed of initialisation, data order and augmentation")
    augment: bool = option(True, "random rotation about +Y, exposure, view dropout, hidden lighting")
    val_modulo: int = option(50, "hold out objects whose index is val_modulo-1 mod val_modulo (0: none)")
    val_objects: int = option(8, "validation objects evaluated (at most)")
    val_every: int = option(50, "validate every this many steps")
    checkpoint_every: int = option(25, "write the checkpoint every this many steps")
    max_minutes: float = option(0.0, "stop (with a checkpoint) after this many minutes; 0: no limit")
    threads: int = option(1, "torch intra-op threads (CPU)")
    device: Literal["auto", "cpu", "cuda"] = option("auto", "torch device")
    resident: bool = option(False, "keep every object on the training device after its first use and make the "
                                   "samples there (a GPU holds thousands; the samples are the same)")
    resume: bool = option(True, "continue from out/checkpoint.pt when it exists")
    install: bool = option(False, "copy the final weights into neumatex_core/lmrm/data/ (the shipped model)")


@dataclass
class TrainResult:
    steps_done: int
    finished: bool
    metrics: dict[str, Any]
    out: Path


def _is_val(name: str, modulo: int) -> bool:
    if modulo <= 0:
        return False
    try:
        return int(name.rsplit("-", 1)[-1]) % modulo == modulo - 1
    except ValueError:
        return False


def _dist() -> tuple[int, int, bool]:
    """(rank, world size, whether we initialised the process group): torchrun sets WORLD_SIZE and RANK."""
    if "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) >= 1 and "RANK" in os.environ:
        owned = not dist.is_initialized()
        if owned:
            dist.init_process_group(backend="nccl" if torch.cuda.is_available() else "gloo")
        return dist.get_rank(), dist.get_world_size(), owned
    return 0, 1, False


def _lr(cfg: TrainLMRMConfig, step: int) -> float:
    if step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    t = (step - cfg.warmup) / max(cfg.steps - cfg.warmup, 1)
    return cfg.lr * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(t, 1.0))))


def _weights(cfg: TrainLMRMConfig, step: int) -> LossWeights:
    if step < cfg.pbr_steps:
        return LossWeights(mat=0.0, unc=0.0, pbr=1.0)
    return LossWeights(mat=1.0, unc=cfg.lambda_unc, pbr=cfg.lambda_pbr, family=cfg.lambda_family)


def _generator(seed: int, *keys: int) -> torch.Generator:
    value = seed
    for k in keys:
        value = (value * 1_000_003 + k) % (2**62)
    return torch.Generator().manual_seed(value)


class _Order:
    """The object order of the current epoch (ids), re-read from the data folders at each new epoch."""

    def __init__(self, cfg: TrainLMRMConfig, roots: list[Path], cache: Path, device: torch.device) -> None:
        self.cfg, self.roots, self.cache, self.device = cfg, roots, cache, device
        self.resident: dict[str, dict[str, Any]] | None = {} if cfg.resident else None
        self.epoch, self.pos = -1, 0
        self.ids: list[str] = []
        self.dataset = self._scan()

    def _scan(self) -> LMRMDataset:
        ds = LMRMDataset(self.roots, self.cache, resident=self.resident, device=self.device)
        ds.folders = [f for f in ds.folders if not _is_val(f.name, self.cfg.val_modulo)]
        if not ds.folders:
            raise ValueError(f"{', '.join(map(str, self.roots))}: no finished training objects "
                             "(make them with `neumatex synth`)")  # fmt: skip
        return ds

    def state(self) -> dict[str, Any]:
        return {"epoch": self.epoch, "ids": self.ids, "pos": self.pos}

    def load_state(self, state: dict[str, Any]) -> None:
        self.epoch, self.ids, self.pos = int(state["epoch"]), list(state["ids"]), int(state["pos"])
        self.dataset = self._scan()
        missing = sorted(set(self.ids) - set(self.dataset.ids))
        if missing:
            raise ValueError(f"checkpoint's epoch uses objects no longer in the data folders: {missing[:5]}")

    def take(self, n: int) -> list[int]:
        """Indices into self.dataset of the next n objects."""
        if self.pos + n > len(self.ids):
            self.dataset = self._scan()
            self.epoch += 1
            perm = torch.randperm(len(self.dataset), generator=_generator(self.cfg.seed, 7, self.epoch))
            self.ids = [self.dataset.ids[int(i)] for i in perm]
            self.pos = 0
            if n > len(self.ids):
                raise ValueError(f"batch of {n} objects but only {len(self.ids)} training objects")
        index = {name: i for i, name in enumerate(self.dataset.ids)}
        picked = [index[name] for name in self.ids[self.pos:self.pos + n]]
        self.pos += n
        return picked


def widened(source: torch.Tensor, target: torch.Tensor, blocks: int = 1) -> torch.Tensor | None:
    """`source` as a tensor of `target`'s shape when the two differ only by `target` having more input channels
    (dim 1, e.g. a convolution's weight [out, in, k, k] given `angle_bins`' channels): its leading channels copied,
    the new ones zero, so the widened layer computes what `source` did until training moves it; else None. With
    `blocks`, the input is that many equal blocks (a decoder's [3 planes x C] triplane features given `ratio_bins`'
    channels) and each block grows at its end."""
    if (source.dim() < 2 or source.dim() != target.dim() or source.shape[1] >= target.shape[1]
            or source.shape[1] % blocks or target.shape[1] % blocks
            or source.shape[:1] + source.shape[2:] != target.shape[:1] + target.shape[2:]):  # fmt: skip
        return None
    out = torch.zeros_like(target)
    old, new = source.shape[1] // blocks, target.shape[1] // blocks
    for b in range(blocks):
        out[:, b * new: b * new + old] = source[:, b * old: (b + 1) * old].to(target.dtype)
    return out


def init_from(net: LMRMNet, weights: Path) -> int:
    """Copy into `net` the tensors of the LMRM weights file whose name and shape match (another preset's model: a
    head it lacks keeps its fresh initialisation), and those that `widened` fits (a layer reading new input channels
    starts as the old one, zero on the new channels, a decoder's per plane); returns how many were copied. Raises
    ValueError naming the file when it cannot be read or shares no tensor with `net`."""
    from safetensors.torch import load_file

    try:
        source = load_file(str(weights))
    except (OSError, RuntimeError, ValueError) as exc:
        raise ValueError(f"{weights}: cannot read LMRM weights to start from ({exc})") from None
    state = net.state_dict()
    matching = {k: v for k, v in source.items() if k in state and state[k].shape == v.shape}
    for k, v in source.items():
        blocks = len(PLANE_AXES) if k.split(".")[0].endswith("_decoder") else 1  # decoders read [3 planes x C]
        if k in state and k not in matching and (grown := widened(v, state[k], blocks)) is not None:
            matching[k] = grown
    if not matching:
        raise ValueError(f"{weights}: no tensor matches this model's names and shapes (another model size?)")
    net.load_state_dict(matching, strict=False)  # copies into the existing tensors (their device and dtype)
    return len(matching)


def init_minutes(weights: str) -> float:
    """Wall-clock training minutes behind the `--init` weights (0 without): their record's (lmrm.json beside them)
    "minutes_with_init", else its "minutes", else its "minutes_this_run" (records before 2026-12-07 count only the
    last resumed part), else 0 when there is no readable record."""
    if not weights:
        return 0.0
    try:
        training = json.loads(Path(weights).with_suffix(".json").read_text()).get("training", {})
    except (OSError, ValueError):
        return 0.0
    for key in ("minutes_with_init", "minutes", "minutes_this_run"):
        if isinstance(training.get(key), int | float):
            return float(training[key])
    return 0.0


def _to(sample: Sample, device: torch.device) -> Sample:
    s = sample
    s.inputs.inputs, s.inputs.mask = s.inputs.inputs.to(device), s.inputs.mask.to(device)
    s.inputs.position = s.inputs.position.to(device)
    s.points, s.targets, s.family = s.points.to(device), s.targets.to(device), s.family.to(device)
    return s


@torch.no_grad()
def evaluate(net: LMRMNet, dataset: LMRMDataset, device: torch.device, mean: torch.Tensor | None = None
             ) -> dict[str, float]:
    """Mean PSNR_BaseColor / PSNR_Latents ((l+1)/2) over the covered pixels of each object's cached views, and the
    same for the constant `mean` material [14] when given; with a family head, the share of pixels whose family it
    names right."""
    was_training = net.training
    net.eval()
    rows: dict[str, list[float]] = {"psnr_basecolor": [], "psnr_latents": [], "mean_psnr_basecolor": [],
                                    "mean_psnr_latents": []}  # fmt: skip
    for i in range(len(dataset)):
        s = _to(make_sample(dataset.load(i), torch.Generator().manual_seed(0), Augment.none(), 0), device)
        _, (heads,) = net([s.inputs], [s.points])
        t = s.targets
        rows["psnr_basecolor"].append(psnr(heads.rho_d[None], t[None, :, :3]))
        rows["psnr_latents"].append(psnr((heads.latent[None] + 1) / 2, (t[None, :, 3:9] + 1) / 2))
        if heads.family is not None:
            rows.setdefault("family_accuracy", []).append(float(family_accuracy(heads.family, s.family)))
        if mean is not None:
            m = mean.to(device).expand_as(t)
            rows["mean_psnr_basecolor"].append(psnr(m[None, :, :3], t[None, :, :3]))
            rows["mean_psnr_latents"].append(psnr((m[None, :, 3:9] + 1) / 2, (t[None, :, 3:9] + 1) / 2))
    net.train(was_training)
    return {k: float(sum(v) / len(v)) for k, v in rows.items() if v}


def write_curves(history: list[dict[str, Any]], validation: list[dict[str, Any]], out: Path) -> None:
    """curves.json (every logged step and validation) and curves.png (losses; validation PSNR)."""
    (out / "curves.json").write_text(json.dumps({"train": history, "validation": validation}) + "\n")
    if not history:
        return

    def smooth(key: str, stage: int) -> tuple[list[float], list[float]]:
        rows = [h for h in history if h["stage"] == stage]
        xs, ys, k = [], [], 25
        for j in range(0, len(rows), k):
            chunk = rows[j:j + k]
            xs.append(float(chunk[-1]["step"]))
            ys.append(sum(float(c[key]) for c in chunk) / len(chunk))
        return xs, ys

    panels: list[tuple[str, dict[str, tuple[Any, Any]], bool]] = [
        ("training losses (mean of 25 steps)", {"stage 1 L_pbr": smooth("l_pbr", 1), "L_pbr": smooth("l_pbr", 2),
                                                 "MSE rho_d": smooth("mse_rho", 2),
                                                 "MSE (l+1)/2": smooth("mse_lat", 2)}, True),
        ("beta-NLL (stage 2)", {"beta-NLL": smooth("nll", 2)}, False),
    ]  # fmt: skip
    if validation:
        xs = [float(v["step"]) for v in validation]
        series: dict[str, tuple[Any, Any]] = {k: (xs, [float(v[k]) for v in validation]) for k in
                  ("psnr_basecolor", "psnr_latents", "mean_psnr_basecolor", "mean_psnr_latents") if k in validation[0]}
        panels.append(("validation PSNR (dB): LMRM vs mean material", series, False))
    line_chart(panels, out / "curves.png")


def train_lmrm(cfg: TrainLMRMConfig, progress: Callable[[int, int, dict[str, float]], None] | None = None
               ) -> TrainResult:
    """Train (or resume) the LMRM as configured; see the module docstring."""
    rank, world, owned = _dist()
    if cfg.device == "auto":
        device = torch.device(f"cuda:{rank % torch.cuda.device_count()}" if torch.cuda.is_available() else "cpu")
    else:
        device = torch.device(cfg.device)
    if device.type == "cpu":
        torch.set_num_threads(cfg.threads)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    roots = [Path(p) for p in cfg.data.split(",") if p.strip()]
    cache = Path(cfg.cache)
    model_cfg = LMRMConfig.preset(cfg.preset)
    torch.manual_seed(cfg.seed)
    net = LMRMNet(model_cfg).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    ema = LMRMNet(model_cfg).to(device)
    ema.load_state_dict(net.state_dict())
    ema.requires_grad_(False)
    order = _Order(cfg, roots, cache, device)
    history: list[dict[str, Any]] = []
    validation: list[dict[str, Any]] = []
    step = 0
    seconds_before = 0.0  # wall-clock seconds of the earlier runs into this checkpoint (resumes)
    ckpt = out / "checkpoint.pt"
    if cfg.init:
        copied = init_from(net, Path(cfg.init))
        ema.load_state_dict(net.state_dict())
        if rank == 0:
            print(f"initialised {copied} of {len(net.state_dict())} tensors from {cfg.init}")
    if cfg.resume and ckpt.is_file():
        state = torch.load(ckpt, map_location=device, weights_only=False)
        if state["model_config"] != model_cfg.to_dict():
            raise ValueError(f"{ckpt}: made with another model config ({state['model_config']}); use a new --out")
        net.load_state_dict(state["model"])
        ema.load_state_dict(state["ema"])
        opt.load_state_dict(state["optimizer"])
        order.load_state(state["order"])
        history, validation, step = state["history"], state["validation"], int(state["step"])
        seconds_before = float(state.get("seconds", 0.0))
    model: torch.nn.Module = net
    if world > 1 or dist.is_initialized():
        model = DistributedDataParallel(net, device_ids=[device.index] if device.type == "cuda" else None)
    def validation_set() -> LMRMDataset:  # re-read each time: objects may still be arriving
        ds = LMRMDataset(roots, cache)
        ds.folders = [f for f in ds.folders if _is_val(f.name, cfg.val_modulo)][:cfg.val_objects]
        return ds

    val_set = validation_set()

    @functools.cache
    def mean_material() -> torch.Tensor:
        """[14] training_mean, computed at first need (a pass over every object, so not at start-up), then reused."""
        return training_mean(order.dataset)

    augment = Augment() if cfg.augment else Augment.none()
    started = time.monotonic()

    def seconds_so_far() -> float:
        return seconds_before + time.monotonic() - started

    def save_checkpoint() -> None:
        if rank != 0:
            return
        state = {"model": net.state_dict(), "ema": ema.state_dict(), "optimizer": opt.state_dict(),
                 "order": order.state(), "step": step, "seconds": seconds_so_far(),
                 "history": history, "validation": validation, "model_config": model_cfg.to_dict(),
                 "train_config": asdict(cfg)}  # fmt: skip
        tmp = ckpt.with_suffix(".tmp")
        torch.save(state, tmp)
        tmp.replace(ckpt)
        write_curves(history, validation, out)

    net.train()
    stopped_early = False
    while step < cfg.steps:
        global_batch = order.take(cfg.batch_size * world)
        mine = global_batch[rank * cfg.batch_size:(rank + 1) * cfg.batch_size]
        samples = [_to(order.dataset.sample(i, _generator(cfg.seed, step, rank, k), augment, cfg.points), device)
                   for k, i in enumerate(mine)]  # fmt: skip
        for g in opt.param_groups:
            g["lr"] = _lr(cfg, step)
        w = _weights(cfg, step)
        _, heads = model([s.inputs for s in samples], [s.points for s in samples])
        mat_weights = [(1.0, 1.0)] * len(samples)
        if cfg.log_mse and w.mat > 0:  # the neural stage's material loss
            mses = torch.stack([torch.stack(material_mse(h, s.targets)) for h, s in zip(heads, samples, strict=True)])
            mat_weights = [(float(a), float(b)) for a, b in object_weights(mses)]
        total = torch.zeros((), device=device)
        parts: dict[str, float] = {}
        for h, s, mw in zip(heads, samples, mat_weights, strict=True):
            loss, p = lmrm_loss(h, s.targets, w, cfg.beta, s.family, mw)
            total = total + loss / len(samples)
            for k, v in p.items():
                parts[k] = parts.get(k, 0.0) + v / len(samples)
        opt.zero_grad(set_to_none=False)
        total.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.clip)
        opt.step()
        with torch.no_grad():
            for slow, fast in zip(ema.parameters(), net.parameters(), strict=True):
                slow.lerp_(fast, 1 - cfg.ema)
        step += 1
        row = {"step": step, "stage": 1 if w.mat == 0 else 2, "loss": float(total.detach()), "lr": _lr(cfg, step - 1),
               **parts}  # fmt: skip
        history.append(row)
        if progress is not None and rank == 0:
            progress(step, cfg.steps, row)
        if rank == 0 and (step % cfg.val_every == 0 or step == cfg.steps) and (val_set := validation_set()).folders:
            validation.append({"step": step, **evaluate(ema, val_set, device, mean_material())})
        if step % cfg.checkpoint_every == 0:
            save_checkpoint()
        if cfg.max_minutes > 0 and (time.monotonic() - started) / 60 > cfg.max_minutes and step < cfg.steps:
            stopped_early = True
            break
    save_checkpoint()
    metrics: dict[str, Any] = {}
    if rank == 0 and not stopped_early:
        mean = mean_material()
        if val_set.folders and (not validation or validation[-1]["step"] != step):
            validation.append({"step": step, **evaluate(ema, val_set, device, mean)})
            save_checkpoint()
        tail = history[-50:]
        metrics = {
            "steps": step, "train_objects": len(order.dataset), "validation_objects": len(val_set),
            "train_l_mat_last50": sum(h["l_mat"] for h in tail) / len(tail),
            "train_nll_last50": sum(h["nll"] for h in tail) / len(tail),
            "validation": validation[-1] if validation else {},
            "training_mean": [round(float(x), 6) for x in mean],
        }  # fmt: skip
        minutes = seconds_so_far() / 60
        info = {"metrics": metrics, "train_config": asdict(cfg),
                "data": {"folders": [str(r) for r in roots], "objects": len(order.dataset),
                         "manifest_sha256": order.dataset.manifest_hash(), "validation_ids": val_set.ids},
                "training": {"world_size": world, "device": str(device),
                             "device_name": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
                             "minutes_this_run": round(minutes - seconds_before / 60, 2), "minutes": round(minutes, 2),
                             "minutes_with_init": round(minutes + init_minutes(cfg.init), 2)}}  # fmt: skip
        basis = load_basis()
        save_lmrm(ema, out / "lmrm.safetensors", out / "lmrm.json", basis, info)
        if cfg.install:
            for name in ("lmrm.safetensors", "lmrm.json"):
                shutil.copy2(out / name, DATA_DIR / name)
    if owned:
        dist.destroy_process_group()
    return TrainResult(step, not stopped_early, metrics, out)
