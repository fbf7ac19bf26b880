# Quick start (README): `make demo` installs into .venv and runs the demo;
# `make test` installs into .venv, runs the linter (ruff) and the whole test suite (.ci/run calls it).
# Both install the versions constraints.txt pins, with which the golden results were taken.
VENV ?= .venv
PYTHON ?= python3
BIN = $(VENV)/bin

$(BIN)/gridslam: pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c constraints.txt -e '.[plots,ros,foxglove,test]'
	touch $@

.PHONY: demo test bench wheels docker-test
demo: $(BIN)/gridslam
	$(BIN)/gridslam demo

# The linter first ([tool.ruff] in pyproject.toml), then the suite: two test processes side by side
# (pytest-xdist, a module's tests in one of them), then the tests marked `serial`, which need the
# machine to themselves, one at a time. One BLAS thread per process: tests and services share two
# cores, and idle BLAS threads spinning on busy cores slow small matrix work a hundredfold.
test: $(BIN)/gridslam
	$(BIN)/ruff check .
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=15 -m "not serial"
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q --durations=10 -m serial

bench: $(BIN)/gridslam
	$(BIN)/gridslam bench

# Wheels of every dependency (and of setuptools, the project's build backend) for an image
# built without network: GRIDSLAM_WHEELS=true docker-compose build (docs/deploy.md). PYTHON
# must be the image's Python version (3.11) on its architecture.
wheels:
	$(PYTHON) -m pip wheel -q -c constraints.txt --wheel-dir deploy/wheels . 'setuptools>=70.1'
	rm -f deploy/wheels/gridslam-*.whl

# The image, the compose stack and the swarm stack on a real Docker engine (tests/e2e/test_docker.py;
# also part of `make test`). As root it installs and starts an engine where there is none.
docker-test: $(BIN)/gridslam
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q tests/e2e/test_docker.py
