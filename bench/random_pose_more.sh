#!/usr/bin/env bash
# Issue 18's end-to-end table grown one object at a time, resumable (docs/benchmark.md "Random-pose captures"):
# for each index of the test split, make the synthetic object (its shard of `neumatex synth`), its references, its
# random-pose capture, then bench/random_pose_e2e.py on it unless bench/results/random_pose_e2e.jsonl has it already.
# Every step keeps what is there, so an interrupted run picks up where it stopped. About 15 CPU-minutes per object.
# CORES (default 2) is how many cores it may use: CORES=1 leaves the other core to other work (the files come out
# byte for byte the same; torch threads beyond the free cores spin and slow everything down).
#
#   NEUMATEX_SHARED=../shared bench/random_pose_more.sh 4 5 6 7
#   .venv/bin/python bench/random_pose_e2e.py --summarise
set -euo pipefail
cd "$(dirname "$0")/.."
data=data/benchmark-test
cores=${CORES:-2}
for i in "$@"; do
  id=$(printf "test-%06d" "$i")
  echo "== $id ($(date -u +%H:%M:%S))"
  .venv/bin/neumatex synth --split test --n 40 --layered --out "$data" --shard "$i/40" --no-progress
  .venv/bin/neumatex references "$data" --objects "$id" --workers "$cores" --no-progress
  .venv/bin/neumatex synth-random-pose "$data" --objects "$id" --photos 100 --threads "$cores"
  if grep -q "\"object\": \"$id\"" bench/results/random_pose_e2e.jsonl 2>/dev/null; then
    echo "$id: already in bench/results/random_pose_e2e.jsonl"
  else
    .venv/bin/python bench/random_pose_e2e.py --data "$data" --objects "$id" --workers 1
  fi
done
