# The two commands of the README: `make demo` and `make test`. Both set everything up first.
VENV ?= .venv
PYTEST_ARGS ?=

.PHONY: setup demo test test-slow bench clean

setup:
	@VENV=$(VENV) ./scripts/setup.sh

demo: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(VENV)/bin/maglog demo

test: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(VENV)/bin/python -m pytest -n 2 $(PYTEST_ARGS)

test-slow: setup
	PATH="$(CURDIR)/$(VENV)/bin:$$PATH" $(VENV)/bin/python -m pytest -n 2 -m slow $(PYTEST_ARGS)

clean:
	rm -rf build .pytest_cache
