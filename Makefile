# make demo: install into .venv and run the main job.  make test: install and run the whole test suite.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test test-under-load bench install clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e '.[all]'
	touch $(STAMP)

install: $(STAMP)

# 12 simulated Crazyflies (5 pursuers, 5 scouts, 2 evaders) flown through cflib with the shipped role_based models
demo: $(STAMP)
	$(VENV)/bin/swarm-gs demo --models models/role_based --duration 30 \
		--json results/demo.json --log results/demo_flight.jsonl --plot results/demo.png

# bytecode is written (an environment with PYTHONDONTWRITEBYTECODE set recompiled every module in every test
# subprocess and re-rewrote every test module's asserts: collection alone took 24 s instead of 10)
PYTEST := PYTHONDONTWRITEBYTECODE= $(PY) -m pytest

# two pytest-xdist workers, one test file on one worker (the files' module fixtures fly once for all their
# tests): most of the suite waits on subprocesses, sockets and simulated flights, so two
# workers: 848 s against 962 s serial with four trainings beside them; the whole make test 281 s on a quiet
# machine (909 passed, 2026-12-03 07:38), 295 s with two trainings at nice 10 beside it; PYTEST_WORKERS=0: serial
PYTEST_WORKERS ?= 2
XDIST = $(if $(filter 0,$(PYTEST_WORKERS)),,-n $(PYTEST_WORKERS) --dist loadfile)

test: $(STAMP)
	$(PYTEST) -q $(XDIST)

# the suite three times in a row while stress-ng keeps both cores busy (Debian: apt-get install stress-ng)
LOAD_RUNS ?= 3
test-under-load: $(STAMP)
	@command -v stress-ng >/dev/null || { echo "test-under-load: stress-ng is not installed: apt-get install stress-ng"; exit 2; }
	@stress-ng --cpu 2 --quiet & pid=$$!; trap "kill $$pid 2>/dev/null" EXIT INT TERM; \
	for i in $$(seq $(LOAD_RUNS)); do echo "== run $$i of $(LOAD_RUNS) under stress-ng --cpu 2"; \
		$(PYTEST) -q $(XDIST) $(PYTEST_ARGS) || exit 1; done

bench: $(STAMP)
	$(PY) -m pytest tests/benchmarks -m "slow or not slow" --benchmark-enable --benchmark-columns=min,median,mean,ops,rounds

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
