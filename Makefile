# The two entry points of the README: `make run` (main job) and `make test`.
# Each creates the virtual environment first if setup.py changed since it was made.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: run test

$(BIN)/.installed: setup.py setup.cfg package.xml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade 'pip==25.3'
	$(BIN)/pip install --quiet -e '.[test]'
	touch $@

run: $(BIN)/.installed
	$(BIN)/ddarm episode --controller computed_torque --omega 15
	$(BIN)/ddarm episode --controller pd_gravity --omega 10 --delay 0

test: $(BIN)/.installed
	$(BIN)/python -m pytest -q
