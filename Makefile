# The two commands of the README: `make run` (the main job) and `make test`. Both set
# everything up first.
VENV ?= .venv
PYTEST_ARGS ?=

.PHONY: setup run demo test test-slow test-kernel test-wheel bench-peers bench-calib clean

setup:
	@VENV=$(VENV) ./scripts/setup.sh

run: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(VENV)/bin/maglog run

demo: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(VENV)/bin/maglog demo

test: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(VENV)/bin/python -m pytest -n 2 $(PYTEST_ARGS)

test-slow: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(VENV)/bin/python -m pytest -n 2 -m slow $(PYTEST_ARGS)

# What the project promises byte for byte (wire bytes, card images, logs) checked again
# under another OpenBLAS kernel and without numpy's AVX-512 paths (CI: a digest that follows
# the machine's CPU cannot land).
KERNEL_ENV = OPENBLAS_CORETYPE=Prescott NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL AVX512_SPR"
test-kernel: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(KERNEL_ENV) $(VENV)/bin/python -m pytest -n 2 \
		tests/sim/test_scenario.py tests/sim/stimulus tests/system/test_backends.py \
		tests/cli/test_summary.py $(PYTEST_ARGS)

# The wheel as pip builds it, installed into a new venv, its first commands run.
test-wheel: setup
	VENV=$(VENV) ./scripts/wheel_check.sh

# The calibration benchmark and the peers it compares against (see bench/RESULTS.md).
bench-peers: setup
	VENV=$(VENV) ./scripts/peers.sh

bench-calib: bench-peers
	$(VENV)/bin/python bench/calib/run.py

clean:
	rm -rf build .pytest_cache
