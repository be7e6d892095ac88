# Two commands set up a fresh machine: `make up` and `make test`. Both bootstrap .venv first.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
export MUJOCO_GL ?= egl

.PHONY: install browser up test docs lint bench mesh clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	# The CPU wheel of torch 2.13.0 is on disk; install it first so nothing pulls a CUDA build.
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP) browser

# The plan viewer's browser tests drive Debian's chromium through Playwright (the `dev` extra);
# Playwright's own browser download is not used. Installed when missing (CI runs as root).
browser:
	@command -v chromium >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq chromium; \
	  else echo "chromium is missing: run 'sudo apt-get install -y chromium'" >&2; exit 1; fi; }

up: $(STAMP)
	$(BIN)/lsr up

# The docs site is built strictly first: a broken link, a missing page or anchor fails CI
# (not --quiet: it hides the warnings that --strict counts).
# pytest then runs everything else, the examples (tests/services/test_examples.py) and the
# import-cycle check (tests/test_imports.py) among them.
test: $(STAMP) browser
	$(BIN)/ruff check .
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict
	$(BIN)/pytest -q

# The documentation site from docs/ (MkDocs Material) into build/site/.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_datagen.py

# The stack on three hosts (network namespaces; root) and its faults under load: one JSON line.
mesh: $(STAMP)
	$(BIN)/python benchmarks/mesh_faults.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
