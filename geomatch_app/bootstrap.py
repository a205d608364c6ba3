"""The composition root: settings -> store, storage, queue and locks -> the Service.

REDIS_URL decides the mode: set, jobs go to Celery and writers lock in Redis; unset (the
embedded default), jobs run on threads of this process and writers lock with files.
"""

from __future__ import annotations

from geomatch_core.config import Settings
from geomatch_core.locks import FileLocks, RedisLocks
from geomatch_core.storage import Storage
from geomatch_core.store import MetadataStore
from service.usecases import Service


def build_service(settings: Settings) -> Service:
    store = MetadataStore(settings.database_url)
    store.create_all()
    storage = Storage(settings.home)
    storage.ensure()
    if settings.embedded:
        from workers.local import LocalQueue

        locks = FileLocks(storage.writer_lock_path)
        queue = LocalQueue(settings, store, storage, locks)
        queue.resume()
        return Service(settings, store, storage, queue, locks)
    import redis

    from workers.celery_queue import CeleryQueue

    assert settings.redis_url is not None
    client = redis.Redis.from_url(settings.redis_url)
    redis_locks = RedisLocks(client, settings.redis_prefix, settings.lock_timeout_s)
    return Service(settings, store, storage, CeleryQueue(settings), redis_locks)


def close_service(service: Service) -> None:
    service.queue.close()
    service.store.dispose()
