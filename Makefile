# seanv-analysis: two commands set everything up on a fresh machine.
#   make demo   create .venv, install, run the paper pipeline on simulated data
#   make test   create .venv, install, run the test suite
#   make test-fast  the edit loop: every test not marked slow (< 60 s)
#   make bench  run the benchmarks (ratios written to benchmarks/results/)
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test test-fast bench venv clean

venv: $(STAMP)

# constraints.txt: the versions the results were made with (reproducible installs)
$(STAMP): pyproject.toml constraints.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c constraints.txt -e ".[test,dask]"
	$(PY) -c "from seanv_analysis.sim.compiled import main; main()"  # the simulator, compiled once (10-30 s)
	touch $(STAMP)

# when this make started [s since the epoch]: the demo times itself from here,
# the install of a fresh clone included (outputs/demo/timings.json, the README)
MAKE_STARTED := $(shell date +%s)

demo: $(STAMP)
	$(PY) -m seanv_analysis.demo --started-at $(MAKE_STARTED) --installed-at $(STAMP)

# two pytest-xdist workers (the 2-core machine): about 11.5-16 CPU-minutes of
# tests (most of it closed-loop identification and discovery, their flow and
# static fits, and the figures of the commands tested whole) in about 6-8.5
# min on a clean clone (2026-11-28: 7 min 13 s, and 8 min 26 s later that day;
# 8 min 34 s and 9 min 59 s with the install; in the evening 6 min 27 s and
# 6 min 45 s, 7 min 26 s and 7 min 42 s with it; late evening 6 min 16 s, 7 min
# 22 s with it, 11.5 CPU-minutes; a third worker: 13 s slower). One seed per case here; the
# multi-seed acceptance sweeps and their rates are make bench's
# (benchmarks/bench_discover.py, bench_identify.py, bench_coverage.py)
TEST_WORKERS ?= 2

# bytecode caches allowed for the tests (__pycache__ is gitignored): where the
# environment sets PYTHONDONTWRITEBYTECODE, every pytest worker and every CLI
# subprocess of the tests would compile the package again (~13 s of CPU per
# worker: collection 13.5 -> 6.4 s CPU). Empty = unset for Python; plain sh.

# --dist loadfile: a test module's fixtures (foreign-rig data sets, identify
# runs, report pipelines) are made once, on the worker that runs the module
# (with --dist load both workers made most of them); the golden pipeline run
# is made once and shared by the workers (tests/conftest.py: golden_run)
test: $(STAMP)
	PYTHONDONTWRITEBYTECODE= MPLBACKEND=Agg $(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

test-fast: $(STAMP)
	PYTHONDONTWRITEBYTECODE= MPLBACKEND=Agg $(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not slow"

bench: $(STAMP)
	MPLBACKEND=Agg $(PY) -m benchmarks

# never results: outputs/ is yours (the built-in data sets and compiled code
# live in the user cache folder, ~/.cache/seanv-analysis, safe to delete)
clean:
	rm -rf $(VENV) .pytest_cache build dist *.egg-info
