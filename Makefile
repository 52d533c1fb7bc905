# make demo  — create .venv, install, run the main job end to end on simulated devices
# make test  — create .venv, install, run the whole test suite
# make bench — run the benchmark scripts (figures and ratios to a peer measured in the same run)

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
JOBS   ?= 2

.PHONY: demo test bench venv clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,bench]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/mls demo

test: $(STAMP)
	$(PY) -m pytest -n $(JOBS) --dist loadgroup -q

bench: $(STAMP)
	@set -e; for b in benchmarks/[!_]*.py; do echo "== $$b"; $(PY) $$b; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .hypothesis
