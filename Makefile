# marsyard: every target sets itself up on a fresh machine (Debian libraries, venv, packages).
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.marsyard-setup
export MUJOCO_GL ?= egl
# pytest workers: 2 cores on our machines
WORKERS ?= 2

.PHONY: setup demo test test-slow regress bench experiments lint clean

setup: $(STAMP)

$(STAMP): pyproject.toml scripts/system-deps.sh scripts/constraints.txt
	bash scripts/system-deps.sh
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]' -c scripts/constraints.txt
	touch $(STAMP)

demo: setup
	$(BIN)/marsyard run scenarios/quickstart.yaml --out results/quickstart

test: setup
	$(BIN)/python -m pytest -q -n $(WORKERS) -m "not slow"

test-slow: setup
	$(BIN)/python -m pytest -q -n $(WORKERS) -m slow

# every canonical scenario of results/baselines/regress.yaml against its baseline
regress: setup
	$(BIN)/marsyard regress

bench: setup
	$(BIN)/python -m sim.tools.bench scenarios/quickstart.yaml --out results/bench
	$(BIN)/python -m sim.tools.bench scenarios/etna_two_rovers.yaml --variants no_depth_truth --out results/bench/etna
	$(BIN)/python -m comms.bench --out results/bench/comms.json
	$(BIN)/python -m slam.bench --out results/bench/graph.json
	$(BIN)/python -m sim.tools.match_bench --out results/bench/matching.json
	$(BIN)/python -m sim.tools.batch_bench --out results/bench/batch.json
	$(BIN)/python -m sim.tools.team_bench --sizes 1 2 4 8 --duration 30 --out results/bench/team
	# one simulated hour of three robots (about 90 min of wall time): metrics.json runtime.memory
	$(BIN)/marsyard run scenarios/soak.yaml --out results/bench/soak --no-progress

# the thesis's claims as batches (docs/fidelity.md), into results/experiments/<name>/, then the claims table
# (sim/tools/fidelity.py); each batch resumes where it
# stopped (about 9.5 h on 2 cores in all, as measured: multi_vs_single 2.2 h, graph_topology 2.65 h, bandwidth
# 2.3 h, matching_4d_6d 1.06 h, marker_uncertainty 1.29 h); a batch with runs that did not complete makes the
# target fail at the end
EXPERIMENTS ?= multi_vs_single graph_topology bandwidth matching_4d_6d marker_uncertainty
experiments: setup
	@echo "make experiments: $(EXPERIMENTS) (about 9.5 h on 2 cores; interrupt and rerun to continue)"
	@status=0; for name in $(EXPERIMENTS); do \
		$(BIN)/marsyard batch scenarios/experiments/$$name.yaml --out results/experiments/$$name --resume --workers $(WORKERS); \
		code=$$?; [ $$code -eq 130 ] && exit 130; [ $$code -ne 0 ] && status=1; \
	done; $(BIN)/python -m sim.tools.fidelity; exit $$status

lint: setup
	$(BIN)/ruff check sim slam comms tests

clean:
	rm -rf $(VENV) build *.egg-info
