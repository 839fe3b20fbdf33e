#!/usr/bin/env bash
# The LMRM trained on a lent GPU within BUDGET seconds of wall clock (issue 14, lever 4; docs/lmrm.md): the
# machine's CPU cores synthesise the train split (`neumatex synth`, 128 px views) while the GPU trains on the objects
# already made (the object list is re-read every epoch; `--resident` keeps each object on the GPU after its first
# use, so the samples are made there). A short calibration run times a step (tqdm's rate at its end); the real run's step count
# fills what is left of the budget, so its schedule (warm-up, cosine decay) ends inside it.
#   OUT=/tmp/out BUDGET=480 NEUMATEX_SHARED=.shared tools/train_lmrm_gpu.sh
# Output in OUT: per run NAME.tar (lmrm.safetensors + lmrm.json (record: data, compute used), curves.png/json),
# train.log, synth.log, cache.log.
#   RUNS='a gpu 8 1e-3;b cpu 16 1e-3' ... trains the named runs side by side on the same objects.
set -uo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-out/lmrm-gpu}; budget=${BUDGET:-480}; py=${PYTHON:-python3}
data=${DATA:-data/synth-train-gpu}; cache=${CACHE:-data/lmrm-cache-gpu}; work=${WORK:-runs/lmrm/gpu}
res=${RES:-128}; spp=${SPP:-8}
workers=${WORKERS:-12}; cachers=${CACHERS:-2}; first=${FIRST_OBJECTS:-24}; tail_s=${TAIL_S:-40}
start=$(date +%s)
elapsed() { echo $(( $(date +%s) - start )); }
mkdir -p "$out" "$work" "$cache"
log="$out/train.log"
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null | tee "$log"
nx() { "$py" -m neumatex_core.cli "$@"; }
setsid "$py" -m neumatex_core.cli synth --split train --n 100000 --out "$data" --resolution "$res" --spp "$spp" --photos 0 --relight-maps 0 \
   --workers "$workers" --no-progress > "$out/synth.log" 2>&1 &
synth=$!  # its own process group: killing the group stops its worker processes too
# Cache the finished objects beside the trainer, so it seldom waits on one (data.build_cache; shards by index).
cacher_pids=()
for k in $(seq 0 $((cachers - 1))); do
  "$py" - "$data" "$cache" "$k" "$cachers" <<'PY' >> "$out/cache.log" 2>&1 &
import sys, time
from pathlib import Path
from neumatex_core.lmrm.data import build_cache, finished_objects
data, cache, k, n = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
done: set[str] = set()
while True:
    found = finished_objects(data) if data.is_dir() else []
    for f in [f for f in found if f.name not in done and int(f.name.rsplit("-", 1)[-1]) % n == k]:
        try:
            build_cache(f, cache)
        except Exception as exc:  # the trainer will name it; this helper only saves it time
            print(f"{f}: {exc}", flush=True)
        done.add(f.name)
    time.sleep(2)
PY
  cacher_pids+=($!)
done
finished() { ls "$data"/train-*/meta.json 2>/dev/null | wc -l; }
while [ "$(finished)" -lt "$first" ] && [ "$(elapsed)" -lt 120 ]; do sleep 2; done
echo "t=$(elapsed)s: $(finished) objects made; calibrating" | tee -a "$log"
# RUNS: "name preset batch lr" entries separated by ';', trained side by side on the same objects.
IFS=';' read -ra runs <<< "${RUNS:-main gpu 8 1e-3}"
train() { local preset=$1 batch=$2 lr=$3; shift 3
          nx train-lmrm --data "$data" --cache "$cache" --preset "$preset" --batch-size "$batch" --lr "$lr" \
             --resident --threads 1 "$@"; }
calibration_pids=()
for r in "${runs[@]}"; do
  set -- $r
  train "$2" "$3" "$4" --out "$work/$1-calibrate" --steps 60 --pbr-steps 20 --warmup 5 --val-every 1000 \
        --checkpoint-every 1000 --no-resume > "$work/$1-calibrate.log" 2>&1 &
  calibration_pids+=($!)
done
for p in "${calibration_pids[@]}"; do wait "$p"; done
# Steps from the step rate tqdm reports at the calibration's end (start-up excluded) times RATE_SCALE: the runs go
# faster once every object is on the GPU and the calibrations no longer share it (2026-11-29, three runs side by
# side: 1.97 steps/s at calibration, 3.4 in the run; the validations cost the rest).
left=$(( budget - $(elapsed) - tail_s ))
rate() { "$py" -c "import re,sys; m=re.findall(r'([0-9.]+)(step/s|s/step)', open(sys.argv[1]).read()); v,u=m[-1]; v=float(v); print(v if u=='step/s' else 1/v)" "$1"; }
run_pids=()
for r in "${runs[@]}"; do
  set -- $r
  steps=$("$py" -c "print(max(100, int($left * $(rate "$work/$1-calibrate.log") * ${RATE_SCALE:-1.4})))")
  echo "t=$(elapsed)s: run $1 ($2, batch $3, lr $4): $(rate "$work/$1-calibrate.log") steps/s at calibration; $steps steps in the $left s left" | tee -a "$log"
  train "$2" "$3" "$4" --out "$work/$1" --steps "$steps" --pbr-steps $(( steps / 8 )) --warmup $(( steps / 50 + 5 )) \
        --val-every $(( steps / 10 + 1 )) --checkpoint-every 500 --val-objects 16 > "$work/$1.log" 2>&1 &
  run_pids+=($!)
done
rc=0
for p in "${run_pids[@]}"; do wait "$p" || rc=$?; done
kill -- -"$synth" 2>/dev/null; kill "${cacher_pids[@]}" 2>/dev/null; wait 2>/dev/null
echo "t=$(elapsed)s: training exit $rc; $(finished) objects synthesised, $(ls "$cache" | wc -l) cached" | tee -a "$log"
for r in "${runs[@]}"; do
  set -- $r
  grep -v "step/s\|s/step" "$work/$1.log" | tail -3 >> "$log"
  tar -cf "$out/$1.tar" -C "$work/$1" lmrm.safetensors lmrm.json curves.png curves.json 2>/dev/null
done
tail -3 "$out/synth.log" >> "$log"
exit $rc
