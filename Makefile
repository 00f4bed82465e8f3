# `make demo` and `make test` set everything up from a fresh clone.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-$(shell cksum < pyproject.toml | cut -d' ' -f1)

.PHONY: setup demo test dist bench mutate clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	rm -f $(VENV)/.installed-*
	touch $(STAMP)

setup: $(STAMP)

demo: setup
	mkdir -p demo-out
	$(BIN)/prism-stream data/autzen_trim.laz demo-out/autzen_1pct.parquet --ratio 0.01 --overwrite \
		--summary demo-out/autzen_1pct.json
	@echo "summary JSON: demo-out/autzen_1pct.json"

test: setup
	$(BIN)/python -m pytest -n 2 -q

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
	rm -rf $(VENV) demo-out bench/data bench/out .pytest_cache dist build *.egg-info
