#!/usr/bin/env python3
"""The choice between two bases on held-out photos (TTOConfig.select_basis, docs/design-notes.md item 80), read
from both sides' stored results: what the default with basis v6's candidates joined to its choice gives, paired
against the configured basis alone, v6 alone and the PBR baseline.

    .venv/bin/python bench/basis_choice.py [--variant default_choose_v6_alone] [--page bench/results/eval-clean] \\
        [--before default_choose_v6]

Each side is the plain TTO in one basis (`bench/variants_clean.py` `basis_sides`: for the default, `default_v1`
and `default_v6_dec`; a side without the alternative basis takes the rows of a variant that differs from it in the
alternative alone wherever that one's start stayed in v1, `start_stand_ins`: for default_v1 the default of design
note 75, item 81). The choice's candidates in each basis are that side's own (the same
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
from common import RESULTS_DIR, argument_parser, mean_se, write_result  # noqa: E402
from variants_clean import (  # noqa: E402
    basis_choice_result,
    basis_sides,
    side_results,
    start_stand_ins,
    start_stayed,
)

from neumatex_core.eval.suite import paired_difference, result_path  # noqa: E402
from neumatex_core.eval.variants import DEFAULT_VARIANT  # noqa: E402

# a side without Cycles rows -> the variant whose rows are its own there: the default of item 75 makes the same
# choices as s900 on every capture (its margin 0 against 0.25; no capture's lies between)
CYCLES_STAND_IN = {"pbr_start_default_settle_decdb_slr10_s900_m0": "pbr_start_default_settle_decdb_slr10_s900"}
PAGE_METRICS = ("psnr_pathtrace_clean", "psnr_relight_clean", "psnr_basecolor")
CYCLES_METRICS = ("photos_clean_db", "relit_clean_db")


def page_table(variant: str, sides: tuple[str, str], page: Path, before: str = "") -> dict[str, Any]:
    """The choice on the benchmark objects of the evaluation in `page`: per metric, the choice's mean and its paired
    difference against each side, PBR and (`before`: another select_basis variant, read from its own sides) that
    choice; how often the other basis was taken."""
    versus = (*sides, "pbr", *([before] if before else []))
    res: dict[str, dict[str, dict[str, float]]] = {v: {m: {} for m in PAGE_METRICS} for v in (variant, *versus)}
    before_sides = basis_sides(before) if before else None
    earlier = side_results(before_sides, page) if before_sides else {}
    taken = 0
    for obj, found in side_results(sides, page).items():
        pbr = result_path(page, obj, "pbr")
        if not pbr.is_file():
            continue
        rows = {sides[0]: found[0][0], sides[1]: found[1][0], "pbr": json.loads(pbr.read_text())}
        chosen = basis_choice_result(variant, rows[sides[0]], rows[sides[1]])
        if chosen is None:
            continue
        if obj in earlier:
            made = basis_choice_result(before, earlier[obj][0][0], earlier[obj][1][0])
            if made is not None:
                rows[before] = made
        taken += int(chosen["choice_select_basis_taken"])
        for v, row in {**rows, variant: chosen}.items():
            for m in PAGE_METRICS:
                if m in row and row[m] is not None and math.isfinite(row[m]):
                    res[v][m][obj] = float(row[m])
    n = len(res[variant][PAGE_METRICS[0]])
    print(f"\n{variant} on the benchmark objects of {page} (n={n}; {sides[1]}'s basis taken on {taken})")
    print(f"| PSNR, dB | {variant} | " + " | ".join(f"- {b}" for b in versus) + " |")
    print("|---" * (2 + len(versus)) + "|")
    table: dict[str, Any] = {"objects": n, "other_taken": taken}
    for m in PAGE_METRICS:
        cells, entry = [], {"mean": float(np.mean(list(res[variant][m].values())))}
        for b in versus:
            mean, se, count = paired_difference(res, variant, b, m)
            entry[b] = {"diff": mean, "se": se, "n": count}
            cells.append(f"{mean:+.2f} +- {se:.2f} (n={count})")
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


def cycles_choices(variant: str, sides: tuple[str, str],
                   before: str = "") -> tuple[dict[str, list[dict[str, float]]], dict[str, str], dict[str, Any]]:
    """The choice on every Cycles capture with rows of both sides and PBR: (per preset, each capture's differences:
    the choice minus each side, minus PBR and (`before`, where its sides have rows) minus that choice; capture ->
    the side it took; capture -> the choice's scores (CYCLES_METRICS))."""
    latest = cycles_latest()
    before_sides = basis_sides(before) if before else None
    for side in {*sides, *(before_sides or ())}:  # its own rows first, else its stand-in's; without the alternative
        # basis then those of the variants that differ in it alone (or their stand-ins') where the start stayed in v1
        starts = [n for s in start_stand_ins(side) for n in (s, CYCLES_STAND_IN.get(s)) if n]
        for capture in {c for c, _ in latest}:
            found = [latest.get((capture, n)) for n in (side, CYCLES_STAND_IN.get(side))] + [
                row for n in starts if (row := latest.get((capture, n))) is not None and start_stayed(flat(row))]
            row = next((r for r in found if r is not None), None)
            if row is not None:
                latest[(capture, side)] = row
    own = sides[0]
    captures = sorted({c for c, v in latest if v == own} & {c for c, v in latest if v == sides[1]}
                      & {c for c, v in latest if v == "pbr"})
    per: dict[str, list[dict[str, float]]] = {}
    took: dict[str, str] = {}
    scores: dict[str, Any] = {}
    for capture in captures:
        a, b, pbr = flat(latest[(capture, own)]), flat(latest[(capture, sides[1])]), latest[(capture, "pbr")]
        chosen = basis_choice_result(variant, a, b)
        if chosen is None:
            continue
        took[capture] = sides[1] if chosen["choice_select_basis_taken"] else own
        scores[capture] = {m: chosen[m] for m in CYCLES_METRICS}
        earlier = None
        if before_sides and all((capture, side) in latest for side in before_sides):
            earlier = basis_choice_result(before, *(flat(latest[(capture, side)]) for side in before_sides))
        diffs = {}
        for m in CYCLES_METRICS:
            diffs[f"{m} - own"] = chosen[m] - a[m]
            diffs[f"{m} - other"] = chosen[m] - b[m]
            diffs[f"{m} - pbr"] = chosen[m] - pbr[m]
            if earlier is not None:
                diffs[f"{m} - before"] = chosen[m] - earlier[m]
        per.setdefault(capture.rsplit("-", 1)[-1], []).append(diffs)
    return per, took, scores


def cycles_table(variant: str, sides: tuple[str, str], before: str = "") -> dict[str, Any]:
    """`cycles_choices` printed and summed up: per preset the mean +- s.e. over meshes of each difference, and which
    basis each capture took."""
    per, took, _ = cycles_choices(variant, sides, before)
    own = sides[0]
    stand_ins = [n for n in (CYCLES_STAND_IN.get(own), *start_stand_ins(own)) if n]
    print(f"\n{variant} on the Cycles captures (clean; {own} (where it has no row, "
          f"{' or '.join(stand_ins) or 'none'}) and {sides[1]} the sides)")
    for capture, side in took.items():
        print(f"  {capture}: {side}")
    keys = [f"{m} - {s}" for m in CYCLES_METRICS for s in ("own", "other", "pbr", *(["before"] if before else []))]
    print("| preset (captures) | " + " | ".join(keys) + " |")
    print("|---" * (1 + len(keys)) + "|")
    table: dict[str, Any] = {"took": took}
    for preset, rows in sorted(per.items()):
        cells, entry = [], {}
        for k in keys:
            mean, se = mean_se([r[k] for r in rows if k in r])
            entry[k] = {"diff": mean, "se": se}
            cells.append(f"{mean:+.2f} +- {se:.2f}")
        table[preset] = entry
        print(f"| {preset} ({len(rows)}) | " + " | ".join(cells) + " |")
    return table


def main() -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--variant", default=DEFAULT_VARIANT)
    parser.add_argument("--page", type=Path, default=RESULTS_DIR / "eval-clean")
    parser.add_argument("--before", default="", metavar="VARIANT", help="also pair against this select_basis "
                        "variant, read from its own two sides (e.g. default_choose_v6, the default before)")
    args = parser.parse_args()
    sides = basis_sides(args.variant)
    for name in (args.variant, *([args.before] if args.before else [])):
        if basis_sides(name) is None:
            print(f"{name} has no select_basis, or no variants that are its two sides", file=sys.stderr)
            return 2
    assert sides is not None
    record = {"variant": args.variant, "sides": list(sides), "before": args.before,
              "benchmark_objects": page_table(args.variant, sides, args.page, args.before),
              "cycles": cycles_table(args.variant, sides, args.before)}
    write_result("basis_choice", record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
