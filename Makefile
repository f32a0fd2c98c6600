SHELL := /bin/bash
PYTHON ?= python3
LINT_PATHS = sb3_lifelong/ tests/ benchmarks/ examples/ setup.py
# the Robotis OP3 model is read from a local copy of mujoco-menagerie when one sits beside the checkout
MENAGERIE_ROOT ?= $(shell [ -d ../shared/menagerie ] && cd ../shared/menagerie && pwd)
export MENAGERIE_ROOT
# one torch / BLAS thread per process: on 2 shared cores more threads slow training down (see docs)
export OMP_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1
DEMO_DIR ?= demo_output

.PHONY: install test demo demo-mpo lint format check-codestyle type doc clean

# torch first, pinned to the CPU wheel: a bare "torch" requirement would download a CUDA build
install:
	$(PYTHON) -m pip install -q torch==2.13.0
	$(PYTHON) -m pip install -q -e ".[tests,extra,mujoco,cluster,docs]"

test: install
	$(PYTHON) -m pytest -n 2 --timeout 900 -rs tests/

# a short run of the paper's two-stage protocol (Env-A then Env-B, distillation of the lifetime buffer), then its
# report: tables, the pre-registered claims, figures (the "demo" preset: minutes; the study itself is "--preset cpu")
demo: install
	$(PYTHON) -m sb3_lifelong.experiments run --preset demo --seed 0 --output $(DEMO_DIR) --progress-bar
	$(PYTHON) -m sb3_lifelong.experiments report $(DEMO_DIR) --claims benchmarks/studies/paper_cpu/claims.py

# MPO alone on a small MuJoCo task, with a learning curve
demo-mpo: install
	$(PYTHON) examples/demo.py --output $(DEMO_DIR)/mpo

lint:
	$(PYTHON) -m ruff check $(LINT_PATHS)

format:
	$(PYTHON) -m ruff check --select I --fix $(LINT_PATHS)
	$(PYTHON) -m black $(LINT_PATHS)

check-codestyle:
	$(PYTHON) -m black --check $(LINT_PATHS)

type:
	$(PYTHON) -m mypy sb3_lifelong/

# nitpicky (-n) and warnings as errors (-W): every cross-reference must resolve. Offline: the links to SB3, Gymnasium,
# NumPy, PyTorch, pandas and Python come from docs/inventories (python docs/inventories/make_inventories.py).
# `make test` checks the same build (tests/test_docs.py).
doc:
	$(PYTHON) -m pip install -q -e ".[docs]"
	cd docs && $(PYTHON) -m sphinx -b html -n -W --keep-going . _build/html

clean:
	rm -rf build dist *.egg-info .pytest_cache .mypy_cache .ruff_cache docs/_build $(DEMO_DIR)
