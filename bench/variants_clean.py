"""TTO variants against the extraction's default and the PBR baseline on the benchmark's objects, scored clean and
paired per object (issue 14): the same harness as `neumatex eval` (`eval/harness.evaluate_variant`, cpu preset,
the object's 23 preset views, relight views 0, 8, 16), one object per worker process at one torch thread.

    NEUMATEX_SHARED=../shared .venv/bin/python bench/variants_clean.py --variants pbr_start_consistent_1 \\
        --objects test-000010,test-000011 [--workers 2]
    .venv/bin/python bench/variants_clean.py --summarise --variants pbr_start_consistent_1

Each finished (object, variant) appends one JSON line to bench/results/variants_clean.jsonl, so a stopped run
resumes where it stopped (an object already there for a variant is skipped). `--summarise` prints, per metric,
each variant's mean and its paired difference (mean +- standard error over objects) against every baseline in
--against (default: the anchored recipe `pbr_start_anchor_01`, the extraction's default until 2026-11-27, and the
PBR baseline `pbr`), with eval/suite.py's `paired_difference`. A baseline's rows come from this file and from
bench/results/random_pose_e2e.jsonl (its "preset/<variant>" rows: the same harness on the same preset views), the
latest per object. Needs the objects' references (`neumatex references`).

`--fill-from B,C` (with --summarise) completes each summarised variant on the objects where it has no row with the
row of the first of B, C, ... whose config differs from it only in the alternative basis (or its margin; where the
default basis is chosen, also in `decoder_in_other_basis`, which acts only in another) and whose choice of basis there
is the same (`alternative_basis`, docs/design-notes.md item 38): such variants give the same
result bit for bit where they choose the same basis. The choice is worked out from the scores of
bench/results/basis_start.jsonl and from the basis records of this file's rows, so e.g. the default's table covers
objects that only a neighbouring variant was run on.

`--since ISO_TIME` (UTC): rows written before it neither count as done nor are summarised, so a baseline can be run
again beside a variant on one machine (results move between machines: docs/design-notes.md item 45).

`--to-eval OUT` writes each of --variants' rows (the latest per object) as results of the evaluation in OUT
(`OUT/results/<object>/<variant>.json`, with a "source" naming this file, the row's time and commit), so that
`neumatex eval --out OUT --report-only` pages them, e.g. the default's table once its variant has rows on every
object (docs/design-notes.md items 51 and 59). With `--fill-from B,C`, where a variant has no row, the row of B or C
that differs from it only in the uniform/textured choice's margin and makes the same choice there stands in
(`same_uniform_choice`, item 75). A variant that also tries another basis (`TTOConfig.select_basis`, item 80)
with no row of its own is made from its two sides' results (the plain TTO in each basis, `basis_sides`: from OUT's
results or this file): their recorded held-out scores decide as its TTO does (`basis_choice_result`). A side
without the alternative basis that has no result there takes that of a variant differing from it in the alternative
alone, wherever that one's start stayed in the configured basis (`start_stand_ins`, item 81):

    .venv/bin/python bench/variants_clean.py --to-eval bench/results/eval-clean \\
        --variants pbr_start_default_settle_decdb

`--against-page OUT` (with --summarise) takes the --against baselines' rows from the evaluation in OUT (its
results/<object>/<variant>.json, what its page shows), e.g. a candidate against the default's page:

    .venv/bin/python bench/variants_clean.py --summarise --variants default_v6_dec --against-page \\
        bench/results/eval-clean --against pbr_start_default_settle_decdb_slr10_s900_m0,pbr,truth

`--by-family BASELINE` (with --summarise) also prints each variant minus BASELINE per material family (the families
of an object's regions, from its meta.json; an object with two counts in both rows) and over all objects, with the
number of objects on which the variant is ahead.

`--per-object BASELINE` (with --summarise) also prints each variant minus BASELINE object by object (PathTrace,
Relight, BaseColor, TTO minutes), the objects where it is behind on PathTrace marked, so a candidate's losses can be
looked at before it becomes the default (docs/design-notes.md item 64).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import argument_parser, write_result  # noqa: E402

from neumatex_core.atomic import write_json_atomic  # noqa: E402
from neumatex_core.eval.harness import evaluate_variant  # noqa: E402
from neumatex_core.eval.suite import (  # noqa: E402
    Results,
    load_results,
    object_families,
    paired_difference,
    paired_values,
    result_path,
    select_objects,
)
from neumatex_core.eval.variants import VARIANTS, variant_config  # noqa: E402
from neumatex_core.materials.neural_basis import BASIS_V4, load_basis  # noqa: E402
from neumatex_core.pipeline import ExtractConfig  # noqa: E402
from neumatex_core.tto.pbr_start import alternative_wins, in_select_basis  # noqa: E402

METRICS = ("psnr_pathtrace_clean", "psnr_relight_clean", "psnr_basecolor", "psnr_latents")
NAMES = {"psnr_pathtrace_clean": "PathTrace, clean", "psnr_relight_clean": "Relight, clean",
         "psnr_basecolor": "BaseColor", "psnr_latents": "Latents"}  # fmt: skip
RESULTS = Path(__file__).resolve().parent / "results"


def one(object_dir: str, work: str, variant: str) -> dict[str, Any]:
    """The scores of `variant` on one object (preset views)."""
    torch.set_num_threads(1)
    config = ExtractConfig.preset("cpu", device="cpu")
    scores = evaluate_variant(object_dir, work, variant, config, relight_views=(0, 8, 16))
    choice = {k: float(v) for k, v in scores.items() if k.startswith("choice_")}  # select_anchor / select_uniform
    return {"object": Path(object_dir).name, "variant": variant,
            "scores": {m: float(scores[m]) for m in (*METRICS, "tto_minutes") if m in scores},
            **({"choice": choice} if choice else {})}  # fmt: skip


def own_rows() -> list[dict[str, Any]]:
    """This benchmark's rows (bench/results/variants_clean.jsonl), oldest first."""
    own = RESULTS / "variants_clean.jsonl"
    return [json.loads(line) for line in own.read_text().splitlines()] if own.is_file() else []


def stored_rows(since: str = "") -> dict[str, dict[str, dict[str, float]]]:
    """variant -> object -> scores: this benchmark's rows, then random_pose_e2e's preset rows where this one has
    none (the latest line wins within each file); with `since` (an ISO time), only this benchmark's rows written at
    or after it."""
    rows: dict[str, dict[str, dict[str, float]]] = {}
    e2e = RESULTS / "random_pose_e2e.jsonl"
    if e2e.is_file() and not since:
        for line in e2e.read_text().splitlines():
            for row in json.loads(line).get("rows", []):
                for key, scores in row.items():
                    if key.startswith("preset/"):
                        rows.setdefault(key.split("/", 1)[1], {})[row["object"]] = scores
    for row in own_rows():
        if row["timestamp"] >= since:
            rows.setdefault(row["variant"], {})[row["object"]] = row["scores"]
    return rows


def basis_scores(variant: str) -> dict[str, dict[str, float]]:
    """object -> the basis choice's scores there (dB: pbr, start in the default basis, start in the alternative when
    known): bench/results/basis_start.jsonl's rows (v4 as the alternative), then the basis records of this file's
    rows of variants that differ from `variant` in the basis choice alone (another PBR phase, e.g. one with its
    head fine-tuned, scores other starts)."""
    scores: dict[str, dict[str, float]] = {}
    path = RESULTS / "basis_start.jsonl"
    for line in path.read_text().splitlines() if path.is_file() else []:
        for row in json.loads(line)["rows"]:
            scores[Path(row["capture"]).name] = {"pbr": row["pbr"], "own": row[load_basis().basis_id],
                                                 "alternative": row[BASIS_V4]}  # fmt: skip
    for row in own_rows():
        c = row.get("choice", {})
        same_phase = row["variant"] in VARIANTS and differs_only_in_basis(variant, row["variant"])
        if "choice_basis_pbr_psnr" in c and same_phase:
            known = scores.setdefault(row["object"], {})
            known.update({"pbr": c["choice_basis_pbr_psnr"], "own": c["choice_basis_start_psnr"]})
            if "choice_basis_alternative_psnr" in c:
                known["alternative"] = c["choice_basis_alternative_psnr"]
    return scores


def basis_choice(variant: str, known: dict[str, float] | None) -> str | None:
    """"default" or the alternative basis `variant` starts its neural phase in, given the scores `known`; None when
    they do not tell (`tto/pbr_start.py` `choose_basis`)."""
    tto = variant_config(variant, ExtractConfig.preset("cpu").tto)
    if tto is None or not tto.alternative_basis:
        return "default"
    if not known or "pbr" not in known:
        return None
    wins = alternative_wins(known["pbr"], known["own"], known.get("alternative"), tto.basis_margin_db)
    return None if wins is None else tto.alternative_basis if wins else "default"


def differs_only_in_basis(variant: str, other: str, in_default_basis: bool = True) -> bool:
    """Whether the configs of `variant` and `other` are the same but for the alternative basis and its margin (and,
    `in_default_basis`, for what the neural phase does in another basis: `decoder_in_other_basis`): only then does
    `other`'s row stand in for `variant`'s where both choose the same basis (--fill-from)."""
    base = ExtractConfig.preset("cpu").tto
    a, b = variant_config(variant, base), variant_config(other, base)
    if a is None or b is None:
        return a is b
    unbased: dict[str, Any] = {"alternative_basis": "", "basis_margin_db": 0.0}
    if in_default_basis:
        unbased["decoder_in_other_basis"] = True
    return replace(a, **unbased) == replace(b, **unbased)


def family_table(res: Results, variant: str, base: str, families: dict[str, list[str]]) -> None:
    """Print `variant` - `base` per material family (mean +- standard error over the objects with a region of that
    family, and on how many of them `variant` is ahead), then over all objects."""
    metrics = ("psnr_pathtrace_clean", "psnr_relight_clean", "psnr_basecolor")
    print(f"\n{variant} - {base} by material family (an object with two families counts in both rows)")
    print("| family | " + " | ".join(NAMES[m] for m in metrics) + " |")
    print("|---" * (1 + len(metrics)) + "|")
    names = sorted({f for fs in families.values() for f in fs})
    groups = {f: {o for o, fs in families.items() if f in fs} for f in names}
    for family, keep in [*groups.items(), ("all", set(families))]:
        sub: Results = {v: {m: {o: x for o, x in per.items() if o in keep} for m, per in res.get(v, {}).items()}
                        for v in (variant, base)}  # fmt: skip
        cells = []
        for m in metrics:
            mean, se, n = paired_difference(sub, variant, base, m)
            ahead = sum(d > 0 for d in paired_values(sub, variant, base, m).values())
            cells.append(f"{mean:+.2f} +- {se:.2f} (ahead on {ahead} of {n})" if n else "-")
        print(f"| {family} | " + " | ".join(cells) + " |")


def object_table(stored: dict[str, dict[str, dict[str, float]]], variant: str, base: str) -> None:
    """Print `variant` - `base` on each object both have a row on, a "<" after the objects where `variant` is behind
    on PathTrace."""
    metrics = ("psnr_pathtrace_clean", "psnr_relight_clean", "psnr_basecolor", "tto_minutes")
    mine, theirs = stored.get(variant, {}), stored.get(base, {})
    print(f"\n{variant} - {base} by object")
    print("| object | " + " | ".join(NAMES.get(m, "TTO, min") for m in metrics) + " |")
    print("|---" * (1 + len(metrics)) + "|")
    for o in sorted(set(mine) & set(theirs)):
        cells = [f"{mine[o][m] - theirs[o][m]:+.2f}" if m in mine[o] and m in theirs[o] else "-" for m in metrics]
        behind = mine[o].get("psnr_pathtrace_clean", 0.0) < theirs[o].get("psnr_pathtrace_clean", 0.0)
        print(f"| {o}{' <' if behind else ''} | " + " | ".join(cells) + " |")


def page_objects(out: Path) -> list[str]:
    """The objects that have results in the evaluation in `out` (its results/<object>/ folders), sorted."""
    folder = out / "results"
    return sorted(p.name for p in folder.iterdir() if p.is_dir()) if folder.is_dir() else []


def page_rows(out: Path, variant: str) -> dict[str, dict[str, float]]:
    """object -> scores of `variant` in the evaluation in `out` (OUT/results/<object>/<variant>.json: what its page
    shows, e.g. bench/results/eval-clean for docs/default/results.md)."""
    rows: dict[str, dict[str, float]] = {}
    for metric, values in load_results(out, page_objects(out), {variant: variant})[variant].items():
        for obj, value in values.items():
            if metric in METRICS:
                rows.setdefault(obj, {})[metric] = value
    return rows


def summarise(variants: list[str], against: list[str], fill_from: list[str] | None = None,
              by_family: tuple[Path, str] | None = None, since: str = "", per_object: str = "",
              page: Path | None = None) -> int:
    stored = stored_rows(since)
    for base in against if page is not None else []:
        stored[base] = page_rows(page, base)
    for variant in variants if fill_from else []:
        scores = basis_scores(variant)
        mine = stored.setdefault(variant, {})
        for o in sorted(set().union(*(stored.get(b, {}) for b in fill_from)) - set(mine)):
            wanted = basis_choice(variant, scores.get(o))
            source = next((b for b in fill_from if o in stored.get(b, {}) and wanted is not None
                           and differs_only_in_basis(variant, b, wanted == "default")
                           and basis_choice(b, scores.get(o)) == wanted),
                          None)  # fmt: skip
            if source is not None:
                mine[o] = stored[source][o]
                print(f"{variant} on {o}: {source}'s row (basis: {wanted})")
    res: Results = {v: {m: {o: s[m] for o, s in by_object.items() if m in s and np.isfinite(s[m])} for m in METRICS}
                    for v, by_object in stored.items()}  # fmt: skip
    for variant in variants:
        mine = stored.get(variant, {})
        if not mine:
            print(f"{variant}: no rows yet")
            continue
        print(f"\n{variant} (n={len(mine)}: {', '.join(sorted(mine))})")
        print("| PSNR, dB | " + " | ".join([variant] + [f"{variant} - {b}" for b in against]) + " |")
        print("|---" * (2 + len(against)) + "|")
        for m in METRICS:
            values = [s[m] for s in mine.values() if m in s and np.isfinite(s[m])]  # NaN: not scored (another basis)
            cells = [f"{np.mean(values):.2f} (n={len(values)})" if values else "-"]
            for base in against:
                mean, se, n = paired_difference(res, variant, base, m)  # the PBR baseline has no latents: n = 0
                cells.append(f"{mean:+.2f} +- {se:.2f} (n={n})" if n > 1 else "-")
            print(f"| {NAMES[m]} | {' | '.join(cells)} |")
        if by_family is not None:
            family_table(res, variant, by_family[1], object_families(by_family[0], sorted(mine)))
        if per_object:
            object_table(stored, variant, per_object)
    return 0


def same_uniform_choice(variant: str, other: str, choice: dict[str, float]) -> bool:
    """Whether `other`'s row, whose choice record is `choice`, stands in for `variant`'s: their configs differ in
    `select_margin_db` alone and both margins make the same uniform/textured choice from the recorded held-out
    scores. The choice's candidates do not depend on the margin (their held-out scores agree bit for bit between
    the default and its forced variants on all 40 objects, docs/design-notes.md item 75), and what follows depends
    on the choice alone, so such a row is the variant's result."""
    base = ExtractConfig.preset("cpu").tto
    a, b = variant_config(variant, base), variant_config(other, base)
    if a is None or b is None or replace(a, select_margin_db=0.0) != replace(b, select_margin_db=0.0):
        return False
    if "choice_validation_psnr_textured" not in choice:
        return False
    gain = choice["choice_validation_psnr_textured"] - choice["choice_validation_psnr_uniform"]
    return (gain > a.select_margin_db) == (gain > b.select_margin_db)


def basis_sides(variant: str) -> tuple[str, str] | None:
    """With TTOConfig.select_basis: the variants that are `variant`'s configured basis alone and its other basis
    alone (`in_select_basis`), by config; None without select_basis or where VARIANTS names no such pair."""
    base = ExtractConfig.preset("cpu").tto
    tto = variant_config(variant, base)
    if tto is None or not tto.select_basis:
        return None
    wanted = (replace(tto, select_basis=""), in_select_basis(tto))
    names = [next((n for n in VARIANTS if variant_config(n, base) == want), None) for want in wanted]
    return None if names[0] is None or names[1] is None else (names[0], names[1])


def basis_choice_result(variant: str, own: dict[str, Any], other: dict[str, Any]) -> dict[str, Any] | None:
    """`variant`'s result (select_basis) from the results of its two sides (`basis_sides`: flat score and choice_
    records, as the evaluation stores them), or None when their choice records do not tell. The choice's candidates
    in each basis are those sides' own (the same PBR phase, start and steps: tests/test_tto.py
    `test_select_basis_...`), so their held-out scores decide as the TTO does: the other basis where its kept
    candidate beats the configured one's by more than select_margin_db. The result is the taken side's scores with
    the configured side's choice record and the other's scores beside it, as the TTO records them; not its TTO
    time, which is both sides' choice and one side's TTO after it."""
    tto = variant_config(variant, ExtractConfig.preset("cpu").tto)
    assert tto is not None

    def kept(result: dict[str, Any]) -> float | None:
        if "choice_uniform_kept" not in result or not result.get("choice_validation_photos"):
            return None
        name = "uniform" if result["choice_uniform_kept"] else "textured"
        return float(result[f"choice_validation_psnr_{name}"])

    a, b = kept(own), kept(other)
    if a is None or b is None:
        return None
    taken = b > a + tto.select_margin_db
    scores = {k: v for k, v in (other if taken else own).items() if not k.startswith("choice_")
              and k not in ("object", "variant", "source", "tto_minutes")}  # fmt: skip
    choice = {k: v for k, v in own.items() if k.startswith("choice_")}
    choice.update({"choice_select_basis_psnr_uniform": other["choice_validation_psnr_uniform"],
                   "choice_select_basis_psnr_textured": other["choice_validation_psnr_textured"],
                   "choice_select_basis_uniform_kept": other["choice_uniform_kept"],
                   "choice_select_basis_taken": float(taken)})  # fmt: skip
    return {**scores, **choice}


def to_eval(variants: list[str], out: Path, fill_from: Sequence[str] = ()) -> int:
    """Write the latest row per (object, variant) of this file as the evaluation's result in `out` (the fields
    `evaluate_variant` stores: scores, choices, object, variant) with its "source"; print how many per variant.
    Where a variant has no row, the latest row of the first of `fill_from` that makes the same uniform/textured
    choice there (`same_uniform_choice`) stands in, its source saying so."""
    latest: dict[tuple[str, str], dict[str, Any]] = {}
    for row in own_rows():
        if row["variant"] in (*variants, *fill_from):
            latest[(row["variant"], row["object"])] = row
    for variant in variants:
        objects = sorted({o for (v, o) in latest if v in (variant, *fill_from)})
        rows: list[dict[str, Any]] = []
        for o in objects:
            row = latest.get((variant, o)) or next(
                (latest[(f, o)] for f in fill_from
                 if (f, o) in latest and same_uniform_choice(variant, f, latest[(f, o)].get("choice", {}))), None)
            if row is not None:
                rows.append(row)
        composed = composed_rows(variant, out, {r["object"] for r in rows})
        for row in rows:
            stand_in = "" if row["variant"] == variant else f", {row['variant']}'s row: the same choice"
            result = {**row["scores"], **row.get("choice", {}), "object": row["object"], "variant": variant,
                      "source": f"bench/results/variants_clean.jsonl {row['timestamp']} (commit {row['commit'][:7]}"
                                f"{stand_in})"}
            path = result_path(out, row["object"], variant)
            path.parent.mkdir(parents=True, exist_ok=True)
            write_json_atomic(path, result)
        for obj, result in composed.items():
            write_json_atomic(result_path(out, obj, variant), result)
        print(f"{variant}: {len(rows) + len(composed)} objects written to {out}/results"
              + (f" ({len(composed)} from its two bases' results)" if composed else ""))
    return 0


def start_stand_ins(variant: str) -> list[str]:
    """The variants whose results are `variant`'s wherever their start stayed in the configured basis (their record's
    choice_basis_switched 0): `variant` has no alternative basis and they differ from it in the alternative basis
    alone (`differs_only_in_basis`). The TTO is then the same bit for bit (tests/test_tto.py
    `test_without_the_alternative_basis_...`, docs/design-notes.md item 81)."""
    tto = variant_config(variant, ExtractConfig.preset("cpu").tto)
    if tto is None or tto.alternative_basis:
        return []
    return [n for n in VARIANTS if n != variant and differs_only_in_basis(variant, n)]


def start_stayed(result: dict[str, Any]) -> bool:
    """Whether a result (flat scores and choice records) records its start in the configured basis: then it stands
    for its `start_stand_ins` variants' result."""
    return result.get("choice_basis_switched") == 0.0


def side_results(sides: Sequence[str], out: Path) -> dict[str, list[tuple[dict[str, Any], str]]]:
    """object -> each side's result (flat scores and choice records) and where it came from, on the objects of the
    evaluation in `out` where every side has one: its result in `out` (e.g. the default's page, its rows filled in
    there), else its latest row of this file, else a `start_stand_ins` variant's result or row where that one's
    start stayed in the configured basis."""
    stand_ins = {name: start_stand_ins(name) for name in sides}
    names = {n for name in sides for n in (name, *stand_ins[name])}
    latest = {(r["variant"], r["object"]): r for r in own_rows() if r["variant"] in names}

    def own(name: str, obj: str) -> tuple[dict[str, Any], str] | None:
        path = result_path(out, obj, name)
        if path.is_file():
            return json.loads(path.read_text()), f"{out}/results/{obj}/{name}.json"
        row = latest.get((name, obj))
        if row is None:
            return None
        return ({**row["scores"], **row.get("choice", {})},
                f"bench/results/variants_clean.jsonl {row['timestamp']} (commit {row['commit'][:7]})")

    def side(name: str, obj: str) -> tuple[dict[str, Any], str] | None:
        found = own(name, obj)
        for other in stand_ins[name] if found is None else []:
            got = own(other, obj)
            if got is not None and start_stayed(got[0]):
                return got[0], f"{other}'s, its start in the configured basis: {got[1]}"
        return found

    found: dict[str, list[tuple[dict[str, Any], str]]] = {}
    for obj in page_objects(out):
        each = [side(name, obj) for name in sides]
        if all(e is not None for e in each):
            found[obj] = [e for e in each if e is not None]
    return found


def composed_rows(variant: str, out: Path, have: set[str]) -> dict[str, dict[str, Any]]:
    """object -> `variant`'s result made from its two sides' results (`basis_sides`, `basis_choice_result`,
    `side_results`) on the objects not in `have`."""
    sides = basis_sides(variant)
    if sides is None:
        return {}
    made: dict[str, dict[str, Any]] = {}
    for obj, found in side_results(sides, out).items():
        if obj in have:
            continue
        result = basis_choice_result(variant, found[0][0], found[1][0])
        if result is not None:
            taken = sides[1] if result["choice_select_basis_taken"] else sides[0]
            made[obj] = {**result, "object": obj, "variant": variant,
                         "source": f"the basis choice of {sides[0]} ({found[0][1]}) and {sides[1]} ({found[1][1]}): "
                                   f"{taken}'s scores"}  # fmt: skip
    return made


def main() -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("--data", default="data/benchmark-test")
    parser.add_argument("--objects", default="all")
    parser.add_argument("--variants", default="pbr_start_consistent_1")
    parser.add_argument("--against", default="pbr_start_anchor_01,pbr")
    parser.add_argument("--work", default="runs/bench-variants-clean")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--since", default="", metavar="ISO_TIME", help="UTC, e.g. 2026-11-28T16:03:10: count only "
                        "rows written since then as done (a baseline run again on this machine beside a variant, "
                        "docs/design-notes.md items 44-45); with --summarise, summarise only those rows")
    parser.add_argument("--summarise", action="store_true", help="print the paired table so far and stop")
    parser.add_argument("--fill-from", default="", help="with --summarise: comma-separated variants whose rows stand "
                        "in where they choose the same basis; with --to-eval: where they make the same uniform/"
                        "textured choice (see above)")
    parser.add_argument("--by-family", default="", metavar="BASELINE", help="with --summarise: also each variant - "
                        "BASELINE per material family of the objects (their meta.json), and on how many it is ahead")
    parser.add_argument("--per-object", default="", metavar="BASELINE", help="with --summarise: also each variant - "
                        "BASELINE object by object")
    parser.add_argument("--against-page", default="", metavar="OUT", help="with --summarise: the --against "
                        "baselines' rows are those of the evaluation in OUT (e.g. bench/results/eval-clean: the "
                        "default's page), not this file's")
    parser.add_argument("--to-eval", default="", metavar="OUT", help="write --variants' rows as results of the "
                        "evaluation in OUT (for `neumatex eval --out OUT --report-only`) and stop")
    args = parser.parse_args()
    variants, against = args.variants.split(","), args.against.split(",")
    if args.to_eval:
        return to_eval(variants, Path(args.to_eval), [v for v in args.fill_from.split(",") if v])
    if args.summarise:
        return summarise(variants, against, [v for v in args.fill_from.split(",") if v],
                         (Path(args.data), args.by_family) if args.by_family else None, args.since,
                         args.per_object, Path(args.against_page) if args.against_page else None)
    data = Path(args.data)
    done = stored_rows(args.since)
    jobs = [(str(data / o), str(Path(args.work) / o), v) for v in variants for o in select_objects(data, args.objects)
            if o not in done.get(v, {})]  # fmt: skip
    print(f"{len(jobs)} (object, variant) pairs to run", flush=True)
    with ProcessPoolExecutor(args.workers) as pool:
        for future in as_completed([pool.submit(one, *job) for job in jobs]):  # each kept as soon as it is done
            row = future.result()
            write_result("variants_clean", row)
            print(f"{row['object']} {row['variant']}: " + ", ".join(f"{NAMES[m]} {row['scores'][m]:.2f}"
                  for m in METRICS if m in row["scores"]), flush=True)  # fmt: skip
    return summarise(variants, against, since=args.since)


if __name__ == "__main__":
    raise SystemExit(main())
