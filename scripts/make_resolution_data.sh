#!/usr/bin/env bash
# The demo object (bunny / wax) rendered again at 128 and 256 px for benchmarks/quality.py's resolution rows
# (issue 17), with small lattices so that a CPU renders them: 16 views x 8 lights at 64 and 128 px, 12 x 6 at 256 px,
# a 4 x 3 test split each, and a second render of each test split (the noise ceiling). Not committed: written to
# outputs/resolution/ (about 15 MB).
# Usage: scripts/make_resolution_data.sh [PYTHON]   (about 15-30 min on 2 CPU cores)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${1:-.venv/bin/python}"
OUT=outputs/resolution
for spec in 64:16:8 128:16:8 256:12:6; do
    IFS=: read -r size views lights <<< "$spec"
    "$PYTHON" -m diamond_sss.cli.main synth --shape bunny --material wax --out "$OUT/bunny_wax_${size}px" \
        --views "$views" --lights "$lights" --test-views 4 --test-lights 3 --size "$size" --spp 128 --seed 0
    "$PYTHON" -m diamond_sss.cli.main synth --shape bunny --material wax --out "$OUT/bunny_wax_${size}px_noise" \
        --views "$views" --lights "$lights" --test-views 4 --test-lights 3 --size "$size" --spp 128 --seed 0 \
        --noise-seed 1 --no-train
done
