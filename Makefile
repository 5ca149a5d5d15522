# Two commands do all the set-up on a fresh machine:
#   make demo   runs the main job on an embedded default (nothing else to install)
#   make test   runs the test suite (make test-fast: without the slow tests, the inner loop)
# Each creates .venv (or reuses it) and installs the CPU build of torch first.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
LINTED := vfm_core service replay tests benchmarks examples
# two test processes (pytest-xdist), a test file each at a time (module fixtures are shared
# by its tests, in order): the suite in about two thirds of the time on two cores; the
# files in collection order, whose longest come first (tests/conftest.py, LONGEST_FIRST);
# `make test PYTEST_ARGS=` runs it in one process
PYTEST_ARGS ?= -n 2 --dist loadfile --no-loadscope-reorder --durations=25

.PHONY: install demo test test-fast lint bench bench-docs docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# The CPU build; a plain `torch` would pull a multi-GB CUDA build.
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/vfm demo

test: $(STAMP)
	$(VENV)/bin/ruff check $(LINTED)
	$(VENV)/bin/ruff format --check $(LINTED)
	@# pytest exits 5 when it collects no test: that is a broken suite, say so.
	@$(PY) -m pytest $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: pytest collected no test" >&2; fi; exit $$rc

# The inner loop: the suite without the tests marked slow (the long end-to-end ones, chosen
# from measured durations in tests/conftest.py). CI runs `make test`, everything.
test-fast: $(STAMP)
	$(VENV)/bin/ruff check $(LINTED)
	$(VENV)/bin/ruff format --check $(LINTED)
	@$(PY) -m pytest $(PYTEST_ARGS) -m "not slow"; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test-fast: pytest collected no test" >&2; fi; exit $$rc

lint: $(STAMP)
	$(VENV)/bin/ruff check $(LINTED)
	$(VENV)/bin/ruff format --check $(LINTED)
	$(VENV)/bin/mypy

bench: $(STAMP)
	$(PY) -m pip install --quiet -e '.[dev,bench]'
	$(PY) benchmarks/bench_study.py

# The documentation site (docs/, mkdocs.yml) into site/, warnings as errors; offline: open
# site/index.html. The docs extra goes into the same .venv, with a stamp of its own.
DOCS_STAMP := $(VENV)/.installed-docs
$(DOCS_STAMP): $(STAMP)
	$(PY) -m pip install --quiet -e '.[docs]'
	touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)
	@# not --quiet: it hides the warnings that --strict counts
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict
	@echo "make docs: site/index.html"

# The benchmark figures the documentation includes, written by the scripts themselves.
bench-docs: $(STAMP)
	$(PY) -m pip install --quiet -e '.[dev,bench]'
	$(PY) benchmarks/bench_speed.py --markdown docs/benchmarks/generated/speed.md
	$(PY) benchmarks/bench_alarms.py --markdown docs/benchmarks/generated/alarms.md
	$(PY) benchmarks/bench_alarms.py --models ham --methods ol --arl0 3000 \
		--fields 'none:41:6:4,none:42:4:5,none:43:8:3,erosion;step=0.1:44:6:4,erosion;rate=0;step=0.1:47:8:4' \
		--markdown docs/benchmarks/generated/alarms_arl3000.md
	$(PY) benchmarks/bench_study.py --markdown docs/benchmarks/generated/study.md
	$(PY) benchmarks/bench_service.py --markdown docs/benchmarks/generated/service.md
	$(PY) benchmarks/bench_effects.py --markdown docs/benchmarks/generated/effects.md
	$(PY) benchmarks/bench_separator.py --markdown docs/benchmarks/generated/separator.md

clean:
	rm -rf $(VENV) build *.egg-info site
