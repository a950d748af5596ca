# Two entry points (see README): `make demo` and `make test`. Both create .venv and install what they need.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP_CORE := $(VENV)/.installed-core
STAMP_ALL := $(VENV)/.installed-all

.PHONY: demo test bench fuzz clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# `pip install -e .` compiles every numba kernel ahead of time (setup.py, scope3d.utils.aot; needs a C
# compiler). The warm-up loads them, or compiles them with numba's JIT where that step could not run, so
# no run pays it.
KERNELS := $(shell $(PYTHON) -c "import runpy; [print('src/' + m.replace('.', '/') + '.py') for m in \
  runpy.run_path('src/scope3d/utils/aot.py')['KERNEL_MODULES']]")
WARM_UP := $(BIN)/python -c "from scope3d.utils import aot; aot.warm_up()"

$(STAMP_CORE): pyproject.toml setup.py src/scope3d/utils/aot.py $(KERNELS) | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e .
	$(WARM_UP)
	touch $@

# The kernels' ahead-of-time build needs a C compiler and Python's headers (CI: a clean Debian machine).
.PHONY: aot-toolchain
aot-toolchain:
	@command -v cc >/dev/null 2>&1 && $(PYTHON) -c "import os, sys, sysconfig; \
	  sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()['include'], 'Python.h')))" || \
	  { apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends gcc libc6-dev python3-dev; }

$(STAMP_ALL): pyproject.toml setup.py src/scope3d/utils/aot.py $(KERNELS) | $(BIN)/python aot-toolchain
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
	@echo "== the versions and machine this run tests (a failure names them)"
	@$(BIN)/python -m pip freeze --all --exclude-editable
	@$(BIN)/python -c "import os, platform, numpy, scipy.linalg, threadpoolctl; print(platform.platform(), platform.python_version(), \
	  os.cpu_count(), 'cpus'); [print(i['internal_api'], i['version'], i.get('architecture'), i['num_threads'], \
	  'threads') for i in threadpoolctl.threadpool_info()]"
	$(BIN)/python -m pytest -q

bench: $(STAMP_ALL)
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

# The long fuzzing run of every file reader (docs/reliability.md section 1): hypothesis, then atheris
# (coverage-guided) when it is installed, FUZZ_SECONDS per reader and engine; results in benchmarks/results/.
FUZZ_SECONDS ?= 600
fuzz: $(STAMP_ALL)
	$(BIN)/python benchmarks/bench_fuzz.py --seconds-per-reader $(FUZZ_SECONDS)

clean:
	rm -rf $(VENV) runs
