#!/usr/bin/env bash
# The wheels a lent GPU machine lacks (environment.md: it has torch, numpy, transformers, accelerate and the like but no
# network), at the versions of this checkout's virtual environment, for CPython 3.12 on manylinux x86-64, into
# outputs/wheels/ (ignored by git; what scripts/gpu_lease.sh installs). LEAN=1 leaves out optuna and its database
# packages (only the test suite and the tuning use them) for a carry that also holds an earlier lease's prior.
# Usage: [LEAN=1] scripts/fetch_gpu_wheels.sh [PYTHON] [DEST]      (needs network here; ~19 MiB, ~13 MiB lean)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${1:-.venv/bin/python}"
DEST="${2:-outputs/wheels}"
packages=(gsplat tyro docstring-parser typeguard typing-extensions plyfile pytorch-msssim pypng diffusers psutil)
[[ "${LEAN:-0}" == 1 ]] || packages+=(optuna alembic colorlog sqlalchemy greenlet mako)
"$PYTHON" -c "import pip" 2>/dev/null \
    || { echo "fetch_gpu_wheels: $PYTHON does not run or has no pip (run make setup first, or name a Python)" >&2; exit 2; }
mkdir -p "$DEST"
for package in "${packages[@]}"; do
    if ! version=$("$PYTHON" -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$package" 2>/dev/null); then
        echo "fetch_gpu_wheels: $package is not installed in $PYTHON's environment: skipped" >&2
        continue
    fi
    "$PYTHON" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        -d "$DEST" "$package==$version"
done
du -sh "$DEST"
