# The two commands of the README: `make run` (the main job) and `make test`. Both set
# everything up first.
VENV ?= .venv
PYTEST_ARGS ?=

.PHONY: setup run demo test test-slow bench-peers bench-calib clean

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

# The calibration benchmark and the peers it compares against (see bench/RESULTS.md).
bench-peers: setup
	VENV=$(VENV) ./scripts/peers.sh

bench-calib: bench-peers
	$(VENV)/bin/python bench/calib/run.py

clean:
	rm -rf build .pytest_cache
