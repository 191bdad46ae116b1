# Two commands set up a fresh machine: `make demo` and `make test`.
# Each creates .venv when missing, installs torch (CPU wheel) first, then the project.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# optional dependency groups: mpi is the MPICH wheel (`make EXTRAS=test` on a cluster whose
# own MPI mpi4py is built against, see deploy/README.md)
EXTRAS ?= mpi,test

.PHONY: demo test test-slow bench lint clean clean-numba gpu-train

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[$(EXTRAS)]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/minority demo

test: $(STAMP)
	$(BIN)/python -m pytest -q

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

bench: $(STAMP)
	@for b in bench/[a-z]*.py; do m=$$(basename $$b .py); echo "# bench.$$m" >&2; $(BIN)/python -m bench.$$m || exit 1; done

# the reference GNS trained on a GPU machine in one time-boxed command, with the machine's own
# python3 (deploy/gpu/train.sh; `make gpu-train TINY=1 PYTHON=.venv/bin/python`: a CPU smoke test)
gpu-train:
	sh deploy/gpu/train.sh

lint: $(STAMP)
	$(BIN)/ruff check .

# numba's on-disk cache tracks a kernel's own file only: clear it after editing a helper
# that other kernels inline (e.g. sim/svd.py, render_server/camera.py)
clean-numba:
	find . -not -path './$(VENV)/*' \( -name '*.nbi' -o -name '*.nbc' \) -delete

clean: clean-numba
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
