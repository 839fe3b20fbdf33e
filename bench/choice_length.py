#!/usr/bin/env python3
"""The uniform/textured choice's held-out scores with longer candidates (docs/design-notes.md item 76).

Runs, per benchmark object, only the choice of the default's TTO (its PBR phase on the fitted photos and both
candidates' neural phases, each scored on the held-out photos) with the candidates `--fraction` of the neural steps
instead of the default's ninth, stopping as soon as the TTO with the chosen config begins, and appends the
selection to bench/results/choice_length.jsonl. The candidates' length changes only the choice, not what follows it
(tests/test_tto.py, the select_uniform test), and bench/results/variants_clean.jsonl holds both branches' results on
every object (item 75), so `bench/choice_rule.py --length FRACTION` scores the rule "textured where the longer
candidates say so" without running the TTO that follows.

    NEUMATEX_SHARED=../shared .venv/bin/python bench/choice_length.py --fraction 0.2222 --objects 0,2,4
    NEUMATEX_SHARED=../shared .venv/bin/python bench/choice_length.py --fraction 0.2222 --captures runs/cycles/cow-*
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import prepared_capture, write_result  # noqa: E402

from neumatex_core.eval.references import harness_envmap  # noqa: E402
from neumatex_core.eval.variants import DEFAULT_VARIANT, variant_config  # noqa: E402
from neumatex_core.materials.neural_basis import load_basis  # noqa: E402
from neumatex_core.tto import solve  # noqa: E402

FINAL_PHASE = 2.0  # the progress rows' phase of the TTO with the chosen config (tto/pbr_start.py)


def choice_of(capture: Path, work: Path, fraction: float) -> dict[str, Any]:
    """The default's choice on one capture with candidates of `fraction` of the neural steps: its selection record."""
    config, pred, cap, mesh, photos = prepared_capture(capture, work)
    tto = variant_config(DEFAULT_VARIANT, config.variant_base())
    assert tto is not None and tto.select_uniform
    tto = replace(tto, select_fraction=fraction)
    final = [False]

    def progress(_s: int, _n: int, row: dict[str, float]) -> None:
        final[0] = final[0] or row.get("phase") == FINAL_PHASE

    result = solve(tto, mesh, harness_envmap(cap), photos, cap.tonemap, pred, load_basis(basis_id=tto.basis),
                   progress=progress, should_stop=lambda: final[0])
    return dict(result.selection)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fraction", type=float, required=True, help="the candidates' share of the neural steps")
    parser.add_argument("--objects", default="", help="comma-separated benchmark indices, e.g. 0,2,4")
    parser.add_argument("--captures", nargs="*", default=[], type=Path, help="capture folders, e.g. runs/cycles/*")
    parser.add_argument("--data", default="data/benchmark-test")
    parser.add_argument("--work", default="runs/choice-length")
    args = parser.parse_args()
    torch.set_num_threads(1)
    folders = [Path(args.data) / f"test-{int(i):06d}" for i in args.objects.split(",") if i] + args.captures
    for folder in folders:
        selection = choice_of(folder, Path(args.work) / folder.name, args.fraction)
        write_result("choice_length", {"object": folder.name, "capture": str(folder), "variant": DEFAULT_VARIANT,
                                       "fraction": args.fraction, "selection": selection})
        print(f"{folder.name}: {selection}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
