#!/usr/bin/env bash
# Training captures and sparse reconstructions for the render-repair model (issue 59). Six shape x material pairs
# of `diamond-sss synth` on the project's own rig (camera radius 4, 32-degree field of view), none of them a
# benchmark object (bunny/wax, torus/soap, blob/marble, bust/jade) nor a held-out one of scripts/make_heldout_data.sh
# (its knot shape, blob/wax, bust/soap): each a complete 24 x 12 lattice at 64 px, 64 spp, no test split. Then, per
# capture, regime images=9 / images=30 and seed 0 / 1, the pipeline's short-run preliminary reconstruction
# (`--preset sss3dgs --short-run`, 1000 steps), two at a time; then the repair pairs: those reconstructions' renders
# at 200 of the lattice images they did not see, against the true images (`diamond-sss repair-data`).
# Not committed: written to outputs/repair/ (captures/<name>, runs/<name>_images<N>_seed<S>, pairs/). Resumable: a
# finished capture (meta.json), run (model.safetensors) or pair file is skipped.
# Then trains the model into outputs/repair/train (`diamond-sss repair-train`, resumable).
# Usage: scripts/make_repair_data.sh [PYTHON]   (about 70 min on 2 CPU cores)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${1:-.venv/bin/python}"
OUT=outputs/repair
OBJECTS=(bunny:skin:41 sphere:jade:42 torus:glazed_wax:43 blob:soap:44 bust:marble:45 torus:skin:46)
cli() { "$PYTHON" -m diamond_sss.cli.main "$@"; }

for spec in "${OBJECTS[@]}"; do
    IFS=: read -r shape material seed <<< "$spec"
    name="${shape}_${material}"
    [[ -f "$OUT/captures/$name/meta.json" ]] || cli synth --shape "$shape" --material "$material" \
        --out "$OUT/captures/$name" --views 24 --lights 12 --test-views 0 --test-lights 0 --size 64 --spp 64 \
        --seed "$seed"
done

jobs=()
for spec in "${OBJECTS[@]}"; do
    IFS=: read -r shape material seed <<< "$spec"
    for images in 9 30; do for run_seed in 0 1; do jobs+=("${shape}_${material} $images $run_seed"); done; done
done
train_one() {
    local name=$1 images=$2 seed=$3 run="$OUT/runs/${1}_images${2}_seed${3}"
    [[ -f "$run/model.safetensors" ]] && return 0
    "$PYTHON" -m diamond_sss.cli.main train --data "$OUT/captures/$name" --out "$run" --regime "images=$images" \
        --preset sss3dgs --short-run --iterations 1000 --seed "$seed" --resume --quiet
}
pairs_of() {
    "$PYTHON" -m diamond_sss.cli.main repair-data --run "$OUT"/runs/"$1"_* --out "$OUT/pairs" --most 200 --quiet
}
export -f train_one pairs_of
export OUT PYTHON
printf '%s\n' "${jobs[@]}" | xargs -P 2 -L 1 bash -c 'train_one $0 $1 $2'
names=()
for spec in "${OBJECTS[@]}"; do IFS=: read -r shape material seed <<< "$spec"; names+=("${shape}_${material}"); done
printf '%s\n' "${names[@]}" | xargs -P 2 -L 1 bash -c 'pairs_of $0'
du -sh "$OUT"/captures "$OUT"/runs "$OUT"/pairs
# the model: torus/skin's 4 pair files held out for validation (an object of the same rig the model never saw)
"$PYTHON" -m diamond_sss.cli.main repair-train --pairs "$OUT"/pairs/torus_skin_* \
    $(ls "$OUT"/pairs/*.safetensors | grep -v /torus_skin_) --validation-files 4 --out "$OUT/train"
# shipped as src/diamond_sss/assets/models/repair (cp "$OUT"/train/model/* there)
