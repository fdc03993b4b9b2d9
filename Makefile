# `make demo` and `make test` each set everything up from a fresh clone, then run.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: install demo test test-fast bench clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check --upgrade "pip>=24"
	$(PY) -m pip install --quiet --disable-pip-version-check -c constraints.txt -e ".[test,cluster]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/d2spo demo --out demo_out

test: $(STAMP)
	$(PY) -m pytest -n 2 --durations=10 tests

bench: $(STAMP)
	$(PY) bench/env_throughput.py

clean:
	rm -rf $(VENV) demo_out .pytest_cache .hypothesis
