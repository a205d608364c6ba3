"""The application layer: every operation the API offers, free of any transport.

Routers (REST and gRPC) translate requests into these calls and the typed errors of
``geomatch_core.errors`` into statuses. A use case validates everything before it stores or
enqueues anything, so a rejected request leaves no trace. One module per concern (projects,
images, ground control points, jobs, outputs, pair tools, localize; ``views`` what they take and
give, ``base`` what they share);
:class:`Service` is all of them over one set of parts.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .. import auth
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


# LocalizeUseCases first: it builds on ImageUseCases and JobUseCases, which must follow it
class Service(
    LocalizeUseCases,
    ProjectUseCases,
    ImageUseCases,
    GcpUseCases,
    JobUseCases,
    OutputUseCases,
    PairToolUseCases,
):
    def authenticate(self, key: str | None) -> str:
        """The tenant id of an API key (Unauthenticated otherwise), one request of its rate
        (RateLimited past it): every REST request and gRPC call is authenticated once, here."""
        tenant_id = auth.authenticate(self.store, key)
        self.rate.take(tenant_id)
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
