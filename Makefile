# Set-up and entry points. `make demo` and `make test` are idempotent: the venv is built once and
# rebuilt only when pyproject.toml or constraints.txt change. --no-compile: Python compiles the modules it imports
# on first use instead (40 s less set-up on the 2-core CPU).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export HF_HUB_OFFLINE := 1
export TRANSFORMERS_OFFLINE := 1

.PHONY: demo test setup system-deps lint clean-venv gpu-setup gpu-check

setup: $(STAMP)

# Mitsuba's vectorised llvm variants need Debian's libllvm19; without it the scalar variant is used.
system-deps:
	@if [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1 && ! ldconfig -p | grep -q 'libLLVM.so.19\|libLLVM-19'; then \
		(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null) \
		|| echo "note: libllvm19 unavailable; Mitsuba falls back to its scalar variant"; \
	fi

$(STAMP): pyproject.toml constraints.txt
	$(MAKE) system-deps
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q --no-compile "torch==2.13.0" \
		|| $(BIN)/python -m pip install -q --no-compile "torch>=2.4" -c constraints.txt
	$(BIN)/python -m pip install -q --no-compile -c constraints.txt -e ".[all,dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/diamond-sss demo

# The distributed-study test starts its own PostgreSQL server; Debian's server programs are installed here.
test: $(STAMP)
	bash scripts/ci_postgres.sh || echo "note: PostgreSQL unavailable; tests/test_tune_postgres.py will skip"
	$(BIN)/python -m pytest -q

lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks

clean-venv:
	rm -rf $(VENV)

# On a CUDA machine: GPU_PYTHON is a Python whose torch is a CUDA build (kept: the project asks for torch>=2.4
# and nothing here pins a CPU build). gpu-setup installs the project into it; gpu-check builds gsplat's CUDA
# kernels, runs the CUDA tests, the whole suite, the speed benchmarks on CUDA and a demo-object reconstruction,
# and writes benchmarks/results/gpu_check/report.md and report.json.
GPU_PYTHON ?= python3
gpu-setup:
	$(GPU_PYTHON) -m pip install --no-build-isolation -e ".[all,dev]"

gpu-check:
	$(GPU_PYTHON) scripts/gpu_check.py $(GPU_CHECK_ARGS)
