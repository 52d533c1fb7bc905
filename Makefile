# make demo  — create .venv, install, run the main job end to end on simulated devices
# make test  — create .venv, install, run the whole test suite
# make bench — run the benchmark scripts (figures and ratios to a peer measured in the same run)
# make lint  — ruff (lint + format check) over the tree, mypy over every package (make test runs it first)
# make test-pythons — the non-realtime suite under each supported interpreter found (3.11, 3.12, 3.13),
#                     one venv each (.venv-3.12, ...); PYTHONS="python3.12 /opt/py/bin/python3.13"
#                     overrides the list, TESTS="tests/cli tests/calib/core" runs a part of the suite
# make stress-test — make test 5 times in a row beside 2 busy processes (RUNS=, HOGS=; .ci/stress-test)
# make wheelhouse — the offline install for the vessel PC: dist/marine-mls-<version>-wheelhouse/ and .tar.gz
#                   (every wheel at .venv's versions, manifest with sha256s, install.py; docs/doctor.md)

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
JOBS   ?= 2

.PHONY: demo test test-pythons stress-test bench lint prereqs venv clean wheelhouse

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

# BLAS on one thread in the tests: two pytest workers on two cores, each OpenBLAS spinning two
# threads, took 26.8 min of CPU for the non-realtime suite against 15.0 min on one thread each
# (15.7 → 9.9 min of wall time); no test gains from a threaded BLAS (its matrices are small)
test test-pythons: export OPENBLAS_NUM_THREADS = 1
test test-pythons: export OMP_NUM_THREADS = 1
test test-pythons: export MKL_NUM_THREADS = 1

# the realtime tests (daemon and emulators against a truth clock, deadlines in milliseconds) run
# after the rest, one at a time: beside another worker's Monte Carlo on 2 cores they measured the
# test machine's load instead of the daemon
test: prereqs lint
	$(PY) -m pytest -n $(JOBS) --dist loadgroup -q -m "not realtime"
	$(PY) -m pytest -q -m realtime

# each name in PYTHONS is looked up on PATH (a pyenv shim that cannot run counts as missing), then
# under /root/.pyenv/versions/X.Y.*/bin; a path is taken as it is. One venv per interpreter, one
# summary line each, missing interpreters named; fails when a suite fails or none was found.
PYTHONS ?= python3.11 python3.12 python3.13
TESTS   ?=

test-pythons: prereqs
	@set -u; failed=0; found=0; missing=""; summary=""; \
	for name in $(PYTHONS); do \
	  exe=""; \
	  case $$name in \
	    */*) cands=$$name ;; \
	    *) ver=$${name#python}; \
	       cands="$$(command -v $$name 2>/dev/null) $$(ls -d /root/.pyenv/versions/$$ver.*/bin/$$name 2>/dev/null | sort -V -r)" ;; \
	  esac; \
	  for c in $$cands; do \
	    if "$$c" -c 'import sys' >/dev/null 2>&1; then exe=$$c; break; fi; \
	  done; \
	  if [ -z "$$exe" ]; then missing="$$missing $$name"; continue; fi; \
	  found=$$((found + 1)); \
	  ver=$$("$$exe" -c 'import sys; print("%d.%d" % sys.version_info[:2])'); \
	  full=$$("$$exe" -c 'import platform; print(platform.python_version())'); \
	  venv=.venv-$$ver; log=$$venv/test-pythons.log; \
	  echo "== Python $$full ($$exe) in $$venv"; \
	  if [ ! -f $$venv/.installed-stamp ] || [ pyproject.toml -nt $$venv/.installed-stamp ]; then \
	    rm -f $$venv/.installed-stamp; { test -x $$venv/bin/python || "$$exe" -m venv $$venv; } && \
	    $$venv/bin/python -m pip install --quiet --upgrade pip && \
	    $$venv/bin/python -m pip install --quiet -e '.[test]' && touch $$venv/.installed-stamp; \
	  fi; \
	  if [ -f $$venv/.installed-stamp ]; then \
	    { $$venv/bin/python -m pytest -n $(JOBS) --dist loadgroup -q -m "not realtime" $(TESTS) 2>&1; \
	      echo $$? > $$venv/test-pythons.rc; } | tee $$log; \
	    rc=$$(cat $$venv/test-pythons.rc); \
	    result="$$(tail -n 1 $$log | sed 's/=//g; s/^ *//; s/ *$$//')"; \
	  else rc=1; result="pip install -e '.[test]' failed"; fi; \
	  if [ $$rc = 0 ]; then status=ok; else status=FAILED; failed=1; fi; \
	  summary="$$summary$$(printf '\n  Python %-8s %-6s %s' "$$full" "$$status" "$$result")"; \
	done; \
	echo; echo "test-pythons:$$summary"; \
	if [ -n "$$missing" ]; then echo "  not found:$$missing (looked on PATH and in /root/.pyenv/versions)"; fi; \
	if [ $$found = 0 ]; then echo "  no interpreter found"; exit 1; fi; \
	exit $$failed

# tests that pass only on an idle machine fail here: .ci/stress-test prints one line per run
stress-test: prereqs
	.ci/stress-test

# the long Monte Carlos and the soak run short here; their full runs are in their docstrings
bench: $(STAMP)
	@set -e; for b in benchmarks/[!_]*.py; do echo "== $$b"; \
	  case $$b in \
	    benchmarks/accuracy.py|benchmarks/honesty.py) $(PY) $$b --quick ;; \
	    benchmarks/soak.py) $(PY) $$b --minutes 5 ;; \
	    benchmarks/watch_honesty.py) $(PY) $$b --production 5 --six-pass 3 ;; \
	    *) $(PY) $$b ;; \
	  esac; done

# the wheels of pyproject's dependencies pinned as installed in .venv, through pip (its cache makes
# a second build quick); then on the vessel: sudo python3 marine-mls-<version>-wheelhouse/install.py
wheelhouse: $(STAMP)
	$(PY) install/wheelhouse.py --out dist

clean:
	rm -rf $(VENV) .venv-3.* build *.egg-info .pytest_cache .hypothesis .mypy_cache .ruff_cache
