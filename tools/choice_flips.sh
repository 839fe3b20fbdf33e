#!/bin/bash
# Both branches of the default's uniform/textured choice on benchmark objects (docs/design-notes.md item 75): per
# object, the forced variant the default did not choose (`..._s900_uniform` where its row kept textured,
# `..._s900_textured` where it kept uniform), run by bench/variants_clean.py like tools/variant_rows.sh runs a
# variant (the object's data and references must exist: make them with tools/variant_rows.sh). Its row records
# the choice's evidence too (held-out scores, the light slope of tto/baked_light.py). Resumable: an object whose
# flipped row exists is skipped by variants_clean.py. Run two side by side on two cores:
#   nohup tools/choice_flips.sh 0 2 39 > runs/flips-0.log 2>&1 &
#   nohup tools/choice_flips.sh 1 2 39 > runs/flips-1.log 2>&1 &
# usage: tools/choice_flips.sh FIRST STEP LAST
set -u
cd "$(dirname "$0")/.."
export NEUMATEX_SHARED=${NEUMATEX_SHARED:-$(cd .. && pwd)/shared} OMP_NUM_THREADS=1
default=pbr_start_default_settle_decdb_slr10_s900
for ((i=$1; i<=$3; i+=$2)); do
  id=$(printf "test-%06d" "$i")
  kept=$(.venv/bin/python - "$id" "$default" <<'PY'
import sys
sys.path.insert(0, "bench")
from variants_clean import own_rows
obj, default = sys.argv[1:]
rows = [r for r in own_rows() if r["variant"] == default and r["object"] == obj]  # the latest wins
kept = rows[-1].get("choice", {}).get("choice_uniform_kept") if rows else None
print("" if kept is None else ("uniform" if kept else "textured"))
PY
)
  if [ -z "$kept" ]; then echo "$id: no row of $default"; continue; fi
  flip=$([ "$kept" = uniform ] && echo textured || echo uniform)
  echo "$(date -u +%T) $id kept $kept: running ${default}_$flip"
  .venv/bin/python bench/variants_clean.py --variants "${default}_$flip" --objects "$id" --workers 1 \
    --work "runs/flips-$i"
  echo "$(date -u +%T) $id done"
done
