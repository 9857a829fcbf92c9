# Two commands do all the set-up on a fresh machine: `make run` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.installed

.PHONY: run test lint bench clean install

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PIP) install --quiet --upgrade pip

# torch goes first and pinned: the CPU build lies on disk; an unpinned torch pulls a multi-GB CUDA build.
# Where pip would still pick a CUDA build: make run TORCH_PIP_ARGS="--index-url https://download.pytorch.org/whl/cpu"
TORCH_PIP_ARGS ?=
$(STAMP): $(PY) pyproject.toml
	$(PIP) install --quiet torch==2.13.0 $(TORCH_PIP_ARGS)
	$(PIP) install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# The best measured recipe as it was measured (dense clutter; 1 simulated actor, 2,500 actions), the whole
# fleet on this machine; results in runs/<name>/. Extra flags go in ARGS and win, e.g.
# `make run ARGS="--actors 2 --max-actions 0"` (0: until Ctrl-C).
run: $(STAMP)
	$(VENV)/bin/romannet up --config configs/experiments/clutter.toml --actors 1 --max-actions 2500 $(ARGS)

# Two workers: most of the suite waits on real processes and sockets, so two share the 2 cores well.
test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -n 2 --dist worksteal

lint: $(STAMP)
	$(VENV)/bin/ruff check .

bench: $(STAMP)
	$(VENV)/bin/romannet bench inference --json

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
