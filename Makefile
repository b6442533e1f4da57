# The README's two commands: `make run` (main job) and `make test`.
# Each creates the virtual environment first if setup.py changed since it was made.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
# Debian's headless browser and its WebDriver, which test/test_report_html.py opens the HTML reports in.
BROWSER := /usr/bin/chromium /usr/bin/chromedriver
BROWSER_INSTALL := env DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends \
    chromium chromium-driver

.PHONY: run test docs

$(BIN)/.installed: setup.py setup.cfg package.xml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade 'pip==25.3'
	$(BIN)/pip install --quiet -e '.[test]'
	touch $@

# Each run writes a new folder: runs/paper-<date>-<time>/REPORT.md, report.html, results.json, bags/, figures/.
run: $(BIN)/.installed
	ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST $(BIN)/ddarm reproduce --out runs/paper-$$(date +%Y%m%d-%H%M%S)

# Installed only when missing: as root (CI), else through sudo; a fresh machine may have no package lists yet.
$(BROWSER):
	@if [ "$$(id -u)" = 0 ]; then sudo=; elif command -v sudo >/dev/null; then sudo=sudo; else \
	    echo "make: $@ is missing; as root: $(BROWSER_INSTALL)" >&2; exit 1; fi; \
	$$sudo $(BROWSER_INSTALL) || { $$sudo apt-get update && $$sudo $(BROWSER_INSTALL); }

test: $(BIN)/.installed $(BROWSER)
	$(BIN)/python -m pytest -q

# The pages of docs/ and the parameter files of config/ generated from the code (tests fail when they drift).
docs: $(BIN)/.installed
	$(BIN)/python -m ddarm.cli.docs
