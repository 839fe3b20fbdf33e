#!/usr/bin/env bash
# Neural-basis candidates trained side by side on one lent GPU within BUDGET seconds (issue 14, lever 5;
# docs/design-notes.md item 30). Output: OUT/<name>.safetensors + .json per candidate, OUT/train.log.
#   OUT=out BUDGET=430 tools/train_basis_gpu.sh finetune   # v3a-c: warm-started from basis v2
#   OUT=out BUDGET=330 tools/train_basis_gpu.sh latent     # from scratch at latent sizes 6, 8 and 12
set -uo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-out/basis-gpu}; budget=${BUDGET:-330}; py=${PYTHON:-python3}
mkdir -p "$out"
v2=neumatex_core/materials/data/bases/v2.safetensors
case "${1:-finetune}" in
  finetune) runs=("v3a --init $v2 --batch 65536 --lr 1e-3" "v3b --init $v2 --batch 16384 --lr 1e-3"
                  "v3c --init $v2 --batch 65536 --lr 3e-3") ;;
  latent) runs=("l6 --latent-dim 6 --lr 2e-3" "l8 --latent-dim 8 --lr 2e-3" "l12 --latent-dim 12 --lr 2e-3") ;;
  *) echo "unknown set $1 (finetune, latent)" >&2; exit 2 ;;
esac
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null | tee "$out/train.log"
export OMP_NUM_THREADS=4 PYTHONUNBUFFERED=1
for r in "${runs[@]}"; do
  set -- $r
  name=$1; shift
  $py tools/train_basis_timed.py --name "$name" --out "$out" --budget-s "$budget" "$@" >> "$out/train.log" 2>&1 &
done
wait
cat "$out/train.log"
