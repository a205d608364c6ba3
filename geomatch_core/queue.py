"""What the application layer needs from a job queue, whatever runs the jobs.

Two implementations: ``workers.celery_queue.CeleryQueue`` (Celery on Redis, ``geomatch worker``
processes) and ``workers.local.LocalQueue`` (threads of the API process: the embedded default).
Steps are named by string so that enqueuing never imports the code that runs them.
"""

from __future__ import annotations

from typing import Any, Protocol

PLAN_MATCH = "geomatch.plan_match"
PLAN_FEATURES = "geomatch.plan_features"  # a chunk of a match job's photos, before its plan
MATCH_PAIR = "geomatch.match_pair"
RECONSTRUCT = "geomatch.reconstruct"
RENDER_PAIR = "geomatch.render_pair"
MATCH_TWO = "geomatch.match_two"  # interactive: two uploaded images, no project (gRPC MatchPair)
LOCALIZE = "geomatch.localize"  # new photos posed against a project's model: one step, one job

# job kind -> its first step
ENTRY_STEP = {"match": PLAN_MATCH, "reconstruct": RECONSTRUCT, "localize": LOCALIZE}


class JobQueue(Protocol):
    def enqueue(self, step: str, *args: Any) -> None:
        """Run ``step(*args)`` at least once, eventually (steps are idempotent)."""

    def call(self, step: str, *args: Any, timeout: float) -> Any:
        """Run an interactive step now and return its result; raises TimeoutError."""

    def ping(self) -> None:
        """Raise if the queue cannot accept work."""

    def slots(self) -> int:
        """Steps the runners take at once, counting what a worker prefetches: a match job keeps
        about this many of its pair steps queued or running (``GEOMATCH_PAIRS_IN_FLIGHT``)."""

    def workers_alive(self) -> int | None:
        """How many worker processes were heard from within their lease; None where the queue
        runs the work itself (embedded), so there is no worker to miss."""

    def close(self) -> None: ...
