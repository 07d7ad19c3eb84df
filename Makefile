# `make demo` and `make test` create .venv and install on first use.
PY ?= python3.11
# the install extras (pyproject.toml): add cuda for JAX on an NVIDIA GPU, e.g.
# `make test EXTRAS=test,cluster,cuda`
EXTRAS ?= test,cluster
# pytest-xdist workers for `make test`: two keep a 2-core machine busy (vmstat: 0-2 % idle;
# tests/conftest.py); the tests marked realtime run after them one at a time, since a
# realtime pipeline (some 1.3 cores) beside a lockstep one running flat out falls behind the
# wall clock and brakes on stale perception
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
	own=; [ -n "$$VAMPPI_JAX_CACHE" ] || { own=$$(mktemp -d); export VAMPPI_JAX_CACHE=$$own; }; \
	failed=0; \
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadgroup --durations=25 \
		-m "not realtime" tests || failed=1; \
	$(BIN)/python -m pytest -q --durations=10 -m realtime tests || failed=1; \
	[ -z "$$own" ] || rm -rf "$$own"; exit $$failed

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
