# seanv-analysis: two commands set everything up on a fresh machine.
#   make demo   create .venv, install, run the paper pipeline on simulated data
#   make test   create .venv, install, run the test suite
#   make bench  run the benchmarks (ratios written to benchmarks/results/)
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test bench venv clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test,dask]"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m seanv_analysis.demo

test: $(STAMP)
	MPLBACKEND=Agg $(PY) -m pytest -q

bench: $(STAMP)
	MPLBACKEND=Agg $(PY) -m benchmarks

clean:
	rm -rf $(VENV) outputs/*/ .pytest_cache
