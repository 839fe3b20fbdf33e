#!/bin/bash
# One eval variant's clean, paired rows on benchmark objects that a fresh machine lacks the data for
# (docs/design-notes.md item 58): per object, synthesise it (`neumatex synth --shard I/40`, bit for bit the data
# the stored rows were made on), render its references, run the variant (bench/variants_clean.py), each step
# skipped or resumed where already done; an object whose row the variant already has is skipped whole (no data
# made for it). Run two side by side on two cores, e.g.
#   nohup tools/variant_rows.sh pbr_start_default_settle_decdb 18 2 39 > runs/rows-a.log 2>&1 &
#   nohup tools/variant_rows.sh pbr_start_default_settle_decdb 19 2 39 > runs/rows-b.log 2>&1 &
# usage: tools/variant_rows.sh VARIANT FIRST STEP LAST
set -u
cd "$(dirname "$0")/.."
export NEUMATEX_SHARED=${NEUMATEX_SHARED:-$(cd .. && pwd)/shared} OMP_NUM_THREADS=1
variant=$1
mkdir -p data/benchmark-test
has_row() {  # whether bench/results/variants_clean.jsonl already holds the variant's row on object $1
  grep -F "\"object\": \"$1\"" bench/results/variants_clean.jsonl 2>/dev/null | grep -qF "\"variant\": \"$variant\""
}
for ((i=$2; i<=$4; i+=$3)); do
  id=$(printf "test-%06d" "$i")
  if has_row "$id"; then echo "$(date -u +%T) $id already has a row"; continue; fi
  echo "$(date -u +%T) $id synth"
  if [ ! -f "data/benchmark-test/$id/transforms.json" ]; then
    # one synth at a time: shards of one split share its manifest
    flock data/.synth.lock .venv/bin/neumatex synth --split test --n 40 --out data/benchmark-test --layered \
      --shard "$i/40" --workers 1 || { echo "$id: synth failed"; continue; }
  fi
  echo "$(date -u +%T) $id references"
  .venv/bin/neumatex references data/benchmark-test --objects "$id" --no-progress || { echo "$id: references failed"; continue; }
  echo "$(date -u +%T) $id variant"
  .venv/bin/python bench/variants_clean.py --variants "$variant" --objects "$id" --workers 1 --work "runs/rows-$variant-$i"
  echo "$(date -u +%T) $id done"
done
