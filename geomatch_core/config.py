"""Settings, all read from the environment so that the API, workers and the CLI of one
deployment agree by sharing the same variables (docs/service.md lists them)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path


def _int(name: str, default: int) -> int:
    raw = os.environ.get(name, "").strip()
    if not raw:
        return default
    try:
        return int(raw)
    except ValueError:
        raise ValueError(f"{name}={raw!r}: expected an integer") from None


def _float(name: str, default: float) -> float:
    raw = os.environ.get(name, "").strip()
    if not raw:
        return default
    try:
        return float(raw)
    except ValueError:
        raise ValueError(f"{name}={raw!r}: expected a number") from None


@dataclass(frozen=True)
class Settings:
    home: Path  # GEOMATCH_HOME: every file of the service lives under it
    database_url: str  # DATABASE_URL, default: SQLite file under home
    redis_url: str | None  # REDIS_URL; None = embedded mode (jobs run in the API process)
    redis_prefix: str = "geomatch:"  # GEOMATCH_REDIS_PREFIX: every Redis key (broker included)
    queue: str = "geomatch"  # GEOMATCH_QUEUE: Celery queue of job steps (+ ".interactive")
    max_upload_bytes: int = 200 * 1024 * 1024  # GEOMATCH_MAX_UPLOAD_MB, per file
    # GEOMATCH_MAX_PIXELS: above it an image is a decompression bomb. The default is Pillow's own
    # MAX_IMAGE_PIXELS: the workers' reader (geomatch.imageio) refuses larger images anyway.
    max_pixels: int = 89_478_485
    visibility_timeout_s: int = 3600  # GEOMATCH_VISIBILITY_TIMEOUT: redelivery of a dead worker's task
    lock_timeout_s: int = 120  # GEOMATCH_LOCK_TIMEOUT: a dead writer's lock expires after this
    # GEOMATCH_WORKER_LEASE: a worker not heard from for this long is dead: the steps it held go
    # back to the queue, and /readyz stops counting it
    worker_lease_s: int = 30
    device: str = "auto"  # GEOMATCH_DEVICE: where workers run the networks
    feature_cache_mb: int = 20_000  # GEOMATCH_FEATURE_CACHE_MB: on-disk feature cache cap (0: off)
    # GEOMATCH_CACHE_MB: in-memory caches of one worker thread (features, anchors), all matchers
    # together; features the on-disk cache can reload are cheap to drop
    cache_mb: int = 1536
    embedded_threads: int = 1  # GEOMATCH_EMBEDDED_THREADS: job threads of the embedded runner
    render_timeout_s: int = 120  # GEOMATCH_RENDER_TIMEOUT: how long a matches.png request waits
    grpc_tenant_streams: int = 16  # GEOMATCH_GRPC_TENANT_STREAMS: streaming calls one tenant may hold open
    grpc_stream_idle_s: int = 120  # GEOMATCH_GRPC_STREAM_IDLE: a request stream quiet this long is cut
    # GEOMATCH_GRPC_FIRST_MESSAGE_S: a unary gRPC call (health checks too) whose request message has
    # not come this long after the call opened ends with DEADLINE_EXCEEDED
    grpc_first_message_s: float = 10.0
    # GEOMATCH_MAX_PAIRS_PER_JOB: the most pairs one match job may plan (0: no limit): a larger
    # request is refused before anything is planned, or its job fails before a pair row is written
    max_pairs_per_job: int = 20_000
    # GEOMATCH_MAX_QUEUED_PAIRS: pairs one tenant's unfinished match jobs may hold in all (0: no
    # limit): a match past it is 429 / RESOURCE_EXHAUSTED until some of that work is done
    max_queued_pairs: int = 50_000
    # GEOMATCH_MAX_OPEN_JOBS: unfinished localize and reconstruct jobs one tenant may have (0: no
    # limit): each is minutes of a worker's time, and a flood of them queued every other tenant's
    # work behind it; past it a request is 429 / RESOURCE_EXHAUSTED until some have ended
    max_open_jobs: int = 8
    # GEOMATCH_PAIRS_IN_FLIGHT: pair steps one match job keeps queued or running at once; the next
    # is queued as one ends, so other jobs' steps interleave with a long job's. 0: the runner's
    # own slots (embedded: its threads; Celery: two per live worker, the one it runs and the one
    # it prefetches)
    pairs_in_flight: int = 0
    # GEOMATCH_HEAD_TIMEOUT_S: an HTTP request head (or a new connection's first one) must be in
    # within this many seconds of its first byte (of the connection's opening): 408 and closed
    head_timeout_s: float = 10.0
    # GEOMATCH_MAX_REQUEST_MB: a whole upload request (every file of it, multipart or gRPC stream)
    max_request_bytes: int = 1024 * 1024 * 1024
    max_json_bytes: int = 4 * 1024 * 1024  # GEOMATCH_MAX_JSON_MB: any other request body
    # per tenant; 0 turns a quota off. GEOMATCH_QUOTA_PROJECTS, _IMAGES, _MB (stored image bytes)
    quota_projects: int = 1000
    quota_images: int = 100_000
    quota_bytes: int = 1024 * 1024 * 1024 * 1024
    # GEOMATCH_RATE_LIMIT: requests per second one tenant may make (REST and gRPC together, per
    # API process), GEOMATCH_RATE_BURST: how many it may make at once above that; 0 turns it off
    rate_per_s: float = 50.0
    rate_burst: int = 500
    # GEOMATCH_HEAVY_SLOTS: API-side heavy calls (match pictures, exports, database snapshots, the
    # viewer's scene) running at once in all, GEOMATCH_HEAVY_TENANT_SLOTS: of one tenant
    heavy_slots: int = 8
    heavy_tenant_slots: int = 2
    # GEOMATCH_LOCALIZE_WAIT_S: how long a localize request waits for its job before it answers
    # 202 with the job instead of the poses (a waiting request holds a thread and a heavy slot)
    localize_wait_s: float = 30.0

    @property
    def embedded(self) -> bool:
        return self.redis_url is None

    @classmethod
    def from_env(cls) -> Settings:
        home = Path(os.environ.get("GEOMATCH_HOME", "geomatch-data")).resolve()
        return cls(
            home=home,
            database_url=os.environ.get("DATABASE_URL") or f"sqlite:///{home / 'geomatch.sqlite'}",
            redis_url=os.environ.get("REDIS_URL") or None,
            redis_prefix=os.environ.get("GEOMATCH_REDIS_PREFIX", "geomatch:"),
            queue=os.environ.get("GEOMATCH_QUEUE", "geomatch"),
            max_upload_bytes=_int("GEOMATCH_MAX_UPLOAD_MB", 200) * 1024 * 1024,
            max_pixels=_int("GEOMATCH_MAX_PIXELS", 89_478_485),
            visibility_timeout_s=_int("GEOMATCH_VISIBILITY_TIMEOUT", 3600),
            lock_timeout_s=_int("GEOMATCH_LOCK_TIMEOUT", 120),
            worker_lease_s=max(3, _int("GEOMATCH_WORKER_LEASE", 30)),
            device=os.environ.get("GEOMATCH_DEVICE", "auto"),
            feature_cache_mb=_int("GEOMATCH_FEATURE_CACHE_MB", 20_000),
            cache_mb=max(64, _int("GEOMATCH_CACHE_MB", 1536)),
            embedded_threads=max(1, _int("GEOMATCH_EMBEDDED_THREADS", 1)),
            render_timeout_s=_int("GEOMATCH_RENDER_TIMEOUT", 120),
            grpc_tenant_streams=max(1, _int("GEOMATCH_GRPC_TENANT_STREAMS", 16)),
            grpc_stream_idle_s=max(1, _int("GEOMATCH_GRPC_STREAM_IDLE", 120)),
            grpc_first_message_s=max(0.1, _float("GEOMATCH_GRPC_FIRST_MESSAGE_S", 10.0)),
            max_pairs_per_job=max(0, _int("GEOMATCH_MAX_PAIRS_PER_JOB", 20_000)),
            max_queued_pairs=max(0, _int("GEOMATCH_MAX_QUEUED_PAIRS", 50_000)),
            max_open_jobs=max(0, _int("GEOMATCH_MAX_OPEN_JOBS", 8)),
            pairs_in_flight=max(0, _int("GEOMATCH_PAIRS_IN_FLIGHT", 0)),
            head_timeout_s=max(0.1, _float("GEOMATCH_HEAD_TIMEOUT_S", 10.0)),
            max_request_bytes=max(1, _int("GEOMATCH_MAX_REQUEST_MB", 1024)) * 1024 * 1024,
            max_json_bytes=max(1, _int("GEOMATCH_MAX_JSON_MB", 4)) * 1024 * 1024,
            quota_projects=max(0, _int("GEOMATCH_QUOTA_PROJECTS", 1000)),
            quota_images=max(0, _int("GEOMATCH_QUOTA_IMAGES", 100_000)),
            quota_bytes=max(0, _int("GEOMATCH_QUOTA_MB", 1024 * 1024)) * 1024 * 1024,
            rate_per_s=max(0.0, _float("GEOMATCH_RATE_LIMIT", 50.0)),
            rate_burst=max(1, _int("GEOMATCH_RATE_BURST", 500)),
            heavy_slots=max(1, _int("GEOMATCH_HEAVY_SLOTS", 8)),
            heavy_tenant_slots=max(1, _int("GEOMATCH_HEAVY_TENANT_SLOTS", 2)),
            localize_wait_s=max(0.0, _float("GEOMATCH_LOCALIZE_WAIT_S", 30.0)),
        )
