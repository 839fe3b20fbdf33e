#!/usr/bin/env bash
# Neural-basis candidates trained side by side on one lent GPU within BUDGET seconds (issue 14, lever 5;
# docs/design-notes.md item 30). Output: OUT/<name>.safetensors + .json per candidate, OUT/train.log.
#   OUT=out BUDGET=430 tools/train_basis_gpu.sh finetune   # v3a-c: warm-started from basis v2
#   OUT=out BUDGET=330 tools/train_basis_gpu.sh latent     # from scratch at latent sizes 6, 8 and 12
#   OUT=out BUDGET=390 tools/train_basis_gpu.sh aux        # a wider auxiliary (T, R) network at latent 6 and 12,
#                                                          # and c12: G12 (grow's g12) continued (item 77)
#   OUT=out BUDGET=420 tools/train_basis_gpu.sh grow       # basis v4 grown to latent 8 and 12 (and kept at 6) on
#                                                          # v4's render-unit objective; g8w4 weighs it twice (item 77)
#   OUT=out BUDGET=400 tools/train_basis_gpu.sh mix        # basis v5 continued, with the mixture family drawn 4x as
#                                                          # often, and grown to latent 16 (item 78)
#   OUT=out BUDGET=330 tools/train_basis_gpu.sh mix2       # g16m (mix's) continued: the mixture 4x / 8x as often,
#                                                          # and at half the rate (item 78)
set -uo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-out/basis-gpu}; budget=${BUDGET:-330}; py=${PYTHON:-python3}
mkdir -p "$out"
v2=neumatex_core/materials/data/bases/v2.safetensors
v4=neumatex_core/materials/data/bases/v4.safetensors
render="--render-weight 2 --render-base 0.5 --batch 65536 --lr 1e-3 --version ${VERSION:-v5}"
case "${1:-finetune}" in
  finetune) runs=("v3a --init $v2 --batch 65536 --lr 1e-3" "v3b --init $v2 --batch 16384 --lr 1e-3"
                  "v3c --init $v2 --batch 65536 --lr 3e-3") ;;
  latent) runs=("l6 --latent-dim 6 --lr 2e-3" "l8 --latent-dim 8 --lr 2e-3" "l12 --latent-dim 12 --lr 2e-3") ;;
  grow) runs=("g6 --init $v4 --latent-dim 6 $render" "g8 --init $v4 --latent-dim 8 $render"
              "g12 --init $v4 --latent-dim 12 $render" "g8w4 --init $v4 --latent-dim 8 $render --render-weight 4") ;;
  aux) g12=${G12:-runs/basis-v5/g12.safetensors}
       runs=("w6 --init $v4 --latent-dim 6 --aux-width 128 $render" "w6s --init $v4 --latent-dim 6 --aux-width 128 --aux-share 0.3 $render"
             "w12 --init $g12 --latent-dim 12 --aux-width 128 $render" "c12 --init $g12 --latent-dim 12 $render") ;;
  mix) v5=neumatex_core/materials/data/bases/v5.safetensors
       runs=("c12c --init $v5 --latent-dim 12 $render" "m12 --init $v5 --latent-dim 12 --mixture-weight 4 $render"
             "g16 --init $v5 --latent-dim 16 $render" "g16m --init $v5 --latent-dim 16 --mixture-weight 4 $render") ;;
  mix2) g16m=${G16M:-runs/basis-v6/g16m.safetensors}
        runs=("c16m --init $g16m --latent-dim 16 --mixture-weight 4 $render"
              "c16m8 --init $g16m --latent-dim 16 --mixture-weight 8 $render"
              "c16mh --init $g16m --latent-dim 16 --mixture-weight 4 $render --lr 5e-4") ;;
  *) echo "unknown set $1 (finetune, latent, grow, aux, mix, mix2)" >&2; exit 2 ;;
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
