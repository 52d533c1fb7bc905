# make demo  — create .venv, install, run the main job end to end on simulated devices
# make test  — create .venv, install, run the whole test suite
# make bench — run the benchmark scripts (figures and ratios to a peer measured in the same run)
# make lint  — ruff (lint + format check) over the tree, mypy on calib/ and drivers/ (make test runs it first)

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
JOBS   ?= 2

.PHONY: demo test bench lint prereqs venv clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,bench,dev]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/mls demo

# the system programs the integration tests run for real; one line naming the install when missing
prereqs:
	@command -v mosquitto >/dev/null 2>&1 || test -x /usr/sbin/mosquitto || \
	    { echo "make test needs the mosquitto broker: apt-get install mosquitto"; exit 1; }
	@command -v systemd-analyze >/dev/null 2>&1 || \
	    { echo "make test needs systemd-analyze: apt-get install systemd"; exit 1; }

lint: $(STAMP)
	$(VENV)/bin/ruff check --quiet .
	$(VENV)/bin/ruff format --check --quiet .
	$(VENV)/bin/mypy

# the realtime tests (daemon and emulators against a truth clock, deadlines in milliseconds) run
# after the rest, one at a time: beside another worker's Monte Carlo on 2 cores they measured the
# test machine's load instead of the daemon
test: prereqs lint
	$(PY) -m pytest -n $(JOBS) --dist loadgroup -q -m "not realtime"
	$(PY) -m pytest -q -m realtime

# the long Monte Carlos and the soak run short here; their full runs are in their docstrings
bench: $(STAMP)
	@set -e; for b in benchmarks/[!_]*.py; do echo "== $$b"; \
	  case $$b in \
	    benchmarks/accuracy.py|benchmarks/honesty.py) $(PY) $$b --quick ;; \
	    benchmarks/soak.py) $(PY) $$b --minutes 5 ;; \
	    benchmarks/watch_honesty.py) $(PY) $$b --production 5 --six-pass 3 ;; \
	    *) $(PY) $$b ;; \
	  esac; done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .hypothesis .mypy_cache .ruff_cache
