# Two commands on a fresh machine:  `make run` (enumerate n = 10)  and  `make test`.
# Both create the virtual environment .venv and install the package into it first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
N ?= 10

.PHONY: install run test test-fast lint clean

SOURCES := pyproject.toml $(wildcard packings/*.py service/*.py service/*.json workers/*.py alembic/*.py alembic/*.mako alembic/versions/*.py)

# Installed as a user installs it, from the wheel (never editable): the tests
# run the code and the migrations the wheel carries.  Reinstalled when a source
# file changes; build/ goes first so that no deleted module lingers in the wheel.
$(BIN)/.installed: $(SOURCES)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	rm -rf build
	$(BIN)/python -m pip install --quiet '.[test]'
	rm -rf build
	touch $@

install: $(BIN)/.installed

run: install
	$(BIN)/packings enumerate $(N)

test: install
	$(BIN)/python -m pytest

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test-fast: install
	$(BIN)/python -m pytest -m "not slow"

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .hypothesis
