#!/bin/bash
# Both branches of the default's uniform/textured choice on the Blender Cycles captures (docs/design-notes.md item
# 75): per capture, the forced variant the default did not choose, from the capture's kept scores under WORK
# (bench/cycles_matrix.sh with the default among VARIANTS made them), run by bench/cycles_extract.py beside the kept
# PBR and default scores; each appends its line to bench/results/cycles_extract.jsonl, with the choice's evidence in
# its selection. Run two side by side on two cores:
#   nohup tools/cycles_choice_flips.sh "teapot suzanne" > runs/cflips-0.log 2>&1 &
#   nohup tools/cycles_choice_flips.sh "cow cheburashka" > runs/cflips-1.log 2>&1 &
# usage: [WORK=runs/bench-cycles-extract-rr16] tools/cycles_choice_flips.sh "MESHES"
set -u
cd "$(dirname "$0")/.."
export NEUMATEX_SHARED=${NEUMATEX_SHARED:-$(cd .. && pwd)/shared} OMP_NUM_THREADS=1
work=${WORK:-runs/bench-cycles-extract-rr16}
default=pbr_start_default_settle_decdb_slr10_s900
for mesh in $1; do
  for preset in coat sheen metal diffuse; do
    capture=$mesh-$preset
    kept=$(.venv/bin/python - "$work/$capture/scores.json" "$default" <<'PY'
import json, sys
from pathlib import Path
path, default = Path(sys.argv[1]), sys.argv[2]
row = json.loads(path.read_text()).get(default, {}) if path.is_file() else {}
kept = row.get("selection", {}).get("uniform_kept")
print("" if kept is None else ("uniform" if kept else "textured"))
PY
)
    if [ -z "$kept" ]; then echo "$capture: no kept scores of $default under $work"; continue; fi
    flip=$([ "$kept" = uniform ] && echo textured || echo uniform)
    echo "$(date -u +%T) $capture kept $kept: running ${default}_$flip"
    .venv/bin/python bench/cycles_extract.py --threads 1 --variants "pbr,${default}_$flip" --work "$work" \
      "runs/cycles/$capture" | grep -v "^|"
  done
done
