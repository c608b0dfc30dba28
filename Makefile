# StillBox-gen: `make install` builds .venv (Python 3.11), `make test` runs every test from nothing,
# `make demo` runs the main job on a small default.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: install test test-kernels test-bench-only lint demo bench-gen golden clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[gen,bench,tb,toy,dev,ray,export]'
	touch $(STAMP)

install: $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: $(STAMP) lint
	$(BIN)/python -m pytest -q --durations=5
	$(MAKE) --no-print-directory test-kernels
	$(MAKE) --no-print-directory test-bench-only

# The suite again under an old x86-64's CPU kernels (OpenBLAS, numpy SIMD, ATen, oneDNN, libm):
# what must not depend on the machine does not (docs/DETERMINISM.md).
test-kernels: $(STAMP)
	tests/old_x86_kernels.sh $(BIN)/python -m pytest -q -p no:cacheprovider

# The reader and the benchmark without Blender: a venv with the `bench` extra only (no bpy) runs
# every test that neither renders nor needs bpy (markers render, blender); tests/test_packaging.py checks that bpy is really absent there.
# Without the `gen` extra's caps it gets current numpy (2.x), OpenCV and pyarrow.
BENCH_VENV := .venv-bench
$(BENCH_VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(BENCH_VENV)
	$(BENCH_VENV)/bin/pip install --quiet --upgrade pip
	$(BENCH_VENV)/bin/pip install --quiet -e '.[bench,toy,dev]'
	touch $@

test-bench-only: $(BENCH_VENV)/.installed
	STILLBOX_EXPECT_NO_BPY=1 $(BENCH_VENV)/bin/python -m pytest -q -p no:cacheprovider -m "not render and not blender"

# The main job on a small default: generate 40 scenes at 64 px, check them, train DepthNet
# briefly on CPU (or GPU), score it and write the report (21-53 s in all on 2 cores).
demo: $(STAMP)
	$(BIN)/stillbox-gen --res 64 --scenes 40 --out data/demo-64
	$(BIN)/stillbox-gen validate data/demo-64
	$(BIN)/stillbox-gen preview data/demo-64 --out data/demo-64-preview.png
	rm -rf runs/demo-depthnet
	$(BIN)/stillbox-bench run depthnet --data data/demo-64 --epochs 5 --batch-size 32 --out runs/demo-depthnet
	cat runs/demo-depthnet/summary.md

# Whole-process generation speed and PSNR at 64/128/256 px, every quality level vs a plain config.
bench-gen: $(STAMP)
	$(BIN)/stillbox-gen bench --csv bench-gen.csv

# Regenerate tests/golden/ after a deliberate change of outputs; review `git diff tests/golden`.
golden: $(STAMP)
	STILLBOX_UPDATE_GOLDEN=1 $(BIN)/python -m pytest -q tests/test_golden.py
	git status --short tests/golden; git diff --stat tests/golden

clean:
	rm -rf $(VENV) $(BENCH_VENV) data/demo-64 data/demo-64-preview.png runs/demo-depthnet .pytest_cache .ruff_cache
