#!/usr/bin/env bash
# Judge a novel-view prior on issue 18's 30-image regime (CPU, after a GPU lease returned it): the pipeline with
# it on the three benchmark objects, beside the shipped model's rows (RESULTS, session 15-17), and what its
# generated views carry against the truth and the preliminary render (benchmarks/generated_views.py). The weights
# of the generated images were chosen for views worse than that render, so each setting is run three ways:
#   <tag>            the full pipeline with the prior (relighting with the shipped model);
#   <tag>_norelight  without the relighting stage (--pipeline-set augment=nvs);
#   <tag>_once       without relighting, each image drawn once at full weight (generated_as_real=102,
#                    synthetic_weight=1: what lifted true novel views to plain 17-view training).
# The first setting alone (it renders the captures and trains the sss3dgs runs that all three reuse), then the other
# two side by side, one thread each (~1 h on the 2-core CPU). Usage: scripts/judge_prior.sh MODEL_FOLDER [TAG] [PYTHON]
set -euo pipefail
cd "$(dirname "$0")/.."
MODEL="$(realpath "${1:?usage: scripts/judge_prior.sh MODEL_FOLDER [TAG] [PYTHON]}")"
TAG="${2:-gpuprior}"
PYTHON="${3:-.venv/bin/python}"
[[ -f "$MODEL/config.json" ]] || { echo "judge_prior: $MODEL is not a model folder (no config.json)" >&2; exit 2; }
export OMP_NUM_THREADS=1 PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
RESULTS=benchmarks/results/regimes/$TAG
OBJECTS=(src/diamond_sss/assets/data/demo torus:soap blob:marble)
regimes() {  # TAG_SUFFIX PIPELINE_SETTINGS...
    local suffix="$1"
    shift
    "$PYTHON" benchmarks/regimes.py --iterations 1000 --spp 64 --objects "${OBJECTS[@]}" --regimes "views=5,lights=6" \
        --methods full --no-dense --pipeline-set "nvs_model=$MODEL" "$@" --tag "$TAG$suffix" \
        --results "$RESULTS/full$suffix"
}
regimes ""  # alone: it renders the captures and trains the sss3dgs runs that the other two reuse
regimes _norelight augment=nvs &
norelight=$!
regimes _once augment=nvs generated_as_real=102 synthetic_weight=1 &
once=$!
wait "$norelight"  # each wait returns its run's status: set -e stops here if one failed
wait "$once"
mapfile -t runs < <("$PYTHON" -c 'import json, sys; print(*(r["run"] for r in json.load(open(sys.argv[1]))["rows"]), sep="\n")' \
    "$RESULTS/full/regimes.json")  # the pipeline folders regimes.py wrote
"$PYTHON" benchmarks/generated_views.py --tag "$TAG" --runs "${runs[@]}"
echo "judge_prior: tables in $RESULTS/ and benchmarks/results/generated_views/$TAG.md"
