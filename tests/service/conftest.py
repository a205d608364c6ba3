"""Fixtures of the service tests: one synthetic scene and one Redis-backed deployment (API
server + one worker) for the whole session; tests that kill or replace processes make their own."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from geomatch.synth.aerial import write_scene

from .harness import Deployment, deployed
from .image_harness import IMAGE_ENV, ImageDeployment

SCENE_SEED = 1  # the scene of tests/test_pipeline_e2e.py: 2 aerial + 4 ground, 640x480
# every image carries a GPS fix (and the drones their noisy heights), as a phone's and a drone's
# photos do: the service's match and reconstruct jobs then take the GPS path end to end. The renders
# are the same bit for bit as without (synth: the noise has its own generator)
SCENE_GPS_NOISE = 0.5


@pytest.fixture(scope="session")
def redis_url() -> str:
    import redis

    url = os.environ.get("REDIS_URL", "redis://127.0.0.1:6379/0")
    try:
        redis.Redis.from_url(url, socket_connect_timeout=2).ping()
    except redis.RedisError as e:
        pytest.fail(f"no Redis at {url} ({e}); `make test` starts one (tests/service/ensure_redis.py)")
    return url


@pytest.fixture(scope="session")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("service-scene")
    write_scene(d, 2, 4, seed=SCENE_SEED, gps_noise=SCENE_GPS_NOISE)
    return d


@pytest.fixture(scope="session")
def deployment(tmp_path_factory: pytest.TempPathFactory, redis_url: str) -> Iterator[Deployment]:
    """Redis mode: `geomatch serve` + one `geomatch worker`. Uploads are capped at 2 MiB so the
    size limit can be tested with small files. With GEOMATCH_TEST_IMAGE set (`make image`), both
    run from that built image (image_harness.py), so the tests using this fixture test the image."""
    root = tmp_path_factory.mktemp("deployment")
    image = os.environ.get(IMAGE_ENV)
    d = (
        ImageDeployment(root, redis_url, image, GEOMATCH_MAX_UPLOAD_MB="2")
        if image
        else Deployment(root, redis_url, GEOMATCH_MAX_UPLOAD_MB="2")
    )
    with deployed(d) as running:
        yield running


@pytest.fixture(scope="session")
def key_a(deployment: Deployment) -> str:
    return deployment.create_key("tenant-a")


@pytest.fixture(scope="session")
def key_b(deployment: Deployment) -> str:
    return deployment.create_key("tenant-b")
