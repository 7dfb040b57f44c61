# Two commands on a fresh machine: `make demo` and `make test`. Both set up .venv first.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.statmc-installed
export PYTHONUNBUFFERED := 1
# numba caches compiled kernels beside the sources; keep them out of the tree.
export NUMBA_CACHE_DIR := $(CURDIR)/.cache/numba

.PHONY: setup demo test bench bench-quality clean

setup: $(STAMP)

$(STAMP): pyproject.toml tools/ensure_llvm.sh
	@bash tools/ensure_llvm.sh
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@$(PY) -m pip install -q --disable-pip-version-check --upgrade pip
	@$(PY) -m pip install -q --disable-pip-version-check -e '.[test,nn]'
	@touch $(STAMP)

demo: $(STAMP)
	$(PY) -m statmc.demo --out out/demo

test: $(STAMP)
	$(PY) -m pytest -q tests

# Speed targets, each measured against a peer in the same run (a few minutes).
SPEED_BENCHES := bench_render bench_gem bench_analytic bench_sure bench_combine
bench: $(STAMP)
	@set -e; for b in $(SPEED_BENCHES); do echo "== bench/$$b.py"; $(PY) bench/$$b.py; done
	@echo "== bench/bench_progressive.py --only speed"; $(PY) bench/bench_progressive.py --only speed

# Quality at equal budget against cached high-spp references (long on a fresh machine:
# the references are rendered once into out/cache/).
bench-quality: $(STAMP)
	$(PY) bench/bench_quality_gem.py
	$(PY) bench/bench_quality_expected_error.py
	$(PY) bench/bench_progressive.py --only convergence
	$(PY) bench/bench_progressive.py --only sampling
	$(PY) bench/bench_quality_table.py

clean:
	rm -rf $(VENV) .cache out build *.egg-info
