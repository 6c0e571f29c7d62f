# The two Quick-start commands, and the setup they share.
# TORCH picks the PyTorch build: torch==2.13.0 is a CPU wheel on the project's CI machines;
# on a GPU workstation use e.g. `make test TORCH=torch`.
PYTHON ?= python3
TORCH ?= torch==2.13.0
EXTRAS ?= train,export,deploy,dev

.PHONY: setup demo test bench

setup:
	$(PYTHON) -m pip install --quiet "$(TORCH)" -e ".[$(EXTRAS)]"

demo: setup
	dssp-demo --out runs/demo

test: setup
	$(PYTHON) -m pytest -q

bench: setup
	$(PYTHON) benchmarks/train_step_time.py
