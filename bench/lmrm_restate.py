"""A candidate LMRM's prediction restated through the shipped model's decoders: does the extraction's default gain
from a better prediction when the TTO keeps the decoders it works well with? (docs/design-notes.md item 95)

The default reads the LMRM's triplane through the LMRM's own decoders: its PBR phase starts from the PBR head, and its
neural phase fine-tunes a copy of the material decoder. A candidate that predicts better alone made the default worse
(bench/lmrm_swap.py). This separates the prediction from the decoders: per object, a triplane is fitted (Adam on its
planes, from the shipped prediction's) so that the shipped decoders give, at area-uniform surface points, what the
candidate's give there: the PBR head's base colour, roughness and metallic and the material decoder's base colour and
latent (squared error, latents mapped to [0, 1] as the G-buffer metric does). The result is written as the lmrm stage
of a new evaluation folder (the shipped decoders and the fitted planes; validate and prepare_views copied), so
`neumatex eval --out` that folder runs the default table from it without predicting again:

    .venv/bin/python bench/lmrm_restate.py data/benchmark-test --shipped runs/swap/shipped \\
        --candidate runs/swap/NAME --out runs/swap/NAME-restated --objects first:8
    .venv/bin/neumatex eval data/benchmark-test --tables default --relight-views 0,8,16 --objects first:8 \\
        --out runs/swap/NAME-restated --doc '' --record ''
    .venv/bin/python bench/lmrm_swap.py runs/swap/shipped runs/swap/NAME-restated

`--shipped` and `--candidate` are evaluation folders whose lmrm stage has run on the objects (work/<object>/lmrm/).
Appends one JSON line per run to bench/results/lmrm_restate.jsonl: per object the fit's final error on each head.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import argument_parser, write_result  # noqa: E402

from neumatex_core.atomic import write_json_atomic  # noqa: E402
from neumatex_core.capture import load_capture  # noqa: E402
from neumatex_core.eval.suite import select_objects  # noqa: E402
from neumatex_core.lmrm.restate import restate  # noqa: E402
from neumatex_core.pipeline import load_prediction, stage_dir  # noqa: E402
from neumatex_core.tto.pbr_start import FIT_BATCH, FIT_LR, FIT_POINTS, FIT_STEPS  # noqa: E402


def write_restated(shipped_work: Path, out_work: Path, planes: torch.Tensor, note: dict[str, Any]) -> None:
    """out_work's validate, prepare_views and lmrm stages: shipped_work's, with the lmrm prediction's planes
    replaced by `planes` and its record naming what was done."""
    from safetensors.torch import load_file, save_file

    for stage in ("validate", "prepare_views", "lmrm"):
        shutil.copytree(stage_dir(shipped_work, stage), stage_dir(out_work, stage), dirs_exist_ok=True)
    folder = stage_dir(out_work, "lmrm")
    tensors = load_file(str(folder / "prediction.safetensors"))
    tensors["triplane.planes"] = planes.detach().cpu().contiguous()
    save_file(tensors, str(folder / "prediction.safetensors"))
    record = json.loads((folder / "prediction.json").read_text())
    record["restated"] = note
    write_json_atomic(folder / "prediction.json", record)


def main() -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("data", type=Path, help="the benchmark split")
    parser.add_argument("--shipped", type=Path, required=True, help="evaluation folder run with the shipped LMRM")
    parser.add_argument("--candidate", type=Path, required=True, help="evaluation folder run with the candidate")
    parser.add_argument("--out", type=Path, required=True, help="the new evaluation folder")
    parser.add_argument("--objects", default="all", help="as `neumatex eval --objects`")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    fits: dict[str, dict[str, float]] = {}
    for obj in select_objects(args.data, args.objects):
        ship_work, cand_work = args.shipped / "work" / obj, args.candidate / "work" / obj
        if not (stage_dir(ship_work, "lmrm") / "done.json").is_file() or \
                not (stage_dir(cand_work, "lmrm") / "done.json").is_file():
            print(f"{obj}: skipped, the lmrm stage has not run in both {args.shipped} and {args.candidate}")
            continue
        if (stage_dir(args.out / "work" / obj, "lmrm") / "done.json").is_file():
            print(f"{obj}: already restated in {args.out}")
            continue
        shipped, _ = load_prediction(ship_work)
        candidate, cand_record = load_prediction(cand_work)
        points, _ = load_capture(args.data / obj).load_mesh().sample_surface(FIT_POINTS, seed=0)
        restated, err = restate(candidate, shipped, points, steps=FIT_STEPS, lr=FIT_LR, batch=FIT_BATCH)
        write_restated(ship_work, args.out / "work" / obj, restated.triplane.planes,
                       {"candidate": cand_record.get("lmrm", {}), "fit": err})
        fits[obj] = err
        print(f"{obj}: mean squared error, PBR head {err['pbr_start']:.4f} -> {err['pbr_end']:.5f}, "
              f"material decoder {err['material_start']:.4f} -> {err['material_end']:.5f}")
    if fits:
        path = write_result("lmrm_restate", {"shipped": str(args.shipped), "candidate": str(args.candidate),
                                             "out": str(args.out), "fits": fits})
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
