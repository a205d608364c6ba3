"""The application layer: every operation the API offers, free of any transport.

Routers (REST and gRPC) translate requests into these calls and the typed errors of
``geomatch_core.errors`` into statuses. A use case validates everything before it stores or
enqueues anything, so a rejected request leaves no trace. One module per concern (projects,
images, ground control points, jobs, outputs, pair tools, localize; ``views`` what they take and
give, ``base`` what they share); :class:`Service` holds one object per concern over one
:class:`~.base.Context`, so callers name the concern: ``service.jobs.start_match(...)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from geomatch_core.config import Settings
from geomatch_core.locks import LockFactory
from geomatch_core.queue import JobQueue
from geomatch_core.storage import Storage
from geomatch_core.store import MetadataStore

from .. import auth
from .base import Context
from .gcp import GcpUseCases
from .images import ImageUseCases
from .jobs import JobUseCases
from .localize import LocalizeUseCases
from .outputs import OutputUseCases
from .pairtools import PairToolUseCases
from .projects import ProjectUseCases


@dataclass
class Readiness:
    """``ok``: the service can take work and get it done. ``serving``: the server's own parts answer
    (database, queue, storage); in queue mode a server can serve and not be ok, with no worker alive:
    jobs would be accepted and wait in the queue, which is what a router of traffic must hear."""

    ok: bool
    checks: dict[str, str] = field(default_factory=dict)
    serving: bool = True


class Service:
    """The use cases of every concern, one object each, over one context: a request's transport
    picks the concern (``service.images.upload_images``, ``service.localize.localize``)."""

    def __init__(
        self,
        settings: Settings,
        store: MetadataStore,
        storage: Storage,
        queue: JobQueue,
        locks: LockFactory,
    ) -> None:
        self.ctx = Context(settings, store, storage, queue, locks)
        self.projects = ProjectUseCases(self.ctx)
        self.images = ImageUseCases(self.ctx)
        self.gcp = GcpUseCases(self.ctx)
        self.jobs = JobUseCases(self.ctx)
        self.outputs = OutputUseCases(self.ctx)
        self.pairtools = PairToolUseCases(self.ctx)
        self.localize = LocalizeUseCases(self.ctx, self.images, self.jobs)

    # the parts the transports and the composition root read (limits, closing, the embedded key)
    @property
    def settings(self) -> Settings:
        return self.ctx.settings

    @property
    def store(self) -> MetadataStore:
        return self.ctx.store

    @property
    def storage(self) -> Storage:
        return self.ctx.storage

    @property
    def queue(self) -> JobQueue:
        return self.ctx.queue

    def authenticate(self, key: str | None) -> str:
        """The tenant id of an API key (Unauthenticated otherwise), one request of its rate
        (RateLimited past it): every REST request and gRPC call is authenticated once, here."""
        tenant_id = auth.authenticate(self.store, key)
        self.ctx.rate.take(tenant_id)
        return tenant_id

    def readiness(self) -> Readiness:
        r = Readiness(ok=True)
        for name, check in (
            ("database", self.store.ping),
            ("queue", self.queue.ping),
            ("storage", self.storage.check_writable),
        ):
            try:
                check()
                r.checks[name] = "ok"
            except Exception as e:
                r.ok = r.serving = False
                r.checks[name] = f"error: {e}"
        r.checks["mode"] = "embedded" if self.settings.embedded else "redis"
        if r.checks["queue"] == "ok":
            self._check_workers(r)
        return r

    def _check_workers(self, r: Readiness) -> None:
        """Queue mode: at least one worker heard from within its lease (GEOMATCH_WORKER_LEASE)."""
        try:
            alive = self.queue.workers_alive()
        except Exception as e:
            r.ok = False
            r.checks["workers"] = f"error: {e}"
            return
        if alive is None:  # embedded: the API runs the steps itself
            return
        if alive:
            r.checks["workers"] = "ok"
        else:
            r.ok = False
            r.checks["workers"] = f"error: no worker heard from in the last {self.settings.worker_lease_s} s"
