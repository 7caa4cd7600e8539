# Two entry points on a fresh machine: `make demo` and `make test`.
# Both create .venv and install the project with its dev tools first.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
DATA   ?= ../shared/data
OUT    ?= out/loop600
# Small dense matrices: multi-threaded BLAS only adds contention (docs/results/performance.md),
# so every target runs single-threaded BLAS.
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1
# Two workers match the 2-core CI machine.
PYTEST_WORKERS ?= 2

.PHONY: venv demo test lint typecheck unit docs bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $@

venv: $(VENV)/.installed

# loop600 (dense: fusion changes little) and, beside it, loop600-sparse (the paper's
# regime: fusion's gap shows), each with its table and figures.
demo: venv
	$(VENV)/bin/mapfuse compare loop600 --seed 0 --beside loop600-sparse --out $(OUT) --force
	@echo "Demo done: open $(OUT)/report.md (loop600, then loop600-sparse beside it)."
	@echo "Fusion's effect: $(OUT)/fig7_error_fusion.png (loop600: small) against"
	@echo "  $(OUT)/beside/loop600-sparse/fig7_error_fusion.png (the paper's regime: large)."

lint: venv
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

typecheck: venv
	$(VENV)/bin/mypy mapfuse_core ekf_reference mapfuse_graph mapfuse

unit: venv
	MAPFUSE_DATA=$(DATA) $(PY) -m pytest -n $(PYTEST_WORKERS) -q

# The guide and the API reference into build/site; any warning (a dead link, a page
# missing from the nav) fails the build (tests/test_docs_build.py shows it can).
docs: venv
	$(VENV)/bin/mkdocs build --strict

test: lint typecheck docs unit

bench: venv
	$(PY) benchmarks/bench_simulate.py
	$(PY) benchmarks/bench_ekf.py
	$(PY) benchmarks/bench_graph.py
	$(PY) benchmarks/bench_isam2_sparse.py
	$(PY) benchmarks/bench_real.py --data $(DATA)

clean:
	rm -rf $(VENV) out .pytest_cache .mypy_cache .ruff_cache .hypothesis
