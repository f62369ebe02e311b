# Two commands on a fresh machine:  `make run` (enumerate n = 10)  and  `make test`.
# Both create the virtual environment .venv and install the package into it first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
N ?= 10

.PHONY: install run test test-fast clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $@

install: $(BIN)/.installed

run: install
	$(BIN)/packings enumerate $(N)

test: install
	$(BIN)/python -m pytest

test-fast: install
	$(BIN)/python -m pytest -m "not slow"

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .hypothesis
