#!/usr/bin/env bash
# `make image`: build the real image from the real Dockerfile without a Docker engine or a registry,
# then run it. Where neither Docker Hub nor download.pytorch.org can be reached, buildah (rootful,
# vfs storage, chroot isolation: no daemon, no cgroups, no overlay mounts) builds and runs it:
#
#   1. base: a debootstrap of Debian bookworm (Python 3.11, venv, CA certificates, passwd) committed
#      as a local image, standing in for python:3.11-slim-bookworm (the Dockerfile's PYTHON_IMAGE);
#      made once, reused while it exists (BASE_REBUILD=1 makes it again);
#   2. image: `buildah build` of Dockerfile with that base and torch from wheels/ (TORCH_WHEEL), the
#      rest from PyPI; its build runs docker/selfcheck.py (a real match with the real weights);
#   3. run: tests/service/test_image.py (the image's config, the self-check again in a container of
#      it, the health check inside it against a running `serve` and `worker`, a REST flow) and
#      tests/service/test_e2e.py, with `geomatch serve` / `geomatch worker` run from the image over
#      loopback against the host's Redis (GEOMATCH_TEST_IMAGE, tests/service/harness.py).
#
# Times and the image size are printed at the end and kept in $WORK/report.txt.
# Settings (environment): IMAGE, BASE_IMAGE, TORCH_WHEEL_PATH, DEBIAN_MIRROR, WORK, STORAGE_DRIVER,
# BUILD_CA_DIR, PYTHON (the test runner's interpreter), SKIP_TESTS=1 (build only), BASE_REBUILD=1.
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
IMAGE=${IMAGE:-localhost/geomatch:cpu}
BASE_IMAGE=${BASE_IMAGE:-localhost/geomatch-base:bookworm}
TORCH_WHEEL_PATH=${TORCH_WHEEL_PATH:-/opt/wheels/torch-2.13.0+cpu-cp311-cp311-manylinux_2_28_x86_64.whl}
DEBIAN_MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
WORK=${WORK:-/var/tmp/geomatch-image}
export STORAGE_DRIVER=${STORAGE_DRIVER:-vfs}  # passed as --storage-driver (buildah 1.28 ignores the variable)
BUILD_CA_DIR=${BUILD_CA_DIR-/etc/ssl/certs}  # empty: the image's own CA certificates only
PYTHON=${PYTHON:-python3}
NICE=(nice -n 10)  # the build shares the machine: a lower priority for its heavy steps

die() { echo "build_local.sh: $*" >&2; exit 1; }
bah() { buildah --storage-driver "$STORAGE_DRIVER" "$@"; }
now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.0f", b - a }'; }

command -v buildah >/dev/null || die "buildah is not installed (apt-get install buildah debootstrap)"
[ "$(id -u)" = 0 ] || die "run as root: debootstrap and rootful buildah (vfs, chroot isolation)"
[ -f "$TORCH_WHEEL_PATH" ] || die "no torch wheel at $TORCH_WHEEL_PATH (set TORCH_WHEEL_PATH)"
mkdir -p "$WORK"
REPORT="$WORK/report.txt"
: > "$REPORT"
note() { echo "$*" | tee -a "$REPORT"; }

# -- 1. the base image ------------------------------------------------------------------------------
if [ "${BASE_REBUILD:-0}" != 1 ] && bah inspect --type image "$BASE_IMAGE" >/dev/null 2>&1; then
    note "base: $BASE_IMAGE exists, reused (BASE_REBUILD=1 makes it again)"
else
    command -v debootstrap >/dev/null || die "debootstrap is not installed (apt-get install debootstrap)"
    t0=$(now)
    rootfs="$WORK/rootfs"
    rm -rf "$rootfs"
    # minbase: dpkg, apt and the Essential set; python3-venv brings ensurepip (the Dockerfile's
    # `python -m venv`), passwd groupadd/useradd (its runtime user), ca-certificates pip's HTTPS.
    "${NICE[@]}" debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates,passwd \
        bookworm "$rootfs" "$DEBIAN_MIRROR" > "$WORK/debootstrap.log" 2>&1 \
        || { tail -20 "$WORK/debootstrap.log"; die "debootstrap failed (log: $WORK/debootstrap.log)"; }
    # the Dockerfile calls `python`, as in python:3.11-slim (where it is /usr/local/bin/python)
    ln -sf /usr/bin/python3 "$rootfs/usr/local/bin/python"
    rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
    ctr=$(bah from scratch)
    mnt=$(bah mount "$ctr")
    cp -a "$rootfs/." "$mnt/"
    bah umount "$ctr" >/dev/null
    bah config --env PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
        --env LANG=C.UTF-8 --cmd python3 --label org.opencontainers.image.title=geomatch-base "$ctr"
    bah commit --rm "$ctr" "$BASE_IMAGE" >/dev/null
    rm -rf "$rootfs"
    note "base: $BASE_IMAGE built in $(since "$t0") s (debootstrap bookworm minbase + python3)"
fi
note "base size: $(bah images --format '{{.Size}}' "$BASE_IMAGE" | head -1)"

# -- 2. the image, from the real Dockerfile ---------------------------------------------------------
wheel=$(basename "$TORCH_WHEEL_PATH")
mkdir -p "$ROOT/wheels"
cmp -s "$TORCH_WHEEL_PATH" "$ROOT/wheels/$wheel" || cp "$TORCH_WHEEL_PATH" "$ROOT/wheels/$wheel"
t0=$(now)
# --format docker keeps HEALTHCHECK (OCI has no such field); --layers caches the steps for rebuilds.
# The build's RUN steps see the host's CA certificates (BUILD_CA_DIR, read-only, never committed):
# where HTTPS to PyPI passes a TLS-inspecting proxy, its CA is in the host's trust store only, and
# Debian's pip (the venv's, from ensurepip) verifies against /etc/ssl/certs/ca-certificates.crt.
ca_mount=()
[ -n "$BUILD_CA_DIR" ] && ca_mount=(--volume "$BUILD_CA_DIR:/etc/ssl/certs:ro")
# HEALTHCHECK --start-interval (Docker Engine 25+) is unknown to older buildah (1.28, Debian
# bookworm's, fails the build on it). Where a probe build rejects it, the image is built from a copy
# of Dockerfile without that one flag: its health check then polls at --interval while starting
# (as under older Docker engines); every other line is the real Dockerfile's.
dockerfile="$ROOT/Dockerfile"
probe=$(mktemp -d)
printf 'FROM scratch\nHEALTHCHECK --start-interval=2s CMD ["true"]\n' > "$probe/Dockerfile"
if bah build --isolation chroot --format docker --iidfile "$probe/iid" "$probe" > "$probe/log" 2>&1; then
    bah rmi "$(cat "$probe/iid")" > /dev/null 2>&1 || true
else
    dockerfile="$WORK/Dockerfile.no-start-interval"
    sed -E 's/ --start-interval=[^ ]+//' "$ROOT/Dockerfile" > "$dockerfile"
    note "buildah $(buildah --version | awk '{print $3}') rejects HEALTHCHECK --start-interval: built from $dockerfile (Dockerfile without that flag)"
fi
rm -rf "$probe"
"${NICE[@]}" buildah --storage-driver "$STORAGE_DRIVER" build --isolation chroot --format docker \
    --layers --pull=never "${ca_mount[@]}" \
    --build-arg PYTHON_IMAGE="$BASE_IMAGE" --build-arg TORCH_WHEEL="$wheel" \
    -t "$IMAGE" -f "$dockerfile" "$ROOT" 2>&1 | tee "$WORK/build.log"
note "image: $IMAGE built in $(since "$t0") s"
note "image size: $(bah images --format '{{.Size}}' "$IMAGE" | head -1)"
grep -E "^selfcheck|^ok|selfcheck" "$WORK/build.log" | tail -3 | sed 's/^/build-time /' | tee -a "$REPORT" || true

# -- 3. run it --------------------------------------------------------------------------------------
if [ "${SKIP_TESTS:-0}" = 1 ]; then
    note "tests skipped (SKIP_TESTS=1)"
else
    t0=$(now)
    cd "$ROOT"
    "$PYTHON" tests/service/ensure_redis.py
    GEOMATCH_TEST_IMAGE="$IMAGE" "$PYTHON" -m pytest -q -p no:cacheprovider \
        tests/service/test_image.py tests/service/test_e2e.py 2>&1 | tee "$WORK/tests.log"
    status=${PIPESTATUS[0]}
    note "image tests (test_image.py + test_e2e.py against the image): $(tail -1 "$WORK/tests.log") in $(since "$t0") s"
    [ "$status" = 0 ] || die "the tests against the image failed (log: $WORK/tests.log)"
fi
echo "--- $REPORT"
cat "$REPORT"
