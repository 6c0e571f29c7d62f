# The two Quick-start commands, and the setup they share.
# TORCH picks the PyTorch build: torch==2.13.0 is a CPU wheel on the project's CI machines;
# on a GPU workstation use e.g. `make test TORCH=torch`.
PYTHON ?= python3
TORCH ?= torch==2.13.0
EXTRAS ?= train,export,deploy,hardware,sim,dev

.PHONY: system setup demo test bench

# pyrealsense2 needs the system's libusb-1.0 (Debian/Ubuntu: apt-get install libusb-1.0-0).
system:
	@ldconfig -p | grep -q 'libusb-1.0.so.0' || \
	  { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null; } || \
	  { echo "error: libusb-1.0 is missing; install it (sudo apt-get install libusb-1.0-0) and run make again"; exit 2; }

setup: system
	$(PYTHON) -m pip install --quiet "$(TORCH)" -e ".[$(EXTRAS)]"

demo: setup
	dssp-sim demo --out runs/demo --force

test: setup
	$(PYTHON) -m pytest -q

bench: setup
	$(PYTHON) benchmarks/train_step_time.py
