#!/usr/bin/env python3
"""The uniform/textured choice read from both branches (docs/design-notes.md item 75).

On every benchmark object with both branches of s900's choice in bench/results/variants_clean.jsonl (s900's own
row and the forced variant of the branch it did not choose, `tools/choice_flips.sh`), prints per object the
choice's evidence (held-out margin textured - uniform, tto/baked_light.py's light slope, correlation and texture
spread, recorded by the forced run) next to what each branch scores (clean PathTrace and Relight, textured -
uniform), then what each rule gives over those objects, paired against s900's rule (textured where the held-out
margin is above 0.25 dB; the default since item 75 takes 0): mean PathTrace and Relight, and the best choice per
object (the oracle). Then the same on the Blender Cycles captures whose both branches are in
bench/results/cycles_extract.jsonl (`tools/cycles_choice_flips.sh`; held-out photos and relit, clean; their truth
is one uniform material). Appends the summary to bench/results/choice_rule.jsonl.

    .venv/bin/python bench/choice_rule.py [--default pbr_start_default_settle_decdb_slr10_s900]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import RESULTS_DIR, write_result  # noqa: E402
from variants_clean import own_rows  # noqa: E402

SCORES = ("psnr_pathtrace_clean", "psnr_relight_clean")
EVIDENCE = ("light_slope", "light_correlation", "texture_spread")


Entry = tuple[dict[str, float], dict[str, float]]  # one run's scores (SCORES) and its choice's selection record


def forced(default: str) -> tuple[str, str, str]:
    """The default and its two forced variants (eval/variants.py: ..._uniform, ..._textured)."""
    return default, f"{default}_uniform", f"{default}_textured"


def paired(latest: dict[tuple[str, str], Entry], default: str) -> dict[str, dict[str, Any]]:
    """name -> {"uniform": scores, "textured": scores, "kept": the default's branch, "margin", evidence...} from the
    latest run per (variant, name), where the default's and its flipped branch's runs are both there; the evidence
    is the forced run's record (the default's rows may predate it)."""
    out: dict[str, dict[str, Any]] = {}
    for (variant, name), (scores, selection) in latest.items():
        kept = "uniform" if selection.get("uniform_kept") else "textured"
        flipped = "textured" if kept == "uniform" else "uniform"
        other = latest.get((f"{default}_{flipped}", name))
        if variant != default or other is None:
            continue
        sel = other[1]
        out[name] = {kept: scores, flipped: other[0], "kept": kept,
                     "margin": sel["validation_psnr_textured"] - sel["validation_psnr_uniform"],
                     **{k: sel.get(k, math.nan) for k in EVIDENCE}}
    return out


def branches(default: str) -> dict[str, dict[str, Any]]:
    """object -> `paired`'s record from bench/results/variants_clean.jsonl (the latest row per object and variant)."""
    latest: dict[tuple[str, str], Entry] = {}
    for row in own_rows():
        if row["variant"] in forced(default):
            selection = {k.removeprefix("choice_"): v for k, v in row.get("choice", {}).items()}
            latest[(row["variant"], row["object"])] = (row["scores"], selection)
    return paired(latest, default)


def cycles_branches(default: str) -> dict[str, dict[str, Any]]:
    """capture -> `paired`'s record from bench/results/cycles_extract.jsonl (the latest clean scores per capture and
    variant; its SCORES hold the held-out photos' and the relit PSNR)."""
    path = RESULTS_DIR / "cycles_extract.jsonl"
    latest: dict[tuple[str, str], Entry] = {}
    for line in path.read_text().splitlines() if path.is_file() else []:
        for row in json.loads(line).get("rows", []):
            for variant in forced(default):
                if "relit_clean_db" in (e := row.get(variant, {})):
                    scores = {SCORES[0]: e["photos_clean_db"], SCORES[1]: e["relit_clean_db"]}
                    latest[(variant, Path(row["capture"]).name)] = (scores, e.get("selection", {}))
    return paired(latest, default)


def longer_margins(fraction: float) -> dict[str, float]:
    """object -> textured - uniform held-out PSNR of the choice with candidates `fraction` of the neural steps long
    (bench/results/choice_length.jsonl, the latest record per object)."""
    path = RESULTS_DIR / "choice_length.jsonl"
    out: dict[str, float] = {}
    for line in path.read_text().splitlines() if path.is_file() else []:
        row = json.loads(line)
        if abs(row["fraction"] - fraction) < 1e-6:
            sel = row["selection"]
            out[row["object"]] = sel["validation_psnr_textured"] - sel["validation_psnr_uniform"]
    return out


def rule_scores(objects: dict[str, dict[str, Any]], rule: Callable[[dict[str, Any]], bool]) -> dict[str, np.ndarray]:
    """Per score, [objects] what the rule (True: textured) gives."""
    return {s: np.array([o["textured" if rule(o) else "uniform"][s] for o in objects.values()]) for s in SCORES}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--default", default="pbr_start_default_settle_decdb_slr10_s900")
    parser.add_argument("--length", type=float, default=0.0, metavar="FRACTION", help="also the rules on the held-out "
                        "margin of candidates this share of the neural steps long (bench/choice_length.py's records)")
    args = parser.parse_args()
    objects = dict(sorted(branches(args.default).items()))
    captures = dict(sorted(cycles_branches(args.default).items()))
    if args.length:
        longer = longer_margins(args.length)
        for name, o in (*objects.items(), *captures.items()):
            if name in longer:
                o["margin_long"] = longer[name]
        print(f"held-out margins of candidates {args.length:.4f} of the neural steps long on {len(longer)} objects")
    if not objects:
        print("no object has both branches yet (tools/choice_flips.sh)")
        return 1
    summary = report(objects, f"benchmark objects with both branches of {args.default}'s choice")
    cycles = report(captures, "Cycles captures with both branches (PathTrace: held-out photos)") if captures else {}
    write_result("choice_rule", {"default": args.default, "objects": len(objects), "rules": summary,
                                 "per_object": objects, "captures": len(captures), "cycles_rules": cycles,
                                 "per_capture": captures})
    return 0


def report(objects: dict[str, dict[str, Any]], label: str) -> dict[str, Any]:
    """Print the per-object table, the evidence's correlations and the rules' paired differences against the
    default's rule; return the latter."""
    print(f"{len(objects)} {label}")
    print("| object | kept | margin T-U | light slope | corr | spread | PathTrace T-U | Relight T-U |")
    print("|---|---|---|---|---|---|---|---|")
    for name, o in objects.items():
        d = [o["textured"][s] - o["uniform"][s] for s in SCORES]
        print(f"| {name} | {o['kept'][0].upper()} | {o['margin']:+.2f} | {o['light_slope']:+.3f} | "
              f"{o['light_correlation']:+.3f} | {o['texture_spread']:.3f} | {d[0]:+.2f} | {d[1]:+.2f} |")
    diff = {s: np.array([o["textured"][s] - o["uniform"][s] for o in objects.values()]) for s in SCORES}
    for k in ("margin", *EVIDENCE):
        x = np.array([o[k] for o in objects.values()])
        ok = np.isfinite(x)
        if ok.sum() > 2:
            cells = ", ".join(f"{s.split('_')[1]} r = {np.corrcoef(x[ok], diff[s][ok])[0, 1]:+.2f}" for s in SCORES)
            print(f"{k} against textured - uniform: {cells} (n = {int(ok.sum())})")
    default = rule_scores(objects, lambda o: o["kept"] == "textured")
    rules: dict[str, Callable[[dict[str, Any]], bool]] = {
        "always uniform": lambda o: False,
        "always textured": lambda o: True,
        "oracle PathTrace": lambda o: o["textured"][SCORES[0]] > o["uniform"][SCORES[0]],
        "oracle Relight": lambda o: o["textured"][SCORES[1]] > o["uniform"][SCORES[1]],
        "margin > 0 (select_margin_db 0)": lambda o: o["margin"] > 0,
    }
    if all("margin_long" in o for o in objects.values()):  # --length
        rules["longer candidates: margin > 0"] = lambda o: o["margin_long"] > 0
        rules["longer candidates: margin > 0.25"] = lambda o: o["margin_long"] > 0.25
        x, d = (np.array([o["margin_long"] for o in objects.values()]), diff[SCORES[0]])
        print(f"longer candidates' margin against textured - uniform: pathtrace r = {np.corrcoef(x, d)[0, 1]:+.2f}, "
              f"relight r = {np.corrcoef(x, diff[SCORES[1]])[0, 1]:+.2f}")
    for slope in (0.0, 0.05, 0.1, 0.2):
        rules[f"margin > 0.25 and light slope < {slope}"] = \
            lambda o, s=slope: o["margin"] > 0.25 and o["light_slope"] < s  # fmt: skip
        rules[f"margin > 0 and light slope < {slope}"] = lambda o, s=slope: o["margin"] > 0 and o["light_slope"] < s
    summary: dict[str, Any] = {}
    print(f"rule - the default's rule, mean ± se over {len(objects)} (textured on how many)")
    for name, rule in rules.items():
        got = rule_scores(objects, rule)
        cells = {}
        for s in SCORES:
            d = got[s] - default[s]
            cells[s] = [float(d.mean()), float(d.std(ddof=1) / math.sqrt(len(d))) if len(d) > 1 else math.nan]
        n_textured = sum(rule(o) for o in objects.values())
        summary[name] = {**cells, "textured": n_textured}
        print(f"  {name}: PathTrace {cells[SCORES[0]][0]:+.3f} ± {cells[SCORES[0]][1]:.3f}, Relight "
              f"{cells[SCORES[1]][0]:+.3f} ± {cells[SCORES[1]][1]:.3f} ({n_textured} textured)")
    return summary


if __name__ == "__main__":
    raise SystemExit(main())
