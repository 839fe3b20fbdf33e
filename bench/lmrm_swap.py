"""The LMRM swap, measured before it is made: the extraction's default table (`neumatex eval --tables default`: the PBR
baseline, its head fine-tuned, the default) run once with the shipped LMRM and once with a candidate, on the same
objects and machine, compared per object (docs/design-notes.md items 84 and 95). The figure: each variant's
candidate - shipped, paired, and the default - PBR under each LMRM, which is what the swap would move.

    .venv/bin/neumatex eval data/benchmark-test --tables default --relight-views 0,8,16 --objects first:8 \\
        --out runs/swap/shipped --doc '' --record ''
    .venv/bin/neumatex eval data/benchmark-test --tables default --relight-views 0,8,16 --objects first:8 \\
        --lmrm-weights bench/candidates/NAME/lmrm.safetensors --out runs/swap/NAME --doc '' --record ''
    .venv/bin/python bench/lmrm_swap.py runs/swap/shipped runs/swap/NAME [--keep bench/results/lmrm-swap]

Each folder is an evaluation's --out (its results/<object>/<variant>.json are read; their work/ is not needed).
Only objects with every variant in both folders count, so a half-finished run is compared on what it has.
`--variants ours` pairs other variants the two folders hold (e.g. the paper's recipe, `--tables table1`).
`--keep DIR` copies both folders' eval.json and results/ to DIR/<folder name>/, small enough to commit, so that a
later session (on a fresh machine) can add objects and compare all of them. Appends one JSON line to
bench/results/lmrm_swap.jsonl.
"""

from __future__ import annotations

import json
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import argument_parser, write_result  # noqa: E402

from neumatex_core.eval.suite import Results, load_results, paired_difference, paired_values  # noqa: E402
from neumatex_core.eval.variants import DEFAULT_VARIANT, TABLES  # noqa: E402

VARIANTS = TABLES["default"]  # the PBR baseline, its head fine-tuned, the default
PBR = "pbr"
METRICS = ("psnr_pathtrace_clean", "psnr_relight_clean", "psnr_basecolor", "psnr_latents")


def complete_objects(folder: Path, variants: Sequence[str] = VARIANTS) -> set[str]:
    """Objects of an evaluation folder with a result for every one of `variants` (default: the default table's)."""
    results = folder / "results"
    if not results.is_dir():
        return set()
    return {d.name for d in results.iterdir() if all((d / f"{v}.json").is_file() for v in variants)}


def joined_folders(folders: Sequence[Path], canon: dict[str, str], required: Sequence[str] | None = None) -> Results:
    """The results of `canon`'s runs ({name: stored variant}) in several evaluation folders as one table, each object
    taken from the first folder that has a result for every `required` variant (default: all of `canon`'s)."""
    res: Results = {}
    seen: set[str] = set()
    for folder in folders:
        objects = sorted(complete_objects(folder, list(canon.values()) if required is None else required) - seen)
        seen |= set(objects)
        for name, rows in load_results(folder, objects, canon).items():
            for m, values in rows.items():
                res.setdefault(name, {}).setdefault(m, {}).update(values)
    return res


def joined(shipped: Path, candidate: Path, variants: Sequence[str] = VARIANTS) -> tuple[Results, list[str]]:
    """Both folders' results of `variants` in one table, the candidate's named `<variant>@candidate`, on the objects
    complete in both."""
    objects = sorted(complete_objects(shipped, variants) & complete_objects(candidate, variants))
    canon = {v: v for v in variants}
    res = load_results(shipped, objects, canon)
    for v, rows in load_results(candidate, objects, canon).items():
        if v in canon:
            res[f"{v}@candidate"] = rows
    return res, objects


def swap_figures(res: Results, variants: Sequence[str] = VARIANTS) -> dict[str, Any]:
    """{variant: {metric: {shipped, candidate, diff, se, n, ahead}}} (candidate - shipped, paired) and, where
    `variants` hold the default and PBR, {"default_minus_pbr": {metric: {shipped: [mean, se, n], candidate: ...}}}."""
    out: dict[str, Any] = {}
    for v in variants:
        for m in METRICS:
            pairs = paired_values(res, f"{v}@candidate", v, m)
            if not pairs:
                continue
            diff, se, n = paired_difference(res, f"{v}@candidate", v, m)
            out.setdefault(v, {})[m] = {
                "shipped": sum(res[v][m][o] for o in pairs) / n,
                "candidate": sum(res[f"{v}@candidate"][m][o] for o in pairs) / n,
                "diff": diff, "se": se, "n": n, "ahead": sum(d > 0 for d in pairs.values())}
    if DEFAULT_VARIANT not in variants or PBR not in variants:
        return out
    gaps: dict[str, Any] = {}
    for m in METRICS[:2]:
        gaps[m] = {side: list(paired_difference(res, f"{DEFAULT_VARIANT}{suffix}", f"{PBR}{suffix}", m))
                   for side, suffix in (("shipped", ""), ("candidate", "@candidate"))}
    out["default_minus_pbr"] = gaps
    return out


def keep(folder: Path, target: Path) -> None:
    """Copy an evaluation folder's eval.json and results/ (not its work/) to target/<folder name>/."""
    dest = target / folder.name
    (dest / "results").mkdir(parents=True, exist_ok=True)
    if (folder / "eval.json").is_file():
        shutil.copy2(folder / "eval.json", dest / "eval.json")
    shutil.copytree(folder / "results", dest / "results", dirs_exist_ok=True)


def main() -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("shipped", type=Path, help="the evaluation run with the shipped LMRM")
    parser.add_argument("candidate", type=Path, help="the evaluation run with the candidate (--lmrm-weights)")
    parser.add_argument("--keep", type=Path, default=None, help="copy both folders' results here")
    parser.add_argument("--no-record", action="store_true", help="print only; append no JSON line")
    parser.add_argument("--variants", default=",".join(VARIANTS),
                        help="comma-separated eval variants to pair (default: the default table's)")
    args = parser.parse_args()
    variants = [v for v in args.variants.split(",") if v]
    res, objects = joined(args.shipped, args.candidate, variants)
    if not objects:
        print(f"no object has all of {', '.join(variants)} in both {args.shipped} and {args.candidate}")
        return 1
    figures = swap_figures(res, variants)
    print(f"candidate - shipped LMRM, paired over {len(objects)} objects ({', '.join(o[-2:] for o in objects)}); "
          "mean +- standard error (objects ahead)")
    for v in variants:
        for m, f in figures.get(v, {}).items():
            print(f"  {v:26s} {m:22s} {f['shipped']:6.2f} -> {f['candidate']:6.2f}  "
                  f"{f['diff']:+.2f} +- {f['se']:.2f} ({f['ahead']}/{f['n']})")
    if "default_minus_pbr" in figures:
        print(f"the default ({DEFAULT_VARIANT}) - PBR under each LMRM")
    for m, sides in figures.get("default_minus_pbr", {}).items():
        print(f"  {m:22s} " + "  ".join(f"{side} {d:+.2f} +- {se:.2f} (n={n})" for side, (d, se, n) in sides.items()))
    if args.keep is not None:
        for folder in (args.shipped, args.candidate):
            keep(folder, args.keep)
    if not args.no_record:
        candidate_cfg = args.candidate / "eval.json"
        config = json.loads(candidate_cfg.read_text()).get("config", {}) if candidate_cfg.is_file() else {}
        weights = config.get("lmrm_weights", "")
        path = write_result("lmrm_swap", {"shipped": str(args.shipped), "candidate": str(args.candidate),
                                          "lmrm_weights": weights, "variants": variants, "objects": objects,
                                          "figures": figures})
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
