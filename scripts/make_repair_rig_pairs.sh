#!/usr/bin/env bash
# Repair pairs from rigs that frame the object smaller than the priors' (issue 57 item 4: retraining measured against
# framing; session 52 measured it, and the shipped model is not trained on these: docs/pipeline.md, render repair).
# Six shape x material pairs, none a benchmark, held-out or scripts/make_repair_data.sh object, each on one of two
# rigs no held-out capture uses (A: cameras at radius 5.5 with a 40-degree field of view, the object ~51% of the
# image width, band z/r in [-0.1, 0.7]; B: radius 3.5, 48 degrees, ~67%, band [-0.4, 0.9]; their lights on other
# bands and radii): a complete 24 x 12 lattice at 64 px, and its framed twin (the same seed, so the same cameras and
# lights, with the field of view that frames the unit sphere as the priors' cameras do, ~90% of the width, as the
# pipeline frames the cameras it generates at). Each lattice's 9-image preliminary reconstructions (seeds 0 and 1;
# `--preset sss3dgs --short-run`, 1000 steps) are rendered at 200 of the twin's images they did not see
# (`diamond-sss repair-data --lattice`). Then the candidate model trains on these pairs and scripts/make_repair_data.sh's
# (run that first), the same 4 files held out, into outputs/repair/train_rigs.
# Resumable: a finished capture, run or pair file is skipped. Usage: scripts/make_repair_rig_pairs.sh [PYTHON]
# (about 25 min on 2 CPU cores)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${1:-.venv/bin/python}"
OUT=outputs/repair
RIG_A=(5.5 40 --camera-band -0.1 0.7 --light-radius 4.5 --light-band -0.5 1)  # camera radius, field of view, ...
RIG_B=(3.5 48 --camera-band -0.4 0.9 --light-radius 3 --light-band -1 1)
OBJECTS=(A:torus:jade:51 A:blob:skin:52 A:bunny:soap:53 B:bust:wax:54 B:sphere:marble:55 B:blob:glazed_wax:56)
cli() { "$PYTHON" -m diamond_sss.cli.main "$@"; }
framed_fov() {  # framed_fov RADIUS: the field of view (deg) framing the unit sphere at RADIUS as the priors' cameras
    "$PYTHON" -c "import math, sys; from diamond_sss.diffusion.nvs.canonical import PRIOR_FRAME_FILL as fill
print(round(2 * math.degrees(math.atan(math.tan(math.asin(1 / float(sys.argv[1]))) / fill)), 2))" "$1"
}
if ! ls "$OUT"/pairs/torus_skin_*.safetensors > /dev/null 2>&1; then
    echo "$OUT/pairs: no pairs of scripts/make_repair_data.sh; run it first" >&2
    exit 2
fi

names=()
for spec in "${OBJECTS[@]}"; do
    IFS=: read -r rig shape material seed <<< "$spec"
    name="rig${rig}_${shape}_${material}"
    names+=("$name")
    declare -n rig_args="RIG_$rig"
    radius=${rig_args[0]}
    for twin in "":${rig_args[1]} _framed:$(framed_fov "$radius"); do
        IFS=: read -r suffix fov <<< "$twin"
        [[ -f "$OUT/captures/$name$suffix/meta.json" ]] || cli synth --shape "$shape" --material "$material" \
            --out "$OUT/captures/$name$suffix" --views 24 --lights 12 --test-views 0 --test-lights 0 --size 64 \
            --spp 64 --seed "$seed" --camera-radius "$radius" --fov-x-deg "$fov" "${rig_args[@]:2}"
    done
    unset -n rig_args
done

train_one() {
    local run="$OUT/runs/${1}_images9_seed$2"
    [[ -f "$run/model.safetensors" ]] && return 0
    "$PYTHON" -m diamond_sss.cli.main train --data "$OUT/captures/$1" --out "$run" --regime images=9 \
        --preset sss3dgs --short-run --iterations 1000 --seed "$2" --resume --quiet
}
pairs_of() {
    "$PYTHON" -m diamond_sss.cli.main repair-data --run "$OUT"/runs/"$1"_images9_* --lattice "$OUT/captures/$1_framed" \
        --out "$OUT/pairs" --most 200 --quiet
}
export -f train_one pairs_of
export OUT PYTHON
for name in "${names[@]}"; do for seed in 0 1; do echo "$name $seed"; done; done | xargs -P 2 -L 1 bash -c 'train_one $0 $1'
printf '%s\n' "${names[@]}" | xargs -P 2 -L 1 bash -c 'pairs_of $0'
"$PYTHON" -m diamond_sss.cli.main repair-train --pairs "$OUT"/pairs/torus_skin_* \
    $(ls "$OUT"/pairs/*.safetensors | grep -v /torus_skin_) --validation-files 4 --out "$OUT/train_rigs"
