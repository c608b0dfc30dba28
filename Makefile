# StillBox-gen: `make install` builds .venv (Python 3.11), `make test` runs every test from nothing,
# `make demo` runs the main job on a small default.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: install test lint demo bench-gen clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: $(STAMP) lint
	$(BIN)/python -m pytest -q --durations=5

# The main job on a small default: generate 40 scenes at 64 px, check them, train DepthNet
# briefly on CPU (or GPU), score it and write the report (a few minutes in all on 2 cores).
demo: $(STAMP)
	$(BIN)/stillbox-gen --res 64 --scenes 40 --out data/demo-64
	$(BIN)/stillbox-gen validate data/demo-64
	$(BIN)/stillbox-gen preview data/demo-64 --out data/demo-64-preview.png
	rm -rf runs/demo-depthnet
	$(BIN)/stillbox-bench run depthnet --data data/demo-64 --epochs 5 --batch-size 32 --out runs/demo-depthnet
	cat runs/demo-depthnet/summary.md

# Whole-process generation speed (start-up and writing included) at 64/128/256 px, 1 vs 2 workers.
BENCH_DIR ?= /tmp/stillbox-bench-gen
bench-gen: $(STAMP)
	@for spec in 64:40 128:16 256:6; do res=$${spec%:*}; n=$${spec#*:}; \
	  for w in 1 2; do rm -rf $(BENCH_DIR); start=$$(date +%s.%N); \
	    $(BIN)/stillbox-gen --res $$res --scenes $$n --workers $$w --out $(BENCH_DIR) --quiet 2>/dev/null; \
	    end=$$(date +%s.%N); \
	    $(BIN)/python -c "import sys; r,n,w,s,e=sys.argv[1:]; t=float(e)-float(s); \
	      print(f'{r:>4} px  workers {w}  {n} scenes  {t:6.1f} s  {int(n)*10/t:6.1f} frames/s')" \
	      $$res $$n $$w $$start $$end; \
	  done; done; rm -rf $(BENCH_DIR)

clean:
	rm -rf $(VENV) data/demo-64 data/demo-64-preview.png runs/demo-depthnet .pytest_cache .ruff_cache
