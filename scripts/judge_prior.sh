#!/usr/bin/env bash
# Judge a novel-view prior on the CPU (after a GPU lease returned it), in three parts (PARTS, default all three):
#  thirty  issue 18's 30-image regime on its three benchmark objects, each setting three ways (~1 h):
#            <tag>            the full pipeline with the prior (relighting with the shipped model);
#            <tag>_norelight  without the relighting stage (--pipeline-set augment=nvs);
#            <tag>_once       without relighting, each image drawn once at full weight (generated_as_real=102,
#                             synthetic_weight=1: what lifted true novel views to plain 17-view training);
#          then what its generated views carry against the truth and the preliminary render (generated_views.py).
#  nine    the 9-image regime on the four objects of the target's table (the sss3dgs runs shared; ~40 min).
#  views   benchmarks/nvs_quality.py on the three held-out objects with the true reference depth and with a 3% and
#          a 10% smooth depth error (what a sparse reconstruction gives the warp hint; ~20 min, the captures rendered
#          once into outputs/nvsq/data).
# The first run of each part alone where later ones reuse what it made, then the rest side by side, one thread each.
# Usage: [PARTS="thirty nine views"] scripts/judge_prior.sh MODEL_FOLDER [TAG] [PYTHON]
set -euo pipefail
cd "$(dirname "$0")/.."
MODEL="$(realpath "${1:?usage: scripts/judge_prior.sh MODEL_FOLDER [TAG] [PYTHON]}")"
TAG="${2:-gpuprior}"
PYTHON="${3:-.venv/bin/python}"
PARTS="${PARTS:-thirty nine views}"
[[ -f "$MODEL/config.json" ]] || { echo "judge_prior: $MODEL is not a model folder (no config.json)" >&2; exit 2; }
export OMP_NUM_THREADS=1 PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
RESULTS=benchmarks/results/regimes/$TAG

thirty() {  # TAG_SUFFIX PIPELINE_SETTINGS...
    local suffix="$1"
    shift
    "$PYTHON" benchmarks/regimes.py --iterations 1000 --spp 64 \
        --objects src/diamond_sss/assets/data/demo torus:soap blob:marble --regimes "views=5,lights=6" \
        --methods full --no-dense --pipeline-set "nvs_model=$MODEL" "$@" --tag "$TAG$suffix" \
        --results "$RESULTS/full$suffix"
}
nine() {  # OBJECT...
    "$PYTHON" benchmarks/regimes.py --iterations 1000 --spp 64 --objects "$@" --regimes "views=3,lights=3" \
        --methods sss3dgs full --no-dense --pipeline-set "nvs_model=$MODEL" --tag "$TAG" \
        --results "$RESULTS/nine_$(basename "${1//:/_}")"
}
views() {  # NAME [--depth-noise SIGMA 0]
    local name="$1"
    shift
    "$PYTHON" benchmarks/nvs_quality.py --data outputs/nvsq/data/{torus_marble_s21,bunny_soap_s22,blob_jade_s23} \
        --model "$MODEL" --steps 1 --guidance 1.0 --baseline-iterations 200 "$@" \
        --out "benchmarks/results/nvs_quality/$TAG/$name" --work "outputs/benchmarks/nvs_quality/$TAG/$name"
}

if [[ " $PARTS " == *" thirty "* ]]; then
    thirty ""  # alone: it renders the captures and trains the sss3dgs runs that the other two reuse
    thirty _norelight augment=nvs &
    norelight=$!
    thirty _once augment=nvs generated_as_real=102 synthetic_weight=1 &
    once=$!
    wait "$norelight"  # each wait returns its run's status: set -e stops here if one failed
    wait "$once"
    mapfile -t runs < <("$PYTHON" -c 'import json, sys; print(*(r["run"] for r in json.load(open(sys.argv[1]))["rows"]), sep="\n")' \
        "$RESULTS/full/regimes.json")  # the pipeline folders regimes.py wrote
    "$PYTHON" benchmarks/generated_views.py --tag "$TAG" --runs "${runs[@]}"
fi
if [[ " $PARTS " == *" nine "* ]]; then
    nine src/diamond_sss/assets/data/demo torus:soap &
    first=$!
    nine blob:marble bust:jade &
    second=$!
    wait "$first"
    wait "$second"
fi
if [[ " $PARTS " == *" views "* ]]; then
    seed=21
    for pair in torus:marble bunny:soap blob:jade; do  # nvs_quality.py's held-out objects, as its docstring renders them
        folder="outputs/nvsq/data/${pair/:/_}_s$seed"
        [[ -f "$folder/meta.json" ]] || "$PYTHON" -m diamond_sss.cli.main synth --shape "${pair%:*}" \
            --material "${pair#*:}" --seed "$seed" --out "$folder" --views 12 --lights 1 --size 64 --spp 32 \
            --test-views 0 --test-lights 0
        seed=$((seed + 1))
    done
    views true_depth &
    true_depth=$!
    views depth_error_3pct --depth-noise 0.03 0
    wait "$true_depth"
    views depth_error_10pct --depth-noise 0.10 0
fi
echo "judge_prior: tables in $RESULTS/, benchmarks/results/nvs_quality/$TAG/ and benchmarks/results/generated_views/$TAG.md"
