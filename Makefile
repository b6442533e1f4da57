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

# Each run writes a new folder: runs/paper-<date>-<time>/REPORT.md, results.json, bags/, figures/.
run: $(BIN)/.installed
	ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST $(BIN)/ddarm reproduce --out runs/paper-$$(date +%Y%m%d-%H%M%S)

test: $(BIN)/.installed
	$(BIN)/python -m pytest -q
