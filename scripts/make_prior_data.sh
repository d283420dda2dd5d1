#!/usr/bin/env bash
# Training captures for a larger novel-view prior (issue 18's 30-image lever): every shape x material pair of
# `diamond-sss synth` except the 4 benchmark objects (bunny/wax, torus/soap, blob/marble, bust/jade) and the 3 held
# out by benchmarks/nvs_quality.py (torus/marble, bunny/soap, blob/jade): 23 pairs, each VIEWS views x 3 lights
# (the novel-view subset of a 40 x 24 lattice) at 64 px, 128 spp, with depth maps. Not committed: written to
# outputs/priors/ (about 1 MB per pair at 10 views) and packed into outputs/priors.tgz (10 MB), the form that
# travels to a lent GPU machine beside the wheels (its 64 MiB limit counts the checkout, ~40 MiB, too).
# Usage: scripts/make_prior_data.sh [PYTHON] [VIEWS]   (VIEWS default 10; Mitsuba, CPU)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${1:-.venv/bin/python}"
VIEWS="${2:-10}"
OUT=outputs/priors
EXCLUDED=" bunny_wax torus_soap blob_marble bust_jade torus_marble bunny_soap blob_jade "
seed=31
for shape in blob bunny bust sphere torus; do
    for material in glazed_wax jade marble skin soap wax; do
        name="${shape}_${material}"
        [[ "$EXCLUDED" == *" $name "* ]] && continue
        if [[ ! -f "$OUT/$name/meta.json" ]]; then  # written last: a finished capture
            "$PYTHON" -m diamond_sss.cli.main synth --shape "$shape" --material "$material" --out "$OUT/$name" \
                --views 40 --lights 24 --test-views 0 --test-lights 0 --size 64 --spp 128 --seed "$seed" \
                --subset "novelview:${VIEWS}x3"
        fi
        seed=$((seed + 1))
    done
done
tar czf "$OUT.tgz" -C "$(dirname "$OUT")" "$(basename "$OUT")"  # what a GPU machine is sent
du -sh "$OUT" "$OUT.tgz"
