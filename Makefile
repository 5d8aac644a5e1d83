# Two commands on a fresh machine (Python >= 3.10, no venv needed): `make demo`, `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test bench-speed table3 clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -e '.[test,plot]'
	@touch $(STAMP)

demo: $(STAMP)
	$(PY) -m sim_bench table3

test: $(STAMP)
	$(PY) -m pytest

bench-speed: $(STAMP)
	$(PY) -m sim_bench speed-sim

clean:
	rm -rf $(VENV) bench-results .pytest_cache
