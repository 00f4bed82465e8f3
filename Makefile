# `make demo` and `make test` set everything up from a fresh clone.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# One stamp per install level, named by pyproject.toml's checksum: `make demo` installs the package alone,
# `make test` adds the test extras on top; switching between them installs nothing twice, and a changed
# pyproject.toml makes both stale.
SUM := $(shell cksum < pyproject.toml | cut -d' ' -f1)
BASE := $(VENV)/.installed-base-$(SUM)
TESTS := $(VENV)/.installed-test-$(SUM)

.PHONY: setup setup-test aot demo test dist bench mutate clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(BASE): pyproject.toml | $(BIN)/python
	rm -f $(VENV)/.installed-*
	$(BIN)/pip install --quiet --disable-pip-version-check -e .
	touch $(BASE)

# The kernels compile once here, not in each of the suite's first processes at once, into numba's cache and then
# ahead of time into a C extension that loads without numba (prism_stream/run/aot.py; `make aot` alone).
$(TESTS): $(BASE)
	$(BIN)/pip install --quiet --disable-pip-version-check -e '.[test]'
	$(BIN)/python -m prism_stream.engines.warm --aot
	touch $(TESTS)

setup: $(BASE)

# The numba loops compiled ahead of time (needs the C compiler Python's extensions build with): every streamed
# run then starts about 0.6 s sooner. Rebuild after editing prism_stream/core/jit.py (a stale build is ignored).
aot: $(BASE)
	$(BIN)/python -c 'import setuptools' 2>/dev/null || $(BIN)/pip install --quiet setuptools  # for numba.pycc
	$(BIN)/python -m prism_stream.engines.warm --aot

setup-test: $(TESTS)

demo: setup
	mkdir -p demo-out
	$(BIN)/prism-stream data/autzen_trim.laz demo-out/autzen_1pct.parquet --ratio 0.01 --overwrite \
		--summary demo-out/autzen_1pct.json
	@echo "summary JSON: demo-out/autzen_1pct.json"

# Three workers on two cores: much of the suite waits on the command-line processes it starts, and one more
# worker fills that wait (9.2 min against 11.7 with two: bench/RESULTS_TESTS.md); worksteal evens out the end.
# Bytecode is written even where PYTHONDONTWRITEBYTECODE is set (some CI images set it): else each of the
# hundreds of command-line processes the suite starts compiles the package again (0.1 s of a 0.5 s run).
PYTEST_WORKERS ?= 3
test: setup-test
	$(BIN)/python -m prism_stream.engines.warm --aot --if-stale
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -n $(PYTEST_WORKERS) --dist worksteal -q

# The wheel and the sdist in dist/ (pip install dist/prism_stream-*.whl installs it anywhere).
dist: setup
	$(BIN)/pip install --quiet 'build>=1.2'
	$(BIN)/python -m build --outdir dist .

bench: setup
	$(BIN)/pip install --quiet -e '.[bench]'
	$(BIN)/python bench/run.py

# Mutation testing (cosmic-ray), by hand before a release, not in CI: tens of minutes.
# Targets and paths: tests/mutation/targets.toml. TARGETS="bins kernels" runs some of them.
mutate: setup
	$(BIN)/pip install --quiet 'cosmic-ray==8.7.0'
	$(BIN)/python tests/mutation/run.py $(TARGETS)

clean:
	rm -rf $(VENV) demo-out bench/data bench/out .pytest_cache dist build *.egg-info prism_stream/core/_kernels_aot*
