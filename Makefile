# icco-torchrl: every target sets up .venv on first use.
PYTHON     ?= python3
VENV       ?= .venv
TORCH_SPEC ?= torch==2.13.0
PY         := $(VENV)/bin/python
STAMP      := $(VENV)/.installed
ARGS       ?=
# pytest-xdist workers (one torch thread each): the suite's CLI runs keep two cores busy.
PYTEST_WORKERS ?= 2
# Modules whose docstring examples run with the tests (the runnable Examples: of the loss).
DOCTESTS   := icco_torchrl/objectives/icco_loss.py icco_torchrl/objectives/returns.py \
              icco_torchrl/envs/shaping.py icco_torchrl/modules/policy.py \
              icco_torchrl/modules/gru.py icco_torchrl/training/update.py \
              icco_torchrl/modules/activations.py icco_torchrl/methods.py \
              icco_torchrl/envs/layout.py icco_torchrl/envs/params.py \
              icco_torchrl/modules/__init__.py icco_torchrl/objectives/defaults.py

.PHONY: install test bench train eval sweep clean

install: $(STAMP)

# Quiet unless something fails: pip's output (and setuptools' warnings) go to the log, which is
# printed only when a step fails.
INSTALL_LOG := $(VENV).install.log

$(STAMP): pyproject.toml
	@echo "installing into $(VENV) (log: $(INSTALL_LOG))"
	@{ $(PYTHON) -m venv $(VENV) \
	  && $(PY) -m pip install -q --upgrade pip \
	  && $(PY) -m pip install -q "$(TORCH_SPEC)" \
	  && $(PY) -m pip install -q -e ".[dev,submitit]"; } > $(INSTALL_LOG) 2>&1 \
	  || { cat $(INSTALL_LOG); echo "make install failed: see $(INSTALL_LOG)"; exit 1; }
	@touch $(STAMP)

test: $(STAMP)
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/ruff check .
	OMP_NUM_THREADS=1 $(PY) -m pytest -n $(PYTEST_WORKERS) --dist loadgroup tests $(DOCTESTS) --doctest-modules $(ARGS)

bench: $(STAMP)
	$(PY) benchmarks/env_throughput.py
	$(PY) benchmarks/loss_step.py
	$(PY) benchmarks/train_throughput.py

train: $(STAMP)
	$(VENV)/bin/icco train experiment=make_train $(ARGS)

eval: $(STAMP)
	$(VENV)/bin/icco eval $(ARGS)

clean:
	rm -rf $(VENV) outputs multirun runs wandb .pytest_cache
