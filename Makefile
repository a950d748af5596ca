# Two entry points (see README): `make demo` and `make test`. Both create .venv and install what they need.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP_CORE := $(VENV)/.installed-core
STAMP_ALL := $(VENV)/.installed-all

.PHONY: demo test bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# The numba kernels compile once here (cached beside the sources), not in the first map's timings.
WARM_UP := $(BIN)/python -c "import scope3d.estimators.bundle as b; b.warm_up()"

$(STAMP_CORE): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .
	$(WARM_UP)
	touch $@

$(STAMP_ALL): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[peers,test]"
	$(WARM_UP)
	touch $@ $(STAMP_CORE)

# The main job on the built-in default: render the dome phantom, then map it.
demo: $(STAMP_CORE)
	$(BIN)/scope3d phantom dome --out runs/demo/dataset --seed 0 --pose-noise 0.25
	$(BIN)/scope3d map runs/demo/dataset --out runs/demo/map
	@echo "Open runs/demo/map/ (report.json, *.png, *.ply)."

# The report's browser tests drive Debian's chromium through chromedriver (never a downloaded browser
# build); installed here when missing (CI runs as root on a clean Debian machine).
BROWSER := /usr/bin/chromium /usr/bin/chromedriver
$(BROWSER):
	DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends chromium chromium-driver || \
	  { apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends chromium chromium-driver; }

# Open3D (a peer in the thread benchmark) loads Debian's libusb-1.0-0 when imported.
test: $(STAMP_ALL) $(BROWSER)
	@dpkg -s libusb-1.0-0 >/dev/null 2>&1 || (apt-get update && apt-get install -y libusb-1.0-0)
	$(BIN)/python -m pytest -q

bench: $(STAMP_ALL)
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) runs
