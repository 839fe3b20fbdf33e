"""The default's neural start blended with the LMRM's prediction, against the default, paired per object in the same
evaluation folders (docs/design-notes.md item 96): the eval variants of table `lmrm_start` (TTOConfig.lmrm_start_var,
and lmrm_start_anchor: anchored where the LMRM made the start) with the shipped LMRM and with a candidate restated
through the shipped decoders (bench/lmrm_restate.py), each against the default run in the same folder.

    .venv/bin/neumatex eval data/benchmark-test --tables lmrm_start --relight-views 0,8,16 --objects first:8 \\
        --out runs/swap/shipped --doc '' --record ''
    .venv/bin/python bench/lmrm_start.py shipped-lmrm=runs/swap/shipped NAME-restated=runs/swap/NAME-restated \\
        [--keep bench/results/lmrm-swap]

Each argument is NAME=FOLDER[+FOLDER...]: an evaluation's --out (several folders of one LMRM are read as one, their
objects joined). Per LMRM, each variant's paired difference from the default over the objects that have both
(mean +- standard error, objects ahead), and the mean weight the LMRM had in the start. `--keep DIR` copies each
LMRM's results/ (all its folders') to DIR/NAME/results/, small enough to commit: bench/results/lmrm-swap/ holds
those of design note 96 beside bench/lmrm_swap.py's, under the same names, so a later session can add objects.
Appends one JSON line to bench/results/lmrm_start.jsonl.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import argument_parser, write_result  # noqa: E402
from lmrm_swap import METRICS, complete_objects, joined_folders  # noqa: E402

from neumatex_core.eval.suite import Results, paired_difference, paired_values  # noqa: E402
from neumatex_core.eval.variants import DEFAULT_VARIANT, TABLES  # noqa: E402

VARIANTS = [v for v in TABLES["lmrm_start"] if v not in ("pbr", DEFAULT_VARIANT)]
WEIGHTS = ("choice_lmrm_start_weight_rho", "choice_lmrm_start_weight_latent")  # the configured basis's start's


def joined(folders: list[Path], variants: list[str]) -> tuple[Results, dict[str, dict[str, list[float]]]]:
    """The folders' results of the default and `variants` as one table (an object from the first folder that has
    it), and each variant's recorded start weights {variant: {object: [the LMRM's mean weight on rho_d, on the
    latent]}} (NaN where a result has none)."""
    res = joined_folders(folders, {v: v for v in [DEFAULT_VARIANT, *variants]}, [DEFAULT_VARIANT])
    weights: dict[str, dict[str, list[float]]] = {v: {} for v in variants}
    seen: set[str] = set()
    for folder in folders:
        objects = sorted(complete_objects(folder, [DEFAULT_VARIANT]) - seen)
        seen |= set(objects)
        for v in variants:
            for obj in objects:
                f = folder / "results" / obj / f"{v}.json"
                if f.is_file():
                    rec = json.loads(f.read_text())
                    weights[v][obj] = [float(rec.get(key, float("nan"))) for key in WEIGHTS]
    return res, weights


def figures(res: Results, variants: list[str]) -> dict[str, Any]:
    """{variant: {metric: {default, variant, diff, se, n, ahead}}}: variant - default, paired."""
    out: dict[str, Any] = {}
    for v in variants:
        for m in METRICS:
            pairs = paired_values(res, v, DEFAULT_VARIANT, m)
            if not pairs:
                continue
            diff, se, n = paired_difference(res, v, DEFAULT_VARIANT, m)
            out.setdefault(v, {})[m] = {"default": sum(res[DEFAULT_VARIANT][m][o] for o in pairs) / n,
                                        "variant": sum(res[v][m][o] for o in pairs) / n,
                                        "diff": diff, "se": se, "n": n, "ahead": sum(d > 0 for d in pairs.values())}
    return out


def main() -> int:
    parser = argument_parser(__doc__)
    parser.add_argument("runs", nargs="+", help="NAME=FOLDER[+FOLDER...]: one LMRM's evaluation folders")
    parser.add_argument("--keep", type=Path, default=None, help="copy each LMRM's results to KEEP/NAME/results")
    parser.add_argument("--no-record", action="store_true", help="print only; append no JSON line")
    args = parser.parse_args()
    record: dict[str, Any] = {}
    for spec in args.runs:
        name, _, paths = spec.partition("=")
        folders = [Path(p) for p in paths.split("+") if p]
        if not name or not folders:
            print(f"expected NAME=FOLDER[+FOLDER...], got {spec!r}")
            return 1
        res, weights = joined(folders, VARIANTS)
        figs = figures(res, VARIANTS)
        print(f"{name}: variant - the default ({DEFAULT_VARIANT}), paired; mean +- standard error (objects ahead)")
        for v in VARIANTS:
            shares = [[w[k] for w in weights[v].values() if w[k] == w[k]] for k in range(len(WEIGHTS))]
            rho, latent = (sum(x) / max(len(x), 1) for x in shares)
            print(f"  {v} (the LMRM's mean weight in the start: rho_d {rho:.2f}, latent {latent:.2f})")
            for m, f in figs.get(v, {}).items():
                print(f"    {m:22s} {f['default']:6.2f} -> {f['variant']:6.2f}  {f['diff']:+.2f} +- {f['se']:.2f} "
                      f"({f['ahead']}/{f['n']})")
        record[name] = {"folders": [str(f) for f in folders], "figures": figs, "weights": weights}
        if args.keep is not None:
            for folder in folders:
                shutil.copytree(folder / "results", args.keep / name / "results", dirs_exist_ok=True)
    if not args.no_record:
        print(f"wrote {write_result('lmrm_start', {'variants': VARIANTS, 'runs': record})}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
