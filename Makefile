# Every target that needs the package installs it first (into .venv), so on a fresh
# machine with only Python 3.11 and make, `make demo` and `make test` do all set-up.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
TEST_WORKERS ?= 2

.PHONY: install demo test lint docs bench clean study

install: $(STAMP)

# Stale when pyproject.toml changes (dependencies) or the venv is missing.
$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade "pip>=23"
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

demo: $(STAMP)
	$(BIN)/affinebody demo

# One BLAS thread per worker (small matrices: threading only adds contention); xdist uses the
# cores, one test file per worker at a time so jit caches and module fixtures are not duplicated,
# the longest files first (tests/conftest.py, LONGEST_FIRST: xdist keeps that order only with
# --no-loadscope-reorder).
test: $(STAMP)
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python -m pytest -q -n $(TEST_WORKERS) \
		--dist loadfile --no-loadscope-reorder

# The documentation site (docs/, Sphinx + MyST): every page read afresh (-E) and every tutorial
# executed (a broken example fails the build), warnings are errors; HTML in docs/_build/html.
DOCS_STAMP := $(VENV)/.installed-docs

$(DOCS_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[dev,docs]'
	@touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	rm -rf docs/_autosummary
	PATH="$(abspath $(BIN)):$$PATH" OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 \
		$(BIN)/sphinx-build -W --keep-going -E -b html docs docs/_build/html
	@echo "documentation: docs/_build/html/index.html"

# The thermal study of the docs (docs/thermal-study.md): two NPT sweeps of the demo crystal
# (`affinebody sweep` on a local Dask cluster of 2 workers, about 10-15 min on 2 cores); writes
# the configs, data and plots into docs/figures/thermal (committed: `make docs` does not run it).
study: $(STAMP)
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/python benchmarks/thermal_study.py \
		--out docs/figures/thermal

lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info .pytest_cache docs/_build docs/_autosummary
