#!/bin/bash
# Eval variants' clean, paired rows on benchmark objects that a fresh machine lacks the data for
# (docs/design-notes.md items 58 and 71): per object, synthesise it (`neumatex synth --shard I/40`, bit for bit the
# data the stored rows were made on), render its references, run the variants (bench/variants_clean.py), each step
# skipped or resumed where already done; an object on which every variant already has a row is skipped whole (no
# data made for it). VARIANTS is one name or several, comma-separated. With SINCE (UTC, e.g. 2026-12-03T22:20:00)
# only rows written since then count, so a baseline is run again on this machine beside a candidate: another
# machine's rows need not be this one's (item 71: the default's row on object 0 moved by 2.4 dB). Run two side by
# side on two cores, e.g.
#   nohup tools/variant_rows.sh pbr_start_default_settle_decdb 18 2 39 > runs/rows-a.log 2>&1 &
#   nohup tools/variant_rows.sh pbr_start_default_settle_decdb 19 2 39 > runs/rows-b.log 2>&1 &
#   SINCE=2026-12-03T22:20:00 nohup tools/variant_rows.sh BASELINE,CANDIDATE 0 2 39 > runs/rows-c.log 2>&1 &
# usage: [SINCE=ISO_TIME] tools/variant_rows.sh VARIANTS FIRST STEP LAST
set -u
cd "$(dirname "$0")/.."
export NEUMATEX_SHARED=${NEUMATEX_SHARED:-$(cd .. && pwd)/shared} OMP_NUM_THREADS=1
variants=$1
since=${SINCE:-}
mkdir -p data/benchmark-test
has_rows() {  # whether every variant has its row on object $1 (since $since), by bench/variants_clean.py's own rule
  .venv/bin/python - "$1" "$variants" "$since" <<'PY'
import sys
sys.path.insert(0, "bench")
from variants_clean import stored_rows
obj, variants, since = sys.argv[1:]
rows = stored_rows(since)
sys.exit(0 if all(obj in rows.get(v, {}) for v in variants.split(",")) else 1)
PY
}
for ((i=$2; i<=$4; i+=$3)); do
  id=$(printf "test-%06d" "$i")
  if has_rows "$id"; then echo "$(date -u +%T) $id already has its rows"; continue; fi
  echo "$(date -u +%T) $id synth"
  if [ ! -f "data/benchmark-test/$id/transforms.json" ]; then
    # one synth at a time: shards of one split share its manifest
    flock data/.synth.lock .venv/bin/neumatex synth --split test --n 40 --out data/benchmark-test --layered \
      --shard "$i/40" --workers 1 || { echo "$id: synth failed"; continue; }
  fi
  echo "$(date -u +%T) $id references"
  .venv/bin/neumatex references data/benchmark-test --objects "$id" --no-progress || { echo "$id: references failed"; continue; }
  echo "$(date -u +%T) $id variants"
  .venv/bin/python bench/variants_clean.py --variants "$variants" --objects "$id" --workers 1 \
    --work "runs/rows-${variants//,/+}-$i" ${since:+--since "$since"}
  echo "$(date -u +%T) $id done"
done
