# `make demo` and `make test` create .venv and install on first use.
PY ?= python3.11
# the install extras (pyproject.toml): add cuda for JAX on an NVIDIA GPU, e.g.
# `make test EXTRAS=test,cluster,cuda`
EXTRAS ?= test,cluster
# pytest-xdist workers for `make test`: the suite mostly waits on subprocesses and
# realtime episodes, so two share a 2-core machine (tests/conftest.py)
TEST_WORKERS ?= 2
VENV := .venv
BIN := $(VENV)/bin
comma := ,
STAMP := $(VENV)/.installed-$(subst $(comma),-,$(EXTRAS))

.PHONY: demo test lint certs clean native bench-gpu

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV) || python3 -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[$(EXTRAS)]'
	$(BIN)/python -m services.build_native || echo "some native kernels not built: their services use the JAX forms"
	touch $(STAMP)

# the native kernels for the current sources (a no-op when they are built): loading never builds
native: $(STAMP)
	$(BIN)/python -m services.build_native || echo "some native kernels not built: their services use the JAX forms"

demo: native
	$(BIN)/vamppi up --scenario alleyway --controller va --clock lockstep --seed 0

test: native
	$(BIN)/ruff check common services deploy tests
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadgroup --durations=25 tests

# the GPU figures (deploy/bench/gpu.py): a few minutes on a lent GPU machine, with
# EXTRAS=test,cluster,cuda; BENCH_GPU_ARGS=--quick checks it anywhere in a minute or two
bench-gpu: native
	$(BIN)/python -m deploy.bench.gpu --out bench-gpu $(BENCH_GPU_ARGS)

certs: $(STAMP)  # the CA and a certificate per role where vamppi looks (docs/security.md)
	$(BIN)/vamppi certs $${XDG_CONFIG_HOME:-$$HOME/.config}/vamppi/certs

lint: $(STAMP)
	$(BIN)/ruff check common services deploy tests

clean:
	rm -rf $(VENV) build *.egg-info
