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
$(STAMP): $(PY) pyproject.toml
	$(PIP) install --quiet torch==2.13.0
	$(PIP) install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# The whole fleet on this machine (replay server, learner, 2 simulated actors) until Ctrl-C; results in
# runs/<name>/. Extra flags go in ARGS, e.g. `make run ARGS="--max-actions 2000 --robot gripper"`.
run: $(STAMP)
	$(VENV)/bin/romannet up $(ARGS)

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(PY) -m pytest

lint: $(STAMP)
	$(VENV)/bin/ruff check .

bench: $(STAMP)
	$(VENV)/bin/romannet bench inference --json

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
