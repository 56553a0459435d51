# Two commands do everything: `make demo` and `make test`. Both create .venv on first use, and put
# a `ps-lab` launcher in ~/.local/bin (tools/launcher.sh; never over another one there).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
LAUNCHER := $(abspath $(BIN))/ps-lab

.PHONY: demo test test-slow bench lint lint-imports clean launcher warm-up

$(STAMP): pyproject.toml Makefile
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) (set PYTHON=...)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test,distributed,gphoto2]'
	@touch $(STAMP)
	@sh tools/launcher.sh link $(LAUNCHER)

# The ~/.local/bin/ps-lab link alone (for a .venv made before there was one).
launcher: $(STAMP)
	@sh tools/launcher.sh link $(LAUNCHER)

# Compile the numba kernels once, at install, into numba's cache (__pycache__ next to the
# sources): with an empty cache the first reconstruct would compile for a minute or more. Numba
# keys an entry by its source file's mtime, so an edited or pulled kernel source warms again.
KERNEL_SOURCES := $(wildcard reconstruct/*.py) $(wildcard ps_lab/appearance/*.py) \
	ps_lab/render/near_shading.py ps_lab/io/_coding_kernel.py ps_lab/jit.py
WARM := $(VENV)/.kernels-compiled
$(WARM): $(STAMP) $(KERNEL_SOURCES)
	$(BIN)/python -m ps_lab.reconstruct._warm_up
	@touch $(WARM)

warm-up: $(WARM)

# The same kernels compiled for a generic x86-64 (the second pytest run below): like the host's,
# at the install step, not inside the timed tests. Run after the host's, never beside it: both
# write the same cache index files.
WARM_GENERIC := $(VENV)/.kernels-compiled-generic
$(WARM_GENERIC): $(WARM)
	NUMBA_CPU_NAME=generic $(BIN)/python -m ps_lab.reconstruct._warm_up
	@touch $(WARM_GENERIC)

demo: $(WARM)
	$(BIN)/python -m ps_lab.demo
	@sh tools/launcher.sh check $(LAUNCHER)

# The import contracts ([tool.importlinter] in pyproject.toml). grimp finds ps_lab.capture,
# .calibration and .reconstruct through the links ps_lab/capture -> ../capture etc.
lint-imports: $(STAMP)
	$(BIN)/lint-imports --no-cache

# The tests marked `numerical` (pyproject.toml: they compare two numerical paths through the numba
# kernels: kernel and oracle, tiles, bands, near and directional, cluster and one process) run
# once more for a generic x86-64 (NUMBA_CPU_NAME=generic: no SIMD beyond SSE2, other vector widths
# than the host's), since fastmath splits sums by vector width. Numba's cache keys its entries by
# CPU name and features, so the second run compiles its own and leaves the host's alone.

# Import contracts first, then the tests, then the numerical ones for the second CPU target.
# The tests run on every core (pytest-xdist, one test file per worker at a time: a file's
# module fixtures are built once); PYTEST_WORKERS=0 runs them in this process. Each worker loads
# every kernel for its CPU target before its first test (tests/conftest.py; compiled by the
# warm-up steps above), so no test pays a compile against its timeout.
PYTEST_WORKERS ?= auto
PYTEST := $(BIN)/python -m pytest -q -n $(PYTEST_WORKERS) --maxprocesses=8 --dist loadfile
test: lint-imports $(WARM) $(WARM_GENERIC)
	$(PYTEST)
	NUMBA_CPU_NAME=generic $(PYTEST) -m numerical

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

bench: $(STAMP)
	$(BIN)/python benchmarks/solvers.py speed --quick

lint: $(STAMP)
	$(BIN)/python -m pip install -q -e '.[test,lint]'
	$(BIN)/ruff check .

# The launcher link goes too, but only if it points into this .venv.
clean:
	@sh tools/launcher.sh unlink $(LAUNCHER)
	rm -rf $(VENV) build *.egg-info
