#!/usr/bin/env python3
"""The choice between two bases on held-out photos (TTOConfig.select_basis, docs/design-notes.md item 80), read
from both sides' stored results: what the default with basis v6's candidates joined to its choice gives, paired
against the configured basis alone, v6 alone and the PBR baseline.

    .venv/bin/python bench/basis_choice.py [--variant default_choose_v6] [--page bench/results/eval-clean]

Each side is the plain TTO in one basis (`bench/variants_clean.py` `basis_sides`: for the default, the default of
design note 75 in v1/v4 and `default_v6_dec`). The choice's candidates in each basis are that side's own (the same
PBR phase, start and candidate steps, bit for bit: tests/test_tto.py), so each side's recorded held-out scores decide
as the TTO does (`basis_choice_result`), and the chosen side's scores are the choice's. On the benchmark's 40 objects
both sides come from the evaluation in --page (the default's page and default_v6_dec's rows written into it); on
the Blender Cycles captures from bench/results/cycles_extract.jsonl (the latest scores of each (capture, variant):
held-out photos and relit, clean; the default there is `pbr_start_default_settle_decdb_slr10_s900`, whose choice
margin 0.25 makes the same choices as 0 on every capture, item 75). Prints the paired tables and appends them to
bench/results/basis_choice.jsonl.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS_DIR, argument_parser, write_result  # noqa: E402
from variants_clean import basis_choice_result, basis_sides, page_objects  # noqa: E402

from neumatex_core.eval.suite import paired_difference, result_path  # noqa: E402

# a side without Cycles rows -> the variant whose rows are its own there: the default of item 75 makes the same
# choices as s900 on every capture (its margin 0 against 0.25; no capture's lies between)
CYCLES_STAND_IN = {"pbr_start_default_settle_decdb_slr10_s900_m0": "pbr_start_default_settle_decdb_slr10_s900"}
PAGE_METRICS = ("psnr_pathtrace_clean", "psnr_relight_clean", "psnr_basecolor")
CYCLES_METRICS = ("photos_clean_db", "relit_clean_db")


def mean_se(values: list[float]) -> tuple[float, float]:
    """Mean and its standard error (nan with fewer than two values)."""
    a = np.asarray(values, dtype=float)
    return float(a.mean()), float(a.std(ddof=1) / math.sqrt(len(a))) if len(a) > 1 else math.nan


def page_table(variant: str, sides: tuple[str, str], page: Path) -> dict[str, Any]:
    """The choice on the benchmark objects of the evaluation in `page`: per metric, the choice's mean and its paired
    difference against each side and PBR; how often the other basis was taken."""
    objects = page_objects(page)
    res: dict[str, dict[str, dict[str, float]]] = {v: {m: {} for m in PAGE_METRICS} for v in (variant, *sides, "pbr")}
    taken = 0
    for obj in objects:
        found = {v: result_path(page, obj, v) for v in (*sides, "pbr")}
        if not all(path.is_file() for path in found.values()):
            continue
        rows = {v: json.loads(path.read_text()) for v, path in found.items()}
        chosen = basis_choice_result(variant, rows[sides[0]], rows[sides[1]])
        if chosen is None:
            continue
        taken += int(chosen["choice_select_basis_taken"])
        for v, row in {**rows, variant: chosen}.items():
            for m in PAGE_METRICS:
                if m in row and row[m] is not None and math.isfinite(row[m]):
                    res[v][m][obj] = float(row[m])
    n = len(res[variant][PAGE_METRICS[0]])
    print(f"\n{variant} on the benchmark objects of {page} (n={n}; {sides[1]}'s basis taken on {taken})")
    print(f"| PSNR, dB | {variant} | " + " | ".join(f"- {b}" for b in (*sides, "pbr")) + " |")
    print("|---" * (5) + "|")
    table: dict[str, Any] = {"objects": n, "other_taken": taken}
    for m in PAGE_METRICS:
        cells, entry = [], {"mean": float(np.mean(list(res[variant][m].values())))}
        for b in (*sides, "pbr"):
            mean, se, count = paired_difference(res, variant, b, m)
            entry[b] = {"diff": mean, "se": se, "n": count}
            cells.append(f"{mean:+.2f} +- {se:.2f}")
        table[m] = entry
        print(f"| {m} | {entry['mean']:.2f} | " + " | ".join(cells) + " |")
    return table


def cycles_latest() -> dict[tuple[str, str], dict[str, Any]]:
    """(capture, variant) -> its latest scores in bench/results/cycles_extract.jsonl."""
    path = RESULTS_DIR / "cycles_extract.jsonl"
    latest: dict[tuple[str, str], dict[str, Any]] = {}
    for line in path.read_text().splitlines() if path.is_file() else []:
        for row in json.loads(line).get("rows", []):
            for key, scores in row.items():
                if isinstance(scores, dict) and "relit_clean_db" in scores:
                    latest[(row["capture"], key)] = scores
    return latest


def flat(scores: dict[str, Any]) -> dict[str, Any]:
    """A Cycles row's scores with its selection record as the evaluation stores choices (choice_<key>)."""
    return {**{k: v for k, v in scores.items() if k in CYCLES_METRICS},
            **{f"choice_{k}": v for k, v in scores.get("selection", {}).items()}}


def cycles_table(variant: str, sides: tuple[str, str]) -> dict[str, Any]:
    """The choice on every Cycles capture with rows of both sides and PBR: per preset the choice minus each side and
    minus PBR (mean +- s.e. over meshes), and which basis each capture took."""
    latest = cycles_latest()
    for (capture, name), scores in list(latest.items()):  # the configured side's own rows first, else its stand-in's
        if name == CYCLES_STAND_IN.get(sides[0]):
            latest.setdefault((capture, sides[0]), scores)
    own = sides[0]
    captures = sorted({c for c, v in latest if v == own} & {c for c, v in latest if v == sides[1]}
                      & {c for c, v in latest if v == "pbr"})
    per: dict[str, list[dict[str, float]]] = {}
    took: dict[str, str] = {}
    for capture in captures:
        a, b, pbr = flat(latest[(capture, own)]), flat(latest[(capture, sides[1])]), latest[(capture, "pbr")]
        chosen = basis_choice_result(variant, a, b)
        if chosen is None:
            continue
        took[capture] = sides[1] if chosen["choice_select_basis_taken"] else own
        diffs = {}
        for m in CYCLES_METRICS:
            diffs[f"{m} - own"] = chosen[m] - a[m]
            diffs[f"{m} - other"] = chosen[m] - b[m]
            diffs[f"{m} - pbr"] = chosen[m] - pbr[m]
        per.setdefault(capture.rsplit("-", 1)[-1], []).append(diffs)
    print(f"\n{variant} on the Cycles captures (clean; {own} (where it has no row, "
          f"{CYCLES_STAND_IN.get(own, own)}) and {sides[1]} the sides)")
    for capture, side in took.items():
        print(f"  {capture}: {side}")
    keys = [f"{m} - {s}" for m in CYCLES_METRICS for s in ("own", "other", "pbr")]
    print("| preset (captures) | " + " | ".join(keys) + " |")
    print("|---" * (1 + len(keys)) + "|")
    table: dict[str, Any] = {"took": took}
    for preset, rows in sorted(per.items()):
        cells, entry = [], {}
        for k in keys:
            mean, se = mean_se([r[k] for r in rows])
            entry[k] = {"diff": mean, "se": se}
            cells.append(f"{mean:+.2f} +- {se:.2f}")
        table[preset] = entry
        print(f"| {preset} ({len(rows)}) | " + " | ".join(cells) + " |")
    return table


def main() -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--variant", default="default_choose_v6")
    parser.add_argument("--page", type=Path, default=RESULTS_DIR / "eval-clean")
    args = parser.parse_args()
    sides = basis_sides(args.variant)
    if sides is None:
        print(f"{args.variant} has no select_basis, or no variants that are its two sides", file=sys.stderr)
        return 2
    record = {"variant": args.variant, "sides": list(sides), "benchmark_objects": page_table(args.variant, sides,
                                                                                            args.page),
              "cycles": cycles_table(args.variant, sides)}
    write_result("basis_choice", record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
