# Two commands do everything: `make demo` and `make test`. Both create .venv on first use.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-slow bench lint lint-imports clean

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) (set PYTHON=...)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test,distributed]'
	@touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m ps_lab.demo

# The import contracts ([tool.importlinter] in pyproject.toml), on a link tree of the package-dir
# mapping (grimp walks folders and would not find ps_lab.capture in capture/).
lint-imports: $(STAMP)
	$(BIN)/python tools/import_tree.py $(VENV)/import-tree
	cd $(VENV)/import-tree && PYTHONPATH=. $(CURDIR)/$(BIN)/lint-imports --no-cache $(CURDIR)/pyproject.toml

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
