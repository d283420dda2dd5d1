#!/usr/bin/env bash
# Regenerates the synthetic data shipped in src/diamond_sss/assets/data/ (64x64, Mitsuba 3 volpath).
#   demo/             bunny in wax: full 40 views x 24 lights training lattice, 8 novel views x 6 novel
#                     lights test split, depth/normal maps.
#   finetune/<name>/  four other shape/material pairs, only the images diffusion fine-tuning uses
#                     (<= 7% of a 40 x 24 capture): 3 views x 10 lights (relighting) and 3 lights x 10 views
#                     (novel views), depth/normal maps of the views used, no test split.
# Usage: scripts/make_embedded_data.sh [PYTHON]   (about 20-40 min on 2 CPU cores)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${1:-.venv/bin/python}"
DATA=src/diamond_sss/assets/data
SPP=128

rm -rf "$DATA/demo" "$DATA/finetune"
"$PYTHON" -m diamond_sss.cli.main synth --shape bunny --material wax --out "$DATA/demo" \
    --views 40 --lights 24 --test-views 8 --test-lights 6 --size 64 --spp "$SPP" --seed 0

SUBSET="relight:3x10,novelview:10x3"
for spec in torus:jade:1 bust:marble:2 blob:soap:3 sphere:skin:4; do
    IFS=: read -r shape material seed <<< "$spec"
    "$PYTHON" -m diamond_sss.cli.main synth --shape "$shape" --material "$material" \
        --out "$DATA/finetune/${shape}_${material}" --views 40 --lights 24 --test-views 0 --test-lights 0 \
        --size 64 --spp "$SPP" --seed "$seed" --subset "$SUBSET"
done
du -sh "$DATA"
