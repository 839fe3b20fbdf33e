"""Would shipping a candidate LMRM, read through the shipped decoders, with the default's neural start taken from it
beat today's product? (docs/design-notes.md items 96 and 97.) The new extraction is eval variant
`default_lmrm_start_full` run with `--lmrm-weights` the candidate and `--lmrm-readout shipped` (the prediction
restated per object, neumatex_core/lmrm/restate.py); today's is the default with the shipped LMRM, whose 40 objects'
results the results page was made from (kept in bench/results/eval-clean). Paired per object:

    .venv/bin/neumatex eval data/benchmark-test --tables lmrm_start_full --relight-views 0,8,16 --objects IDS \\
        --lmrm-weights bench/candidates/NAME/lmrm.safetensors --lmrm-readout shipped --out runs/ship/NAME \\
        --doc '' --record ''
    .venv/bin/python bench/lmrm_ship.py runs/ship/NAME[+FOLDER...] [--product bench/results/eval-clean] \\
        [--keep bench/results/lmrm-swap/NAME] [--variant default_choose_lmrm_start]

FOLDER+FOLDER...: evaluation folders of the new extraction, their objects joined (the first folder that has an
object gives it). It prints, mean +- standard error (objects ahead): the new default - today's on each metric; the
new PBR baseline (from the restated prediction's PBR head) - today's; and under each LMRM the default - its PBR
baseline on PathTrace and Relight clean (issue 14 asks >= +3 and >= +2 dB); and a choice between the two per object
on held-out photos, simulated from what each run recorded (the best held-out PSNR among its TTO's candidates: the
new one taken where it is higher), against today's. `--keep DIR` copies the new folders'
results/ to DIR/results/ (small; a later session adds objects there). `--variant` names the new extraction's variant
instead: `default_choose_lmrm_start` (table choose_lmrm_start) makes that choice inside its TTO, from the LMRM's
start and the PBR start (design note 98); with `--margins 0,0.25,...` it also prints the choice had it taken the LMRM's
start only where that start's best held-out score beats the PBR start's by more than each margin (dB). That needs
both starts' results per object: the side the choice took is its own result, the other is the PBR start's
(`default_choose_v6_alone`) or the LMRM's (`default_lmrm_start_full`) run in the new folders under the same LMRM
(each side of the choice is that run's, bit for bit). It also prints each start alone against today's on every
object that has it: its side of the choice, or its plain run where no choice ran. Appends one JSON line to
bench/results/lmrm_ship.jsonl.
"""

from __future__ import annotations

import json
import math
import shutil
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import argument_parser, write_result  # noqa: E402
from lmrm_swap import METRICS, PBR, joined_folders  # noqa: E402

from neumatex_core.eval.suite import Results, paired_difference, paired_values  # noqa: E402
from neumatex_core.eval.variants import DEFAULT_VARIANT  # noqa: E402

NEW = "default_lmrm_start_full"
PRODUCT = Path(__file__).resolve().parent / "results" / "eval-clean"
# the table's row names: the new extraction and its PBR baseline (`rows`), today's and its
PRODUCT_ROWS = {"product": DEFAULT_VARIANT, "product_pbr": PBR}
ROWS_PAIRED = {"default": ("new", "product"), "pbr": ("new_pbr", "product_pbr"), "chosen": ("chosen", "product")}
# the held-out photos' PSNR of each candidate a default's TTO compared (configured basis and v6, textured and uniform;
# with select_lmrm_start each from the LMRM's start too)
HELD_OUT = tuple(f"choice_{side}psnr_{candidate}" for side in ("validation_", "select_basis_", "select_lmrm_",
                                                                "select_basis_lmrm_")
                 for candidate in ("textured", "uniform"))  # fmt: skip


# the choice's sides (select_lmrm_start): their held-out score prefixes and the plain run each side is, bit for bit
SIDES = {"pbr_start": (("validation_", "select_basis_"), DEFAULT_VARIANT),
         "lmrm_start": (("select_lmrm_", "select_basis_lmrm_"), NEW)}  # fmt: skip


def rows(variant: str) -> dict[str, str]:
    """The new side's row names: the new extraction (eval variant `variant`) and its PBR baseline."""
    return {"new": variant, "new_pbr": PBR}


def held_out(folders: list[Path], variant: str) -> dict[str, float]:
    """object -> the best held-out-photo PSNR among the candidates of `variant`'s TTO (what its choices compared),
    from the first folder that has the object."""
    out: dict[str, float] = {}
    for folder in folders:
        for f in sorted((folder / "results").glob(f"*/{variant}.json")):
            rec = json.loads(f.read_text())
            values = [float(rec[k]) for k in HELD_OUT if isinstance(rec.get(k), (int, float)) and math.isfinite(rec[k])]
            if values:
                out.setdefault(f.parent.name, max(values))
    return out


def chosen(res: Results, new_held: dict[str, float], product_held: dict[str, float]) -> Results:
    """`res` with a row "chosen": per object the new default's results where its held-out score is higher, else
    today's (objects both sides scored)."""
    if "new" not in res or "product" not in res:  # a side with no complete object
        return res
    rows: dict[str, dict[str, float]] = {}
    for m in res["product"]:
        rows[m] = {}
        for obj, value in res["product"][m].items():
            if obj in new_held and obj in product_held and obj in res["new"][METRICS[0]]:
                take_new = new_held[obj] > product_held[obj]
                if not take_new or obj in res["new"][m]:
                    rows[m][obj] = res["new"][m][obj] if take_new else value
    return {**res, "chosen": rows}


def first_records(folders: list[Path], name: str) -> dict[str, dict[str, Any]]:
    """object -> its `name` result (results/<object>/<name>.json) in the first of `folders` that has one."""
    out: dict[str, dict[str, Any]] = {}
    for folder in folders:
        for f in sorted((folder / "results").glob(f"*/{name}.json")):
            if f.parent.name not in out:
                out[f.parent.name] = json.loads(f.read_text())
    return out


def sides_of(folders: list[Path], variant: str) -> dict[str, dict[str, Any]]:
    """object -> {"gap": the LMRM start's best held-out PSNR - the PBR start's (dB), "pbr_start" / "lmrm_start":
    {metric: value}} for each object of `variant` (a choice with select_lmrm_start) whose two sides' results are
    known: the side it took (gap > 0) is its own result, the other that side's plain run (`SIDES`) in `folders`
    (the first folder that has it)."""
    plain_runs = {side: first_records(folders, name) for side, (_, name) in SIDES.items()}
    out: dict[str, dict[str, Any]] = {}
    for obj, chose in sorted(first_records(folders, variant).items()):
        best = {side: max(float(chose[f"choice_{p}psnr_{c}"]) for p in prefixes for c in ("textured", "uniform")
                          if f"choice_{p}psnr_{c}" in chose)
                for side, (prefixes, _) in SIDES.items()}  # fmt: skip
        gap = best["lmrm_start"] - best["pbr_start"]
        taken = "lmrm_start" if gap > 0 else "pbr_start"
        other = next(side for side in SIDES if side != taken)
        plain = plain_runs[other].get(obj)
        if plain is not None:
            out[obj] = {"gap": gap, taken: {m: chose.get(m) for m in METRICS},
                        other: {m: plain.get(m) for m in METRICS}}
    return out


def with_margins(res: Results, sides: dict[str, dict[str, Any]], margins: list[float],
                 folders: list[Path] | None = None) -> Results:
    """`res` with a row "margin <m>" per margin: per object the LMRM start's result where its best held-out score
    beats the PBR start's by more than m dB, else the PBR start's (`sides_of`); and each start alone ("pbr_start",
    "lmrm_start"): its side of the choice, and on the objects the choice did not run on that start's plain run in
    `folders` (the first folder that has it)."""
    out = dict(res)
    for start, (_, plain) in SIDES.items():
        rows = {obj: {m: rec.get(m) for m in METRICS} for obj, rec in first_records(folders or [], plain).items()}
        rows |= {obj: side[start] for obj, side in sides.items()}
        out[start] = {m: {obj: v for obj, row in rows.items() if isinstance(v := row[m], (int, float))
                          and math.isfinite(v)} for m in METRICS}  # fmt: skip
    for margin in margins:
        out[f"margin {margin:g}"] = {
            m: {obj: v for obj, side in sides.items()
                if isinstance(v := side["lmrm_start" if side["gap"] > margin else "pbr_start"][m], (int, float))
                and math.isfinite(v)}
            for m in METRICS}  # fmt: skip
    return out


def joined(new: list[Path], product: list[Path], variant: str = NEW) -> Results:
    """One table of the new folders' `rows(variant)` and the product folders' `PRODUCT_ROWS` (each object from the
    first folder of its side that has both of that side's rows)."""
    return {**joined_folders(new, rows(variant)), **joined_folders(product, PRODUCT_ROWS)}


def pair(res: Results, a: str, b: str, metric: str) -> dict[str, float]:
    """{a, b: their means over the paired objects, diff, se, n, ahead} for a - b on `metric`."""
    pairs = paired_values(res, a, b, metric)
    diff, se, n = paired_difference(res, a, b, metric)
    return {a: sum(res[a][metric][o] for o in pairs) / n, b: sum(res[b][metric][o] for o in pairs) / n,
            "diff": diff, "se": se, "n": n, "ahead": sum(d > 0 for d in pairs.values())}


def figures(res: Results) -> dict[str, Any]:
    """{"default"|"pbr"|"chosen": {metric: pair(new - product)}, "default_minus_pbr": {metric: {side: pair(...)}}}
    over the objects both sides have ("chosen": where `res` has that row, `chosen`)."""
    out: dict[str, Any] = {"default": {}, "pbr": {}, "chosen": {}, "default_minus_pbr": {}}
    for m in METRICS:
        if paired_values(res, "new", "product", m):
            out["default"][m] = pair(res, "new", "product", m)
        if paired_values(res, "chosen", "product", m):
            out["chosen"][m] = pair(res, "chosen", "product", m)
        if paired_values(res, "new_pbr", "product_pbr", m):
            out["pbr"][m] = pair(res, "new_pbr", "product_pbr", m)
    both = set(paired_values(res, "new", "product", METRICS[0]))
    for m in METRICS[:2]:  # PathTrace and Relight clean, on the objects both sides have
        sub = {row: {mm: {o: v for o, v in vals.items() if o in both} for mm, vals in res[row].items()}
               for row in ("new", "new_pbr", "product", "product_pbr")}  # fmt: skip
        if paired_values(sub, "new", "new_pbr", m):
            out["default_minus_pbr"][m] = {"new": pair(sub, "new", "new_pbr", m),
                                           "product": pair(sub, "product", "product_pbr", m)}
    return out


def main() -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("new", help="FOLDER[+FOLDER...]: evaluation folders of the new extraction")
    parser.add_argument("--product", default=str(PRODUCT), help="FOLDER[+FOLDER...]: today's product's results")
    parser.add_argument("--keep", type=Path, default=None, help="copy the new folders' results to KEEP/results")
    parser.add_argument("--variant", default=NEW, help="the new extraction's eval variant")
    parser.add_argument("--margins", default="", help="comma-separated margins (dB) for the LMRM's start (--variant "
                        "default_choose_lmrm_start): the choice had it needed to win by that much")
    parser.add_argument("--no-record", action="store_true", help="print only; append no JSON line")
    args = parser.parse_args()
    new = [Path(p) for p in args.new.split("+") if p]
    product = [Path(p) for p in args.product.split("+") if p]
    res = chosen(joined(new, product, args.variant), held_out(new, args.variant), held_out(product, DEFAULT_VARIANT))
    figs = figures(res)
    if not figs["default"]:
        print(f"no object has {args.variant} and {PBR} in {args.new} and {DEFAULT_VARIANT} and {PBR} in "
              f"{args.product}")
        return 1
    n = figs["default"][METRICS[0]]["n"] if METRICS[0] in figs["default"] else 0
    print(f"the new extraction ({args.variant}, restated candidate) - today's ({DEFAULT_VARIANT}, shipped LMRM), "
          f"paired over {n} objects; mean +- standard error (objects ahead)")
    for side in ("default", "pbr", "chosen"):
        for m, f in figs[side].items():
            a, b = ROWS_PAIRED[side]
            print(f"  {side:8s} {m:22s} {f[b]:6.2f} -> {f[a]:6.2f}  {f['diff']:+.2f} +- {f['se']:.2f} "
                  f"({f['ahead']}/{f['n']})")
    for m, sides in figs["default_minus_pbr"].items():
        print(f"  the default - its PBR baseline, {m}: " + "  ".join(
            f"{side} {f['diff']:+.2f} +- {f['se']:.2f}" for side, f in sides.items()))
    margins = [float(v) for v in args.margins.split(",") if v.strip()]
    if margins:
        sides = sides_of(new, args.variant)
        res = with_margins(res, sides, margins, new)
        figs["margins"] = {}
        for start in SIDES:  # each start alone, also where the choice did not run (its plain run)
            figs["margins"][start] = {m: pair(res, start, "product", m) for m in METRICS
                                      if paired_values(res, start, "product", m)}  # fmt: skip
            print(f"  the {start.replace('_', ' ')} alone (its side of the choice, or its plain run) - today's: "
                  + "  ".join(f"{m} {f['diff']:+.2f} +- {f['se']:.2f} ({f['ahead']}/{f['n']})"
                              for m, f in figs["margins"][start].items()))
        print(f"  the LMRM's start taken only where it wins on held-out photos by more than a margin ({len(sides)} "
              "objects with both starts' results):")
        for margin in margins:
            row = f"margin {margin:g}"
            taken = sum(side["gap"] > margin for side in sides.values())
            figs["margins"][row] = {m: pair(res, row, "product", m) for m in METRICS
                                    if paired_values(res, row, "product", m)}  # fmt: skip
            print(f"    {row:11s} (LMRM's start on {taken}): " + "  ".join(
                f"{m} {f['diff']:+.2f} +- {f['se']:.2f}" for m, f in figs["margins"][row].items()))
            figs["margins"][f"{row} - pbr_start"] = {m: pair(res, row, "pbr_start", m) for m in METRICS
                                                     if paired_values(res, row, "pbr_start", m)}  # fmt: skip
            print(f"    {'':11s} over the PBR start alone (the same LMRM): " + "  ".join(
                f"{m} {f['diff']:+.2f} +- {f['se']:.2f} ({f['ahead']}/{f['n']})"
                for m, f in figs["margins"][f"{row} - pbr_start"].items()))
    if args.keep is not None:
        for folder in new:
            if (folder / "results").resolve() != (args.keep / "results").resolve():  # a kept folder is read too
                shutil.copytree(folder / "results", args.keep / "results", dirs_exist_ok=True)
    if not args.no_record:
        record = {"new": args.new, "variant": args.variant, "product": args.product, "figures": figs}
        print(f"wrote {write_result('lmrm_ship', record)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
