# The two Quick-start commands, and the setup they share.
# TORCH picks the PyTorch build: torch==2.13.0 is a CPU wheel on the project's CI machines;
# on a GPU workstation use e.g. `make test TORCH=torch`.
PYTHON ?= python3
TORCH ?= torch==2.13.0
EXTRAS ?= train,export,deploy,hardware,sim,viz,ros,lerobot,dev
# Test workers (pytest-xdist), one per core; each test file runs whole in one worker (its fixtures built once).
TEST_WORKERS ?= auto

.PHONY: system setup packages kernel-or-note kernel kernel-aarch64 qgemm-bench block-bench demo test test-slow bench

# The fused Mamba operators for ONNX Runtime (optional at run time; see dssp_deploy/kernel/). Built against
# ONNX Runtime's C API headers: fetched from Debian 13's libonnxruntime-dev into build/ort-include, or taken
# from ORT_INCLUDE_DIR (the include/ folder of an ONNX Runtime release).
CXX ?= g++
KERNEL := dssp_deploy/kernel/libdssp_mamba.so
ORT_INCLUDE_DIR ?= build/ort-include
KERNEL_FLAGS ?= -O3 -std=c++17 -fPIC -shared -fvisibility=hidden -fopenmp-simd -fno-trapping-math -Wall -Wextra

# pyrealsense2 needs the system's libusb-1.0 (Debian/Ubuntu: apt-get install libusb-1.0-0). The tests of the int8
# products and of the int8 block (tests/test_qgemm.py, tests/test_block_harness.py) cross-build their harnesses for
# aarch64 and run them under qemu: g++-aarch64-linux-gnu and qemu-user.
system:
	@ldconfig -p | grep -q 'libusb-1.0.so.0' || \
	  { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null; } || \
	  { echo "error: libusb-1.0 is missing; install it (sudo apt-get install libusb-1.0-0) and run make again"; exit 2; }
	@{ command -v aarch64-linux-gnu-g++ && command -v qemu-aarch64; } >/dev/null || \
	  { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && apt-get update -qq && apt-get install -y -qq g++-aarch64-linux-gnu qemu-user >/dev/null; } || \
	  { echo "error: the aarch64 cross compiler or qemu is missing; install them (sudo apt-get install g++-aarch64-linux-gnu qemu-user) and run make again"; exit 2; }

# MetaWorld (dssp-sim's metaworld/NAME tasks) goes in without its dependencies: it declares mujoco==3.3.0 and runs on
# the MuJoCo installed here (dssp_sim/metaworld_env.py says how); pip's resolver reports that declaration.
METAWORLD ?= metaworld==3.1.1
# LeRobot (the oracle of tests/test_lerobot.py: it writes and reads LeRobot v3 datasets; lerobot-train with the DSSP
# policy plugin, plugins/lerobot_policy_dssp) goes in without its dependencies: it declares torch<2.11 and torchvision,
# and its dataset and training code runs on the torch installed here with the lerobot extra's packages
# (tests/test_lerobot.py says how it stands in for torchvision). The plugin goes in editable, without dependencies.
LEROBOT ?= lerobot==0.4.4

# The system packages, the Python packages and the kernel go in side by side (none needs another to install): each
# one's output is printed whole when it is done.
setup:
	@$(MAKE) --no-print-directory -j3 --output-sync=target system packages kernel-or-note

packages:
	$(PYTHON) -m pip install --quiet "$(TORCH)" -e ".[$(EXTRAS)]"
	@out=$$($(PYTHON) -m pip install --quiet --no-deps "$(METAWORLD)" 2>&1) || { echo "$$out"; exit 1; }; \
	  echo "$$out" | grep -v "requires mujoco==\|dependency resolver\|^$$" || true
	@out=$$($(PYTHON) -m pip install --quiet --no-deps "$(LEROBOT)" 2>&1) || { echo "$$out"; exit 1; }; \
	  echo "$$out" | grep -v "lerobot .* requires \|dependency resolver\|^$$" || true
	$(PYTHON) -m pip install --quiet --no-deps -e plugins/lerobot_policy_dssp

kernel-or-note:
	@$(MAKE) --no-print-directory kernel || echo "note: the fused Mamba kernel was not built; the standard ONNX graphs will run (see make kernel)"

kernel: $(KERNEL)

$(KERNEL): dssp_deploy/kernel/mamba_ops.cc dssp_deploy/kernel/mamba_block.h dssp_deploy/kernel/scan_simd.inc dssp_deploy/kernel/qgemm.h
	@[ -f "$(ORT_INCLUDE_DIR)/onnxruntime_lite_custom_op.h" ] || dssp_deploy/kernel/fetch_ort_headers.sh "$(ORT_INCLUDE_DIR)"
	$(CXX) $(KERNEL_FLAGS) -I"$(ORT_INCLUDE_DIR)" $< -o $@.tmp
	@mv $@.tmp $@

# The library for an aarch64 robot computer (Jetson Orin, Raspberry Pi 5), cross-built here: copy it beside the
# runtime there (or point DSSP_KERNEL at it).
KERNEL_AARCH64 := build/aarch64/libdssp_mamba.so

kernel-aarch64: $(KERNEL_AARCH64)

$(KERNEL_AARCH64): dssp_deploy/kernel/mamba_ops.cc dssp_deploy/kernel/mamba_block.h dssp_deploy/kernel/scan_simd.inc dssp_deploy/kernel/qgemm.h
	@[ -f "$(ORT_INCLUDE_DIR)/onnxruntime_lite_custom_op.h" ] || dssp_deploy/kernel/fetch_ort_headers.sh "$(ORT_INCLUDE_DIR)"
	@mkdir -p $(dir $@)
	aarch64-linux-gnu-g++ $(KERNEL_FLAGS) -I"$(ORT_INCLUDE_DIR)" $< -o $@.tmp
	@mv $@.tmp $@

# One denoiser step of int8 blocks at the robotwin preset's sizes without ONNX Runtime (dssp_deploy/kernel/
# block_check.cc --bench), on one thread and on two: the step and each part of a block, in microseconds.
BLOCK_BENCH := build/block/block_bench

block-bench:
	@mkdir -p build/block
	$(CXX) -O3 -std=c++17 -Wall -Wextra -fopenmp-simd -fno-trapping-math -pthread -o $(BLOCK_BENCH) dssp_deploy/kernel/block_check.cc
	$(BLOCK_BENCH) --bench 1
	$(BLOCK_BENCH) --bench 2

# The int8 products for a few rows (dssp_deploy/kernel/qgemm.h): the harness built with -O3, its parity line and
# the time of 12-row products per path this CPU runs (DSSP_QGEMM_PATH=<path> times that one alone), then this
# machine's read bandwidth to compare them with (numpy summing 512 MB once, best of 5, one thread).
QGEMM_BENCH := build/qgemm/qgemm_bench

qgemm-bench:
	@mkdir -p build/qgemm
	$(CXX) -O3 -std=c++17 -Wall -Wextra -o $(QGEMM_BENCH) dssp_deploy/kernel/qgemm_check.cc
	$(QGEMM_BENCH) --bench
	@$(PYTHON) -c "import time, numpy as np; a = np.ones(1 << 27, np.float32); \
	  best = min(e - s for s, _, e in ((time.perf_counter(), a.sum(), time.perf_counter()) for _ in range(5))); \
	  print(f'read bandwidth (numpy sum of 512 MB, best of 5, one thread): {a.nbytes / best / 1e9:.1f} GB/s')"

demo: setup
	dssp-demo --out runs/demo --force

test: setup
	$(PYTHON) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

# The long end-to-end tests (the memory smoke training, the two studies' quick plans): minutes each.
test-slow: setup
	$(PYTHON) -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m slow

bench: setup
	$(PYTHON) benchmarks/train_step_time.py
