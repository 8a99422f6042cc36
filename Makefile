# topseg: `make demo` and `make test` are all a fresh Debian machine needs.
VENV   := .venv
PY     := $(VENV)/bin/python
TOPSEG := $(VENV)/bin/topseg
STAMP  := $(VENV)/.installed
PYTEST := $(PY) -m pytest

.PHONY: install test test-all demo bench lint format clean model recording cell-recording experiments docs

install: $(STAMP)

$(STAMP): pyproject.toml scripts/install.sh
	bash scripts/install.sh
	touch $(STAMP)

## every test not marked slow, two processes (~8 min of pytest on 2 cores)
test: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(PYTEST) -m "not slow" -q -n 2

## everything: the tests marked slow too (the longest service and command runs, the soaks)
test-all: install
	$(PYTEST) -q

## install, then run the main job end to end
demo: install
	$(TOPSEG) demo

## speed and memory of each stage
bench: install
	$(TOPSEG) bench forest
	$(TOPSEG) bench crf
	$(TOPSEG) bench stages
	$(TOPSEG) bench synthesis
	$(TOPSEG) bench datagen
	$(TOPSEG) bench transport
	$(TOPSEG) bench pipeline

## rebuild the bundled model (models/default.npz) from a fresh synthetic dataset
model: install
	bash scripts/make_model.sh

## rebuild the bundled demo recording (recordings/demo.mcap)
recording: install
	bash scripts/make_recording.sh

## rebuild the rendered robot-cell recording with its truth (recordings/cell.mcap, cell.toml,
## cell.background.npz)
cell-recording: install
	$(TOPSEG) datagen cell-sequence --out recordings/cell.mcap --seed 3 --duration 20 --fps 15 --size 320x240

## the command-line reference, docs/reference/cli.md, from the parsers
docs: install
	$(PY) docs/reference/make_cli.py

## the paper's experiments at the quick scale (docs/results.md): out/experiments-quick/
experiments: install
	for e in table noise features overlap frames; do $(TOPSEG) experiment $$e --scale quick --out out/experiments-quick || exit 1; done

lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: install
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
