# `make demo` and `make test` each set everything up from a fresh clone, then run.
# Any Python >= 3.11: `make test PYTHON=python3.13` (a venv of another version is rebuilt).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
PYEXE  := $(shell .ci/find-python $(PYTHON))
PYVER  := $(shell $(PYEXE) -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null)
VENV   ?= .venv
EXTRAS ?= test,cluster
PY     := $(VENV)/bin/python
comma  := ,
STAMP  := $(VENV)/.installed-$(PYVER)-$(subst $(comma),-,$(EXTRAS))

.PHONY: install demo test test-fast smoke bench bench-smoke clean coinstall-check

# uv installs the pinned set (constraints.txt) in about a quarter of pip's time: 24-26 s against
# 92 s on the slow 2-core Intel, cold, 2026-11-29, the same versions; pip does it where uv cannot be
# had. Both byte-compile what they install, on purpose: with PYTHONDONTWRITEBYTECODE set (these
# machines set it) Python would otherwise compile jax & co. from source in every process the tests
# start (--no-compile saved 20 s of install and cost 2.4 s per such process, about 40 s in all,
# 2026-11-27). uv keeps no cache unless UV_NO_CACHE=0 (its cache is 1.2 GB; CI disks run short).
UV_VERSION  ?= 0.13.8
UV_NO_CACHE ?= 1
export UV_NO_CACHE
$(STAMP): pyproject.toml constraints.txt
	@test -n "$(PYVER)" || { echo "make: no working '$(PYTHON)' on this machine" >&2; exit 2; }
	@if [ -x $(PY) ] && ! $(PY) -c 'import sys; sys.exit(f"{sys.version_info[0]}.{sys.version_info[1]}" != "$(PYVER)")'; \
	  then echo "$(VENV) is another Python's: rebuilding it with $(PYVER)"; rm -rf $(VENV); fi
	rm -f $(VENV)/.installed-*
	$(PYEXE) -m venv $(VENV)
	@echo "installing d2spo[$(EXTRAS)] into $(VENV) with uv $(UV_VERSION) (pip if uv cannot be had)"
	@if $(PY) -m pip install --quiet --disable-pip-version-check "uv==$(UV_VERSION)" && \
	  $(VENV)/bin/uv pip install --quiet --python $(PY) --compile-bytecode -c constraints.txt -e ".[$(EXTRAS)]"; then :; \
	else \
	  echo "make: uv $(UV_VERSION) could not be installed or could not install the set: installing with pip" >&2; \
	  $(PY) -m pip install --quiet --disable-pip-version-check --upgrade "pip>=24" && \
	  $(PY) -m pip install --quiet --disable-pip-version-check -c constraints.txt -e ".[$(EXTRAS)]"; \
	fi
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/d2spo demo --out demo_out

test: $(STAMP)
	$(VENV)/bin/ruff check src tests bench examples
	$(PY) -m pytest -n 2 --dist loadgroup --durations=10 tests

# What .ci/run runs on each other Python version: import, a few fast tests, a 50-episode train.
smoke: $(STAMP)
	$(PY) -c "import d2spo, d2spo.envs, sys; print('d2spo imports on Python', sys.version.split()[0])"
	$(PY) -m pytest -x tests/test_ltl_parser.py tests/test_env_geometry.py \
	  tests/test_env_gym.py::test_gymnasium_env_checker_passes_without_a_warning
	rm -rf $(VENV)/smoke_run
	$(VENV)/bin/d2spo train --task relaxed --layout relaxed --episodes 50 --eval-episodes 10 --out $(VENV)/smoke_run \
	  > $(VENV)/smoke.log 2>&1 || { cat $(VENV)/smoke.log; exit 1; }
	@cat $(VENV)/smoke.log
	@# a warning in a bare install is a dependency the package forgot (filelock, for the compile cache)
	@! grep -n "warning" $(VENV)/smoke.log

# d2spo beside safety-gymnasium 1.0.0 in one throwaway venv (needs PyPI; docs/env.md says what it shows).
coinstall-check:
	.ci/coinstall-safety-gymnasium

bench: $(STAMP)
	$(PY) bench/env_throughput.py

# Every script of bench/ and examples/ once, on tiny settings: that each still runs (not a timing).
bench-smoke: $(STAMP)
	PY=$(PY) bash bench/smoke.sh

clean:
	rm -rf $(VENV) .venv-3.* .venv-coinstall demo_out .pytest_cache .hypothesis
