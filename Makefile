# Two commands on a fresh machine: `make demo` and `make test`. Both set up .venv first.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.statmc-installed
export PYTHONUNBUFFERED := 1
# numba caches compiled kernels beside the sources; keep them out of the tree.
export NUMBA_CACHE_DIR := $(CURDIR)/.cache/numba

.PHONY: setup demo test bench clean

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

# Speed targets, each measured against a peer in the same run (see bench/*.py).
bench: $(STAMP)
	@set -e; for b in bench/bench_*.py; do echo "== $$b"; $(PY) $$b; done

clean:
	rm -rf $(VENV) .cache out build *.egg-info
