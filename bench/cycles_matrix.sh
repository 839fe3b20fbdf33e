#!/usr/bin/env bash
# Issue 14's Cycles table (docs/results.md, "Captures rendered by Blender Cycles"): the four Principled presets
# (coat, sheen, metal, diffuse) on four shared meshes, each rendered by Blender Cycles (`neumatex cycles-capture`,
# 64 px, 256 spp, under courtyard.exr turned 30 degrees; held-out photos at 8 random poses; relit under city.exr and
# forest.exr) twice, the second (<capture>.seed1) with another Cycles seed and the same poses so that the scores
# can be noise-corrected; then extracted with the default recipe and the PBR baseline by bench/cycles_extract.py,
# which prints the table per preset. Resumable: a capture whose cycles.json exists is kept (cycles.json is written
# last), and cycles_extract.py keeps each capture's scores. About 2 min of captures and 3 min of extraction per
# mesh and preset on 2 cores.
#
#   NEUMATEX_SHARED=../shared bench/cycles_matrix.sh
#   MESHES="teapot" PRESETS="coat sheen" THREADS=1 bench/cycles_matrix.sh     # a subset, one torch thread
#   VARIANTS=pbr,<default>,<candidate> WORK=runs/bench-cycles-extract-rr16 THREADS=1 bench/cycles_matrix.sh
#       # eval variants (neumatex_core/eval/variants.py) side by side, each capture's scores kept under WORK
set -euo pipefail
cd "$(dirname "$0")/.."
meshes=${MESHES:-"teapot suzanne cow cheburashka"}
presets=${PRESETS:-"coat sheen metal diffuse"}
captures=()
for mesh in $meshes; do
  for preset in $presets; do
    out=runs/cycles/$mesh-$preset
    for seed in 0 100003; do
      folder=$out$([ "$seed" = 0 ] || echo .seed1)
      if [ ! -f "$folder/cycles.json" ]; then
        .venv/bin/neumatex cycles-capture --mesh "$mesh.obj" --envmap courtyard.exr --envmap-yaw 30 \
          --preset "$preset" --resolution 64 --spp 256 --random 8 --seed "$seed" --pose-seed 0 --out "$folder" \
          --threads "${THREADS:-2}"
      fi
    done
    captures+=("$out")
  done
done
.venv/bin/python bench/cycles_extract.py --threads "${THREADS:-2}" ${VARIANTS:+--variants "$VARIANTS"} \
  ${WORK:+--work "$WORK"} "${captures[@]}"
