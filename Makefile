# Two commands do everything: `make demo` and `make test`. Both create .venv on first use, and put
# a `ps-lab` launcher in ~/.local/bin (tools/launcher.sh; never over another one there).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
LAUNCHER := $(abspath $(BIN))/ps-lab

.PHONY: demo test test-slow bench lint lint-imports clean launcher

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

demo: $(STAMP)
	$(BIN)/python -m ps_lab.demo
	@sh tools/launcher.sh check $(LAUNCHER)

# The import contracts ([tool.importlinter] in pyproject.toml). grimp finds ps_lab.capture,
# .calibration and .reconstruct through the links ps_lab/capture -> ../capture etc.
lint-imports: $(STAMP)
	$(BIN)/lint-imports --no-cache

# Import contracts first, then the tests.
test: lint-imports
	$(BIN)/python -m pytest -q

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
