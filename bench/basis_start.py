"""How well each installed neural basis holds the PBR solution: the start of the neural TTO in every basis, scored
on held-out photos against the PBR solution it was fitted to (docs/design-notes.md, item 38).

For every capture (a Cycles capture, runs/cycles/<mesh>-<preset>, or a benchmark object, data/benchmark-test/<id>),
as the extraction's default does before its neural phase: the PBR phase of the cpu preset on all photos but the 4
held out (`validation_frames`), then its solution fitted into the neural triplane (`fit_start_to_pbr`, no neural
step) in each installed basis, and the PBR solution and every start scored on the held-out photos with the clean
estimator `photo_psnr` (one seed, so all share their random numbers). The start's rule (`TTOConfig.alternative_basis`,
`tto/pbr_start.py` `alternative_wins`) takes the alternative basis (the config's, else `pipeline.ALTERNATIVE_BASIS`)
where the default basis's start is more than the preset's margin (3 dB) below PBR and the alternative's more than
that above the default's; the last column says what it takes. The extraction applies that rule only where no other
basis is tried on the held-out photos (variation textured or uniform; the default "choose" tries basis v6 there
instead: docs/design-notes.md, item 81). One JSON line per capture in bench/results/basis_start.jsonl (a
stopped run keeps the finished ones).

    NEUMATEX_SHARED=../shared .venv/bin/python bench/basis_start.py runs/cycles/teapot-{metal,coat} \\
        data/benchmark-test/test-000017        # about 1.5-2.5 minutes per capture on one thread

`--fits STEPS@LR,...` fits each start also with those Adam settings (`TTOConfig.pbr_fit_steps`, `pbr_fit_lr`),
`--bases` in the bases named (ids or their short names v1, v6); each is paired per capture with the preset's own fit
(the reference, measured in the same run): its held-out score minus the reference's, its G-buffer error (the fit's
MSE) and its seconds over the reference's (docs/design-notes.md, item 104):

    .venv/bin/python bench/basis_start.py --bases v1,v6 --fits 500@0.2,1500@0.2 examples/coat-teapot runs/cycles/*
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import argument_parser, mean_se, prepared_capture, write_result  # noqa: E402

from neumatex_core.eval.references import harness_envmap  # noqa: E402
from neumatex_core.materials.neural_basis import installed_bases, load_basis  # noqa: E402
from neumatex_core.pipeline import ALTERNATIVE_BASIS  # noqa: E402
from neumatex_core.tto.config import TTOConfig  # noqa: E402
from neumatex_core.tto.optimise import build_problem  # noqa: E402
from neumatex_core.tto.params import NeuralTriplane, PBRTriplane  # noqa: E402
from neumatex_core.tto.pbr_start import (  # noqa: E402
    _pbr_phase,
    alternative_wins,
    fit_start_to_pbr,
    photo_psnr,
    validation_frames,
)


def work_dir(capture: Path) -> Path:
    """The stage folder the other benchmarks keep for this capture (its LMRM prediction is reused)."""
    root = "runs/bench-variants-clean" if capture.parent.name.startswith("benchmark") else "runs/bench-cycles-extract"
    return Path(root) / capture.name


def start_config(tto: TTOConfig) -> TTOConfig:
    """The problem each basis's start is fitted in: the extraction's TTO `tto` without its choices, anchor or
    alternative basis (init "lmrm": the start is fitted by hand, `fit_start_to_pbr`)."""
    return replace(tto, init="lmrm", basis="", reg="none", select_uniform=False, select_anchor=False, select_basis="",
                   alternative_basis="")  # fmt: skip


Fit = tuple[int, float]  # (Adam steps, learning rate) of the start's fit


def score_capture(capture: Path, bases: list[str], fits: list[Fit]) -> dict[str, Any]:
    """{"capture", "pbr": dB, <basis id>: dB of its start, "takes": the basis the extraction's rule takes (where
    both bases it compares were fitted), "fits": {"STEPS@LR": {<basis id>: dB, <basis id>_mse, <basis id>_s}} for
    the preset's own fit and each of `fits`}."""
    config, pred, cap, mesh, photos = prepared_capture(capture, work_dir(capture))
    tto, envmap = config.tto_config(), harness_envmap(cap)
    held = validation_frames(photos.cameras, tto.validation_photos, mesh.bounding_sphere()[0])
    fit = photos.subset([i for i in range(photos.count) if i not in held])
    held_photos = photos.subset(held)
    t0 = time.perf_counter()
    first = _pbr_phase(tto, mesh, envmap, fit, cap.tonemap, pred, load_basis(), True, None, None, None)
    row: dict[str, Any] = {"capture": str(capture),
                           "pbr": photo_psnr(first.params, first.mesh or mesh, envmap, held_photos, cap.tonemap, tto,
                                             tto.seed + 1), "fits": {}}  # fmt: skip
    starts = start_config(tto)
    preset: Fit = (tto.pbr_fit_steps, tto.pbr_fit_lr)
    row["reference"] = fit_name(preset)
    for steps, lr in [preset, *(f for f in fits if f != preset)]:
        scores: dict[str, float] = {}
        for basis_id in bases:
            basis = load_basis(basis_id=basis_id)
            problem = build_problem(starts, mesh, envmap, fit, cap.tonemap, pred, basis, True)
            assert isinstance(problem.params, NeuralTriplane) and isinstance(first.params, PBRTriplane)
            t1 = time.perf_counter()
            mse = fit_start_to_pbr(problem.params, first.params, problem.mesh, basis, tto.seed, steps,
                                   tto.pbr_bsdf_fit_steps, lr, tto.pbr_fit_batch)  # fmt: skip
            scores[f"{basis_id}_s"], scores[f"{basis_id}_mse"] = time.perf_counter() - t1, mse
            scores[basis_id] = photo_psnr(problem.params, problem.mesh or mesh, envmap, held_photos, cap.tonemap, tto,
                                          tto.seed + 1)  # fmt: skip
        row["fits"][fit_name((steps, lr))] = scores
    row.update({b: row["fits"][fit_name(preset)][b] for b in bases})
    alternative = tto.alternative_basis or ALTERNATIVE_BASIS
    if load_basis().basis_id in row and alternative in row:
        wins = alternative_wins(row["pbr"], row[load_basis().basis_id], row[alternative], tto.basis_margin_db)
        row["takes"] = alternative if wins else "default"
    row["seconds"] = time.perf_counter() - t0
    return row


def fit_name(fit: Fit) -> str:
    return f"{fit[0]}@{fit[1]:g}"


def parse_fits(text: str) -> list[Fit]:
    """"500@0.2,1500@0.2" -> [(500, 0.2), (1500, 0.2)]."""
    fits = []
    for item in filter(None, text.split(",")):
        steps, _, lr = item.partition("@")
        fits.append((int(steps), float(lr)))
    return fits


def basis_ids(text: str) -> list[str]:
    """Installed basis ids from ids or short names ("v1,v6"); all installed ones for ""."""
    installed = list(installed_bases())
    if not text:
        return installed
    picked = []
    for name in text.split(","):
        found = [b for b in installed if b == name or b.split("-")[2] == name]
        if not found:
            raise SystemExit(f"basis {name!r} is not installed (installed: {', '.join(installed)})")
        picked.append(found[0])
    return picked


def paired_fits(rows: list[dict[str, Any]], bases: list[str], reference: str) -> list[str]:
    """Markdown lines: per fit and basis, mean +- standard error over the rows of its held-out score minus the
    reference fit's (dB), its MSE and seconds over the reference's (ratios of the means)."""
    lines = ["| fit | basis | held-out dB - reference | captures ahead | MSE / reference | seconds / reference |",
             "|---|---|---|---|---|---|"]
    for name in rows[0]["fits"]:
        if name == reference:
            continue
        for b in bases:
            d = np.array([r["fits"][name][b] - r["fits"][reference][b] for r in rows])
            mean, se = mean_se(d)
            mse = np.mean([r["fits"][name][f"{b}_mse"] for r in rows]) / np.mean(
                [r["fits"][reference][f"{b}_mse"] for r in rows])
            sec = np.mean([r["fits"][name][f"{b}_s"] for r in rows]) / np.mean(
                [r["fits"][reference][f"{b}_s"] for r in rows])
            lines.append(f"| {name} | {b.split('-')[2]} | {mean:+.2f} +- {se:.2f} | {int((d > 0).sum())}/{len(d)} "
                         f"| {mse:.2f} | {sec:.2f} |")
    return lines


def main() -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("captures", nargs="+", type=Path)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--bases", default="", help="bases to fit the start in: ids or short names (v1,v6); all")
    parser.add_argument("--fits", default="", help="STEPS@LR,...: the start's fit also with these Adam settings")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    bases, fits = basis_ids(args.bases), parse_fits(args.fits)
    print("| capture | PBR | " + " | ".join(b.split("-")[2] for b in bases) + " | the rule takes |")
    print("|---" * (len(bases) + 3) + "|")
    rows = []
    for capture in args.captures:
        row = score_capture(capture, bases, fits)
        rows.append(row)
        path = write_result("basis_start", {"bases": bases, "rows": [row]})
        print(f"| {capture.name} | {row['pbr']:.2f} | " + " | ".join(f"{row[b]:.2f}" for b in bases)
              + f" | {row.get('takes', '-')} |", flush=True)  # fmt: skip
    if fits:
        print("\n".join(["", *paired_fits(rows, bases, rows[0]["reference"])]))
    print(f"appended to {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
