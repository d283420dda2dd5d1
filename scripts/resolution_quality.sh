#!/usr/bin/env bash
# Issue 17's quality against resolution and steps: the demo object rendered at 64, 128 and 256 px
# (scripts/make_resolution_data.sh, run here when its folders are missing), reconstructed with the shipped short-run
# settings at each STEPS count and scored beside each resolution's own noise ceiling (benchmarks/quality.py).
# SIZES (default "256 128 64") at each of STEPS, JOBS runs at a time (default 2), one thread each; tables in
# benchmarks/results/quality/resolution/res_<size>px_<steps>.{md,json}.
# Usage: [SIZES=...] [JOBS=N] scripts/resolution_quality.sh [STEPS ...]   (default: 1000 3000)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-.venv/bin/python}"
JOBS="${JOBS:-2}"
read -r -a SIZES <<< "${SIZES:-256 128 64}"
STEPS=("$@")
[[ $# -gt 0 ]] || STEPS=(1000 3000)
for size in "${SIZES[@]}"; do
    [[ "$size" =~ ^(64|128|256)$ ]] || { echo "resolution_quality: SIZES: $size px is not rendered by scripts/make_resolution_data.sh (64, 128, 256)" >&2; exit 2; }
done
for steps in "${STEPS[@]}"; do
    [[ "$steps" =~ ^[1-9][0-9]*$ ]] || { echo "resolution_quality: STEPS: '$steps' is not a positive step count" >&2; exit 2; }
done
DATA=outputs/resolution
[[ -d "$DATA/bunny_wax_256px_noise" ]] || scripts/make_resolution_data.sh "$PYTHON"
export OMP_NUM_THREADS=1 PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
run() {  # SIZE STEPS
    "$PYTHON" benchmarks/quality.py --data "$DATA/bunny_wax_$1px" --noise-reference "$DATA/bunny_wax_$1px_noise" \
        --iterations "$2" --variants "res$1_$2" --tag "res_$1px_$2" --results benchmarks/results/quality/resolution
}
jobs_left=()
for steps in "${STEPS[@]}"; do
    for size in "${SIZES[@]}"; do
        jobs_left+=("$size $steps")
    done
done
running=0
for job in "${jobs_left[@]}"; do
    read -r size steps <<< "$job"
    run "$size" "$steps" &
    running=$((running + 1))
    if (( running == JOBS )); then
        wait -n
        running=$((running - 1))
    fi
done
wait
