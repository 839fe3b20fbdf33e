"""Train one neural-basis candidate within a wall-clock budget (issue 14, lever 5; docs/design-notes.md item 25).

A lent GPU comes for minutes, so the schedule is fitted to the time rather than the other way round: the script
times a few steps of each stage (`bsdf`, `aux`, `sampler`) on this device, gives each stage its share of the
budget, then runs `train_basis` with those step counts (a plain, deterministic `neumatex train-basis` schedule
that the record writes down, so the run can be repeated with the CLI). Several candidates can share one GPU: each
step is many small kernels, so one process leaves most of the device idle.

    python3 tools/train_basis_timed.py --name v3a --budget-s 400 --out OUT \
        --init neumatex_core/materials/data/bases/v2.safetensors --batch 65536 --lr 1e-3

Writes OUT/<name>.safetensors and OUT/<name>.json (the basis record, with the device and seconds used).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from neumatex_core.materials.basis_training import (  # noqa: E402
    STAGES,
    TrainBasisConfig,
    architecture,
    stage_parameters,
    train_basis,
    training_step,
)
from neumatex_core.materials.neural_basis import NeuralBasis  # noqa: E402

SHARE = {"bsdf": 0.80, "aux": 0.05, "sampler": 0.15}  # of the training seconds


def seconds_per_step(cfg: TrainBasisConfig, stage: str, device: torch.device, probe_s: float) -> float:
    """Mean wall seconds of one training step of `stage` (after 3 warm-up steps), timed for about probe_s."""
    basis = NeuralBasis(architecture(cfg)).to(device)
    opt = torch.optim.Adam(stage_parameters(basis, stage, cfg.aux_weight), lr=cfg.lr)
    n, t0 = 0, 0.0
    while True:
        training_step(cfg, stage, n, basis, opt, cfg.lr, device)
        if device.type == "cuda":
            torch.cuda.synchronize()
        n += 1
        if n == 3:
            t0 = time.perf_counter()
        elif n > 3 and time.perf_counter() - t0 > probe_s:
            return (time.perf_counter() - t0) / (n - 3)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--name", required=True)
    ap.add_argument("--out", required=True, help="folder for <name>.safetensors and <name>.json")
    ap.add_argument("--work", default="/tmp/train_basis_timed", help="folder for checkpoints")
    ap.add_argument("--budget-s", type=float, required=True, help="wall seconds for everything, probes included")
    ap.add_argument("--probe-s", type=float, default=6.0)
    ap.add_argument("--init", default="")
    ap.add_argument("--batch", type=int, default=65536)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--aux-weight", type=float, default=2.0)
    ap.add_argument("--chroma-weight", type=float, default=1.0)
    ap.add_argument("--render-weight", type=float, default=0.0)
    ap.add_argument("--render-group", type=int, default=16)
    ap.add_argument("--render-base", type=float, default=0.5)
    ap.add_argument("--mirror-share", type=float, default=0.0)
    ap.add_argument("--uniform-share", type=float, default=0.25)
    ap.add_argument("--mixture-weight", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--latent-dim", type=int, default=6)
    ap.add_argument("--aux-width", type=int, default=64)
    ap.add_argument("--aux-share", type=float, default=SHARE["aux"], help="share of the training seconds for the "
                    "auxiliary network alone (the bsdf stage gives up what it takes beyond the default)")
    ap.add_argument("--version", default="v3")
    args = ap.parse_args()
    start = time.perf_counter()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    out = Path(args.out)
    cfg = TrainBasisConfig(out=str(Path(args.work) / args.name), seed=args.seed, batch=args.batch, lr=args.lr,
                           aux_weight=args.aux_weight, chroma_weight=args.chroma_weight,
                           render_weight=args.render_weight, render_group=args.render_group,
                           render_base=args.render_base, mirror_share=args.mirror_share,
                           uniform_share=args.uniform_share, mixture_weight=args.mixture_weight, init=args.init,
                           version=args.version,
                           latent_dim=args.latent_dim, aux_width=args.aux_width, checkpoint_every=2000,
                           device=str(device))  # fmt: skip
    per_step = {s: seconds_per_step(cfg, s, device, args.probe_s if s == "bsdf" else args.probe_s / 2) for s in STAGES}
    train_s = (args.budget_s - (time.perf_counter() - start)) * 0.9 - 15  # margin: held-out metrics, saving
    share = {**SHARE, "aux": args.aux_share, "bsdf": SHARE["bsdf"] + SHARE["aux"] - args.aux_share}
    steps = {s: max(100, int(train_s * share[s] / per_step[s])) for s in STAGES}
    cfg.steps_bsdf, cfg.steps_aux, cfg.steps_sampler = steps["bsdf"], steps["aux"], steps["sampler"]
    print(f"{args.name}: {device}, s/step {per_step}, steps {steps}", flush=True)

    def progress(stage: str, step: int, total: int, loss: float) -> None:
        if step % 2000 == 0 or step == total:
            elapsed = time.perf_counter() - start
            print(f"{args.name} {stage} {step}/{total} loss {loss:.4f} t={elapsed:.0f}s", flush=True)

    basis, metrics = train_basis(cfg, device, progress)
    gpu = torch.cuda.get_device_name(0) if device.type == "cuda" else "cpu"
    metrics["compute"] = f"{gpu}, {time.perf_counter() - start:.0f} wall seconds (tools/train_basis_timed.py)"
    basis_id = basis.save(out / f"{args.name}.safetensors", out / f"{args.name}.json", metrics, args.version)
    print(f"{args.name}: basis {basis_id}, median rel {metrics['bsdf_median_rel_error']:.4f}, "
          f"log-L1 {metrics['bsdf_log_l1']:.4f}, T MAE {metrics['t_mae']:.4f}, {time.perf_counter() - start:.0f}s",
          flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
