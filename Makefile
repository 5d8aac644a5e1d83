# Two commands on a fresh machine (Python >= 3.10 with venv): `make demo`, `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
VCANVM := ../shared/vcan-vm

.PHONY: demo test test-slow test-vcan test-install benches docs lint clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -e '.[test,plot,mdf,fleet,docs,lint]'
	@touch $(STAMP)

# The nominal bench for ~20 s on the default bus (vcan0 if present, else a loopback hub);
# exits non-zero if the estimator misses its accuracy targets.
demo: $(STAMP)
	@$(PY) -m estimator compile --quiet
	$(PY) -m sim_bench table3 --paper-only
	$(PY) -m sim_bench bench --scenario nominal --seconds 20

test: $(STAMP)
	@$(PY) -m estimator compile --quiet
	$(PY) -m pytest -n 2 -m "not slow"

# End-to-end runs as a user types them: the README's quick starts, the CLI calibrations (≈ 2.5 min; CI runs them).
test-slow: $(STAMP)
	@$(PY) -m estimator compile --quiet
	$(PY) -m pytest -n 2 -m slow

# The vcan0 + candump suite: natively where vcan0 exists, otherwise inside the QEMU VM of ../shared/vcan-vm.
test-vcan: $(STAMP)
	@bash tests/vcan/run.sh

# A wheel built here, installed in a fresh venv and run from outside the checkout (~30 s; CI runs it).
test-install: $(STAMP)
	@bash tests/install/run.sh

# The documentation site (docs/_build/html); warnings are errors.
docs: $(STAMP)
	$(PY) -m sphinx -E -b html -W --keep-going -q docs docs/_build/html
	@echo "docs in docs/_build/html/index.html"

# ruff and mypy.
lint: $(STAMP)
	$(PY) -m ruff check estimator sim_bench tests docs
	$(PY) -m mypy

# Every benchmark (takes a while).
benches: $(STAMP)
	$(PY) -m sim_bench speed-sim
	$(PY) -m sim_bench accuracy
	$(PY) -m sim_bench tracking
	$(PY) -m sim_bench table3
	$(PY) -m sim_bench speed
	$(PY) -m sim_bench daemon-bench
	$(PY) -m sim_bench reliability
	$(PY) -m sim_bench bench --scenario all --quiet

clean:
	rm -rf $(VENV) bench-results .pytest_cache docs/_build
