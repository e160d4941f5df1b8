# Two entry points for a fresh machine (Python 3.11 and make): `make run` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: run test lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

run: $(STAMP)
	$(VENV)/bin/scanflow up $(ARGS)

test: $(STAMP)
	bash tools/run-tests.sh $(PY)

# ruff's lint, then mypy's types (pyproject.toml: files, plugins), scanflow read from shared/.
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	MYPYPATH=shared $(VENV)/bin/mypy

clean:
	rm -rf $(VENV) .pytest_cache .hypothesis .ruff_cache .mypy_cache
