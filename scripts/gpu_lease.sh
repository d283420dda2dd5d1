#!/usr/bin/env bash
# scripts/gpu_check.py in one call on a lent GPU machine without network (the device tool of environment.md: the
# checkout and the carried paths travel, 64 MiB in all; what is left in $OUT comes back, at most 8 files).
# It installs the carried wheels (outputs/wheels/, which scripts/fetch_gpu_wheels.sh fills here), unpacks
# outputs/priors.tgz when it was carried (scripts/make_prior_data.sh writes it; `scripts/make_prior_rig_data.py --kind
# novel-view` adds captures on varied rigs, issue 57 item 4, and packs it again) and then trains the novel-view prior on
# those captures, runs gpu_check.py with the arguments given, and leaves in $OUT: report.md, the fp16 prior
# (nvs_prior_model/, when trained) and everything else packed into gpu_check.tgz (logs, report.json, speed tables,
# the prior's train_log.jsonl).
# The checkout is ~57 MB (session 55; the shipped models 16 MB, benchmarks/results/ 25 MB), so all wheels (~18 MB) and
# the captures (~10 MB; ~17 MB with the 23 rig captures) beside it exceed the 64 MiB that travel: a call that trains the prior carries the wheels without
# optuna and its database packages (~13 MB; only the suite and the tuning need them), made here by
# `LEAN=1 scripts/fetch_gpu_wheels.sh .venv/bin/python outputs/wheels_lean`, and names them in WHEELS; and since
# session 31 it also needs benchmarks/results/ moved out of the checkout for the call (`mv benchmarks/results
# /tmp/results_aside` before, back after: no GPU step reads it), which leaves ~55 MB (~62 MB with the rig captures).
# Carry ["outputs/wheels_lean", "outputs/priors.tgz"]:
#   WHEELS=outputs/wheels_lean OUT=$OUT scripts/gpu_lease.sh --skip build cuda-tests suite speed speed-raster \
#       nvs-speed train eval --prior-minutes 8 --prior-init src/diamond_sss/assets/models/nvs
#                       # the shipped prior trained on (no gsplat needed): ~2,300 steps of 32 images; then copy the
#                       # returned nvs_prior_model/ over it once scripts/judge_prior.sh has judged it
#       ... --prior-depth-noise 0.5 0.15 1   # the same on reference depth perturbed like a 3-view reconstruction's
#                       # render for half the references (benchmarks/sparse_depth.py; RESULTS, novel-view section)
#   WHEELS=outputs/wheels_lean OUT=$OUT scripts/gpu_lease.sh --skip suite speed speed-raster train eval \
#       --prior-minutes 6 --prior-init src/diamond_sss/assets/models/nvs   # CUDA tests, the step profiled, the prior
# Carry ["outputs/wheels"] (~58 MiB; no captures, so no prior):
#   scripts/gpu_lease.sh --skip speed speed-raster nvs-speed train eval   # the whole suite (~7 min there)
#   scripts/gpu_lease.sh --skip cuda-tests suite --iterations 10000        # speed + a 10k demo run
#   scripts/gpu_lease.sh --skip cuda-tests suite speed-raster train eval   # speed.py --profile alone
set -uo pipefail
cd "$(dirname "$0")/.."
: "${OUT:?OUT must name the folder whose files come back}"
wheels="${WHEELS:-outputs/wheels}"  # the carried wheels (scripts/fetch_gpu_wheels.sh)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$wheels"/*.whl \
    || { echo "gpu_lease: the wheels in $wheels/ did not install (fill it with scripts/fetch_gpu_wheels.sh and carry it)" >&2; exit 1; }
export PYTHONPATH="/tmp/site:$PWD/src" TORCH_EXTENSIONS_DIR=/tmp/torch_extensions
priors=()
if [[ -f outputs/priors.tgz ]]; then
    tar xzf outputs/priors.tgz -C outputs \
        || { echo "gpu_lease: outputs/priors.tgz did not unpack (damaged? pack it again: scripts/make_prior_data.sh)" >&2; exit 1; }
    priors=(--prior-data outputs/priors/*)
fi
work=/tmp/gpu_check
mkdir -p "$work"
python3 scripts/gpu_check.py --out "$work" "${priors[@]}" "$@"
code=$?
mkdir -p "$OUT"
[[ -f "$work/report.md" ]] && cp "$work/report.md" "$OUT/"
[[ -d "$work/nvs_prior_model" ]] && cp -r "$work/nvs_prior_model" "$OUT/"
[[ -f "$work/nvs_prior_run/train_log.jsonl" ]] && cp "$work/nvs_prior_run/train_log.jsonl" "$work/nvs_prior_train_log.jsonl"
tar czf "$OUT/gpu_check.tgz" -C "$work" --exclude nvs_prior_run --exclude nvs_prior_model --exclude demo_run \
    --exclude generation_work .
exit "$code"
