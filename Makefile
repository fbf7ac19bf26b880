# Quick start (README): `make demo` installs into .venv and runs the demo;
# `make test` installs into .venv and runs the whole test suite (.ci/run calls it).
VENV ?= .venv
PYTHON ?= python3
BIN = $(VENV)/bin

$(BIN)/gridslam: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $@

.PHONY: demo test bench
demo: $(BIN)/gridslam
	$(BIN)/gridslam demo

# One BLAS thread per process: tests and services share two cores, and idle BLAS threads
# spinning on busy cores slow small matrix work a hundredfold.
test: $(BIN)/gridslam
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q

bench: $(BIN)/gridslam
	$(BIN)/gridslam bench
