# Two commands do everything: `make demo` and `make test`. Both create .venv on first use.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-slow bench lint lint-imports clean

$(STAMP): pyproject.toml Makefile
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) (set PYTHON=...)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test,distributed,gphoto2]'
	@touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m ps_lab.demo

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

clean:
	rm -rf $(VENV) build *.egg-info
